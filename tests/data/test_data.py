"""Input validation (construction and add_observations), rating boundaries, data helpers."""

import warnings

import pytest
import torch
from gpytorch.kernels import RBFKernel, ScaleKernel

from torchpref.data.preference_data import (
    PreferenceData,
    RatingBoundaryWarning,
    best_of_m,
    likert_to_unit,
    prepare_ratings,
    unit_to_likert,
)
from torchpref.models.preference_gp import PreferenceGP
from torchpref.testing import rand

F64 = torch.float64


def kernel():
    k = ScaleKernel(RBFKernel(ard_num_dims=2)).to(F64)
    k.base_kernel.lengthscale = 0.4
    return k


@pytest.fixture
def data(generator):
    X = rand(5, 2, generator=generator)
    C = torch.tensor([[0, 1], [2, 3], [4, 0]])
    u = torch.tensor([0.2, 0.8], dtype=F64)
    ri = torch.tensor([1, 3])
    return X, C, u, ri


BAD = [
    ("rating above 1", dict(ratings=torch.tensor([0.2, 1.5], dtype=F64)), "ratings must lie in"),
    ("negative rating", dict(ratings=torch.tensor([-0.1, 0.5], dtype=F64)), "ratings must lie in"),
    ("NaN rating", dict(ratings=torch.tensor([float("nan"), 0.5], dtype=F64)), "ratings must be finite"),
    ("inf rating", dict(ratings=torch.tensor([float("inf"), 0.5], dtype=F64)), "ratings must be finite"),
    ("NaN in X", dict(X_nan=True), "train_X must be finite"),
    ("index out of range", dict(comparisons=torch.tensor([[0, 5]])), "out of range"),
    ("negative index", dict(comparisons=torch.tensor([[-1, 2]])), "out of range"),
    ("self comparison", dict(comparisons=torch.tensor([[2, 2]])), "compared with itself"),
    ("comparisons not p x 2", dict(comparisons=torch.tensor([[0, 1, 2]])), "p x 2"),
    ("comparisons 1-D", dict(comparisons=torch.tensor([0, 1])), "p x 2"),
    ("rating index out of range", dict(rating_index=torch.tensor([1, 7])), "rating_index out of range"),
    ("length mismatch", dict(rating_index=torch.tensor([1, 2, 3])), "same length"),
    ("ratings without index", dict(rating_index=None), "together"),
]


@pytest.mark.parametrize("name,change,match", BAD, ids=[b[0] for b in BAD])
def test_bad_input_at_construction(data, name, change, match):
    X, C, u, ri = data
    args = dict(comparisons=C, ratings=u, rating_index=ri)
    args.update({k: v for k, v in change.items() if k != "X_nan"})
    if change.get("X_nan"):
        X = X.clone()
        X[1, 1] = float("nan")
    with pytest.raises(ValueError, match=match):
        PreferenceGP(X, covar_module=kernel(), **args)


def test_bad_dimensions_at_construction(data):
    X, C, u, ri = data
    with pytest.raises(ValueError, match="n x d"):
        PreferenceGP(X[:, 0], comparisons=C)
    with pytest.raises(ValueError, match="finite"):
        PreferenceGP(torch.full((3, 2), float("inf"), dtype=F64))


ADD_BAD = [
    ("rating above 1", dict(ratings=torch.tensor([1.2], dtype=F64), rating_index=torch.tensor([0])), "ratings"),
    ("NaN rating", dict(ratings=torch.tensor([float("nan")], dtype=F64), rating_index=torch.tensor([0])), "finite"),
    ("index out of range", dict(comparisons=torch.tensor([[0, 9]])), "out of range"),
    ("negative index", dict(comparisons=torch.tensor([[0, -2]])), "out of range"),
    ("self comparison", dict(comparisons=torch.tensor([[3, 3]])), "itself"),
    ("not p x 2", dict(comparisons=torch.tensor([[0, 1, 2], [1, 2, 3]])), "p x 2"),
    (
        "length mismatch",
        dict(ratings=torch.tensor([0.3, 0.4], dtype=F64), rating_index=torch.tensor([0])),
        "same length",
    ),
    ("wrong X dimension", dict(X=torch.zeros(2, 3, dtype=F64), comparisons=torch.tensor([[0, 1]])), "m x 2"),
    ("NaN in X", dict(X=torch.tensor([[0.1, float("nan")]], dtype=F64)), "finite"),
    (
        "index beyond new X",
        dict(X=torch.tensor([[0.1, 0.2], [0.3, 0.4]], dtype=F64), comparisons=torch.tensor([[0, 2]])),
        "out of range",
    ),
    (
        "duplicate rows compared",
        dict(X=torch.tensor([[0.1, 0.2], [0.1, 0.2]], dtype=F64), comparisons=torch.tensor([[0, 1]])),
        "itself",
    ),
]


@pytest.mark.parametrize("name,kwargs,match", ADD_BAD, ids=[b[0] for b in ADD_BAD])
def test_failed_add_observations_leaves_model_unchanged(data, generator, name, kwargs, match):
    X, C, u, ri = data
    model = PreferenceGP(X, C, u, ri, covar_module=kernel())
    Xs = rand(4, 2, generator=generator)
    before = model.posterior(Xs)
    snapshot = [t.clone() for t in (model.train_X, model.comparisons, model.ratings, model.rating_index)]
    data_obj, cache = model.data, model._cache
    with pytest.raises(ValueError, match=match):
        model.add_observations(**kwargs)
    for old, new in zip(snapshot, (model.train_X, model.comparisons, model.ratings, model.rating_index)):
        assert torch.equal(old, new)
    assert model.data is data_obj and model._cache is cache
    after = model.posterior(Xs)
    assert torch.equal(before.mean, after.mean) and torch.equal(before.variance, after.variance)


def test_ratings_at_boundaries_move_to_eps(data):
    X, C, _, _ = data
    with pytest.warns(RatingBoundaryWarning, match="moved in"):
        model = PreferenceGP(
            X,
            C,
            torch.tensor([0.0, 1.0, 0.5], dtype=F64),
            torch.tensor([0, 1, 2]),
            covar_module=kernel(),
            rating_eps=1e-2,
        )
    torch.testing.assert_close(model.ratings, torch.tensor([1e-2, 1 - 1e-2, 0.5], dtype=F64), rtol=0, atol=0)
    assert model.mode.converged and torch.isfinite(model.log_marginal_likelihood())
    with pytest.warns(RatingBoundaryWarning):
        model.add_observations(ratings=torch.tensor([1.0], dtype=F64), rating_index=torch.tensor([4]))
    assert float(model.ratings[-1]) == 1 - 1e-2
    # interior values are used exactly as given, with no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = prepare_ratings([1e-9, 0.3, 1 - 1e-9])
    torch.testing.assert_close(r, torch.tensor([1e-9, 0.3, 1 - 1e-9], dtype=F64), rtol=0, atol=0)
    with pytest.raises(ValueError, match="rating_eps"):
        prepare_ratings([0.5], eps=0.7)


def test_best_of_m():
    C = best_of_m(7, [3, 7, 1, 9])
    assert C.dtype == torch.long
    assert C.tolist() == [[7, 3], [7, 1], [7, 9]]
    assert best_of_m(2, torch.tensor([2, 5])).tolist() == [[2, 5]]
    with pytest.raises(ValueError, match="not among"):
        best_of_m(4, [1, 2, 3])
    with pytest.raises(ValueError, match="distinct"):
        best_of_m(1, [1, 2, 2])
    with pytest.raises(ValueError, match="at least 2"):
        best_of_m(1, [1])


@pytest.mark.parametrize(
    "chosen, shown, match",
    [
        (1.5, [0, 1, 2], r"chosen must hold integer indices, got \[1.5\]"),  # was truncated to 1
        (True, [0, 1, 2], "chosen must hold integer indices, got a bool"),
        ("1", [0, 1, 2], "chosen must hold integer indices, got str"),
        (None, [0, 1], "chosen must hold integer indices"),
        ([0, 1], [0, 1, 2], "chosen must be one item index"),
        (1, [0.0, 1.5, 2.0], r"shown must hold integer indices, got \[0.0, 1.5, 2.0\]"),  # was [0, 1, 2]
        (1, "012", "shown must hold integer indices, got str"),
    ],
)
def test_best_of_m_refuses_what_is_not_an_item_index(chosen, shown, match):
    with pytest.raises(ValueError, match=match):
        best_of_m(chosen, shown)
    assert best_of_m(1.0, torch.tensor([0.0, 1.0])).tolist() == [[1, 0]]  # whole floats are indices


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: likert_to_unit([1, 2], num_levels=2.5), "num_levels must be an integer"),
        (lambda: likert_to_unit([1, 2], num_levels="5"), "num_levels must be an integer"),
        (lambda: likert_to_unit([True]), "levels must hold numbers, got a bool"),
        (lambda: likert_to_unit(["3"]), "levels must hold numbers, got list"),
        (lambda: unit_to_likert([float("nan")]), "values must be finite"),  # was -9223372036854775807
        (lambda: unit_to_likert([1.5]), r"values must lie in \[0, 1\], got \[1.5\]"),
        (lambda: prepare_ratings([True, False]), "ratings must hold numbers, got a bool"),
        (lambda: PreferenceData.create(None), "train_X must hold numbers, got NoneType"),
        (lambda: PreferenceData.create("abc"), "train_X must hold numbers, got str"),
        (lambda: PreferenceData.create(torch.ones(3, 2, dtype=torch.bool)), "train_X must hold numbers, got a bool"),
        (lambda: PreferenceData.create(torch.rand(3, 2, dtype=torch.complex128)), "train_X must hold real numbers"),
        (
            lambda: PreferenceData.create(torch.rand(3, 2, dtype=F64), torch.tensor([[0.0, 1e30]], dtype=F64)),
            r"comparisons must hold integer indices, got \[1e\+30\]",
        ),  # named the wrapped long before
    ],
)
def test_helpers_name_what_is_not_a_number_or_index(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_likert_to_unit_both_modes():
    levels = torch.arange(1, 6)
    centre = likert_to_unit(levels)
    torch.testing.assert_close(centre, torch.tensor([0.1, 0.3, 0.5, 0.7, 0.9], dtype=F64))
    assert centre.dtype == F64
    torch.testing.assert_close(
        likert_to_unit(levels, mode="linear"), torch.tensor([0.0, 0.25, 0.5, 0.75, 1.0], dtype=F64)
    )
    torch.testing.assert_close(likert_to_unit([1, 7], num_levels=7), torch.tensor([0.5 / 7, 6.5 / 7], dtype=F64))
    assert unit_to_likert(centre).tolist() == [1, 2, 3, 4, 5]
    for bad in ([0], [6], [2.5], [float("nan")]):
        with pytest.raises(ValueError):
            likert_to_unit(bad)
    with pytest.raises(ValueError, match="mode"):
        likert_to_unit([1], mode="ends")
    # the linear map's end points are moved in (with a warning) when used as ratings
    with pytest.warns(RatingBoundaryWarning):
        r = prepare_ratings(likert_to_unit(levels, mode="linear"))
    assert 0 < float(r.min()) and float(r.max()) < 1


def test_index_items_reuses_duplicates(generator):
    X = rand(3, 2, generator=generator)
    d = PreferenceData.create(X)
    new = torch.stack([X[1], torch.tensor([0.5, 0.5], dtype=F64), X[1], torch.tensor([0.5, 0.5], dtype=F64)])
    d2, idx = d.index_items(new)
    assert idx.tolist() == [1, 3, 1, 3]
    assert d2.n == 4 and d.n == 3  # immutable: the original is unchanged
    torch.testing.assert_close(d2.train_X[3], torch.tensor([0.5, 0.5], dtype=F64))
    _, idx = d.index_items(X[2] + 1e-9, atol=1e-6)
    assert idx.tolist() == [2]


def test_python_floats_become_float64():
    d = PreferenceData.create([[0.1, 0.2], [0.3, 0.4]], comparisons=[[0, 1]], ratings=[0.5], rating_index=[1])
    assert d.train_X.dtype == F64 and d.ratings.dtype == F64 and d.comparisons.dtype == torch.long
    # exactly, not through float32
    assert float(d.ratings[0]) == 0.5 and float(d.train_X[0, 0]) == 0.1 and float(d.train_X[1, 1]) == 0.4
    assert float(prepare_ratings([0.1])[0]) == 0.1
    assert float(likert_to_unit(3, num_levels=5)) == 0.5
