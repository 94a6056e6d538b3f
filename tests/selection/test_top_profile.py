"""The top-set rating profile's variance reduction: its Monte Carlo estimate against quadrature
on a grid, its bias correction, what a rating of a sure top item buys, and the selector's
choices in cases checked by hand."""

import math

import pytest
import torch
from test_variance_reduction import _line, _model  # the same hand-checked cases

from torchpref import BatchedPreferenceGP, PreferenceGP
from torchpref.acquisition.functions import rating_bin_probabilities
from torchpref.data.queries import RankingQuery, RatingQuery
from torchpref.models.kernels import fixed_rbf_kernel
from torchpref.selection.top_profile import ProfileVariancePerEffort, profile_variance_reduction, top_profile

D = torch.float64
MEAN = torch.tensor([0.3, 0.0], dtype=D)
COV = torch.tensor([[0.5, 0.2], [0.2, 0.4]], dtype=D)


def _lik(**kw):
    X = torch.zeros(2, 1, dtype=D)
    settings = dict(comparison_noise=0.2, rating_scale=0.8, rating_precision=30.0)
    settings.update(kw)
    return PreferenceGP(X, torch.tensor([[0, 1]]), covar_module=fixed_rbf_kernel(0.1, 1.0, X), **settings).likelihood


def _answers(F, kind, lik):
    """``... x Y`` answer probabilities at utilities ``F`` (``... x 2``)."""
    if kind == "pair":  # P(item 0 preferred) = Phi((f0 - f1) / (sqrt 2 sigma_R))
        p = torch.special.ndtr((F[..., 0] - F[..., 1]) / (math.sqrt(2) * 0.2))
        return torch.stack([p, 1 - p], -1)
    return rating_bin_probabilities(F[..., 0], lik.rating, 10)  # a binned rating of item 0


def _grid_reduction(kind, lik, n=801, clipped=False):
    """``sum_i Var(v_i) - E_y Var(v_i | y)`` for the top-1 profile of N(MEAN, COV), by a
    midpoint rule on a grid of whitened coordinates (+-7 sd)."""
    z = torch.linspace(-7, 7, n, dtype=D)
    Z = torch.stack(torch.meshgrid(z, z, indexing="ij"), -1).reshape(-1, 2)
    F = MEAN + Z @ torch.linalg.cholesky(COV).T
    w = torch.exp(-0.5 * (Z * Z).sum(-1))
    w = w / w.sum()
    V = top_profile(F.unsqueeze(0), 1, lik.rating, clipped)[0]  # n^2 x 2
    P = _answers(F, kind, lik)  # n^2 x Y

    def var(weights):
        weights = weights / weights.sum()
        m = weights @ V
        return (weights @ (V - m) ** 2).sum()

    return float(var(w) - sum((w * P[:, y]).sum() * var(w * P[:, y]) for y in range(P.shape[1])))


def _samples(S, seed):
    g = torch.Generator().manual_seed(seed)
    return MEAN + torch.randn(S, 2, generator=g, dtype=D) @ torch.linalg.cholesky(COV).T


@pytest.mark.parametrize("clipped", [False, True])
@pytest.mark.parametrize("kind", ["pair", "rating"])
def test_reduction_matches_quadrature(kind, clipped):
    """With many samples the estimate is the expected reduction of the profile's variance under
    the exact posterior given each answer (Bayes' rule on a grid), to Monte Carlo error."""
    lik = _lik()
    want = _grid_reduction(kind, lik, clipped=clipped)
    F = _samples(200_000, 0)
    V = top_profile(F.unsqueeze(0), 1, lik.rating, clipped)
    got = float(profile_variance_reduction(_answers(F, kind, lik).reshape(1, 1, *F.shape[:1], -1), V))
    assert want > 1e-3
    assert got == pytest.approx(want, rel=0.03)


def test_bias_correction():
    """An answer that depends on something independent of f (probabilities drawn at random per
    sample) is worth 0: the plug-in estimate says more on average, the corrected one does not;
    a real answer's corrected estimate, averaged over draws of few samples, is the truth (grid)."""
    lik = _lik()
    g = torch.Generator().manual_seed(2)
    F = _samples(256 * 300, 1).reshape(300, 256, 2)  # 300 draws of 256 samples (the selector's number)
    V = top_profile(F, 1, lik.rating)
    P = torch.softmax(2 * torch.randn(300, 1, 256, 10, generator=g, dtype=D), -1)
    plain = profile_variance_reduction(P, V, bias_correction=False)
    corrected = profile_variance_reduction(P, V)
    assert float(plain.mean()) > 5 * float(plain.std()) / math.sqrt(300)
    assert abs(float(corrected.mean())) < 3 * float(corrected.std()) / math.sqrt(300)
    assert abs(float(corrected.mean())) < 0.05 * float(plain.mean())  # what is left is O(1 / S^2)
    # a real answer (a binned rating of item 0), 400 draws of 64 samples: unbiased to noise
    F = _samples(64 * 400, 7).reshape(400, 64, 2)
    est = profile_variance_reduction(_answers(F, "rating", lik).unsqueeze(1), top_profile(F, 1, lik.rating))
    assert float(est.mean()) == pytest.approx(_grid_reduction("rating", lik), abs=3 * float(est.std()) / 20)


def test_a_rating_of_a_sure_top_item_reduces_its_level_term():
    """Item 0 is surely the best (top 1): its profile is its rating r(f_0), whose variance a
    precise rating of it mostly removes (binned in tenths of the scale); a rating of an
    independent non-member buys nothing."""
    lik = _lik(rating_precision=200.0)
    g = torch.Generator().manual_seed(3)
    S = 4000
    F = torch.stack(
        [1.0 + 0.5 * torch.randn(S, generator=g, dtype=D), -2.0 + 0.3 * torch.randn(S, generator=g, dtype=D)], -1
    ).unsqueeze(0)
    V = top_profile(F, 1, lik.rating)
    assert bool((V[..., 0] > 0).all()) and bool((V[..., 1] == 0).all())
    level_var = float(V[0, :, 0].var())
    P = torch.stack([rating_bin_probabilities(F[0, :, i], lik.rating, 10) for i in range(2)]).unsqueeze(0)
    red = profile_variance_reduction(P, V)[0]
    assert float(red[0]) > 0.5 * level_var
    assert abs(float(red[1])) < 0.02 * level_var


def test_costs_decide():
    """Items whose level is known from ratings, their order not (the case checked by hand in
    test_variance_reduction.py gets a ranking): with rankings very expensive, a rating."""
    X = _line()
    model = _model(
        X, ratings=torch.full((24,), 0.7, dtype=D), rating_index=torch.arange(8).repeat(3), comparison_noise=0.05
    )
    sel = ProfileVariancePerEffort(m=4, ranking_cost=1e3)
    assert isinstance(sel.select(model, X, None, 0, 10, torch.Generator().manual_seed(0)), RatingQuery)


def test_batch_matches_single_trials():
    g = torch.Generator().manual_seed(5)
    X = torch.rand(12, 2, generator=g, dtype=D)
    models = [
        _model(X, torch.tensor([[0, 1], [2, 3]])),
        _model(X, torch.tensor([[4, 1]]), torch.tensor([0.8, 0.3]), torch.tensor([4, 7])),
    ]
    Xc = torch.rand(2, 30, 2, generator=g, dtype=D)
    sel = ProfileVariancePerEffort(m=4)
    many = sel.select_batch(
        BatchedPreferenceGP.from_models(models),
        Xc,
        [None, None],
        0,
        10,
        [torch.Generator().manual_seed(b) for b in range(2)],
    )
    ones = [sel.select(models[b], Xc[b], None, 0, 10, torch.Generator().manual_seed(b)) for b in range(2)]
    assert [_shown(q) for q in ones] == [_shown(q) for q in many]


def _shown(q):
    """A query's kind and its items, as nested lists."""
    return q.kind, q.items.tolist()


def test_profiles(generator):
    """The profile is the rating on the top k and 0 elsewhere; the clipped one the rating on the
    top k and the k-th largest rating elsewhere."""
    lik = _lik()
    F = torch.randn(3, 7, 9, generator=generator, dtype=D)
    r = lik.rating.expected_rating(F, torch.zeros_like(F))
    kth = r.sort(-1, descending=True).values[..., 2:3]
    top = r >= kth
    assert torch.equal(top_profile(F, 3, lik.rating), torch.where(top, r, 0.0))
    assert torch.equal(top_profile(F, 3, lik.rating, clipped=True), torch.where(top, r, kth))
    assert bool((top.sum(-1) == 3).all())


def test_bad_arguments_and_an_ordinal_model(generator):
    with pytest.raises(ValueError, match="costs"):
        ProfileVariancePerEffort(rating_cost=0)
    with pytest.raises(ValueError, match="top_fraction"):
        ProfileVariancePerEffort(top_fraction=1.5)
    with pytest.raises(ValueError, match="num_samples"):
        ProfileVariancePerEffort(num_samples=1)
    with pytest.raises(ValueError, match="V must be"):
        profile_variance_reduction(torch.ones(1, 2, 5, 3, dtype=D), torch.ones(1, 4, 6, dtype=D))
    X = _line()
    ordinal = PreferenceGP(
        X,
        torch.tensor([[1, 0], [5, 2]]),
        torch.tensor([4.0, 2.0]),
        torch.tensor([3, 6]),
        covar_module=fixed_rbf_kernel(0.1, 1.0, X),
        rating_levels=5,
    )
    q = ProfileVariancePerEffort(m=3).select(ordinal, X, None, 0, 5, generator)
    assert isinstance(q, (RatingQuery, RankingQuery))
