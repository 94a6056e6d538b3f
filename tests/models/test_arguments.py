"""Arguments checked where they enter (issue #26, item 4): types and ranges of the constructor's
arguments and of public functions', unsupported dtypes refused by name, complex and boolean
inputs refused, empty batches giving empty results. Each case here was accepted (or failed deep
in torch) before."""

import pytest
import torch

import torchpref
from torchpref import PreferenceGP

F64 = torch.float64


def _data():
    g = torch.Generator().manual_seed(5)
    return torch.rand(5, 2, generator=g, dtype=F64), torch.tensor([[0, 1], [2, 3]])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(covar_module="rbf"), r"covar_module must be a gpytorch Kernel .* got 'rbf' \(str\)"),
        (dict(input_transform="normalize"), "input_transform must be a BoTorch InputTransform"),
        (dict(ties_offered="no"), r"ties_offered must be True or False, got 'no' \(str\)"),
        (dict(learn_likelihood="no"), "learn_likelihood must be True or False, got 'no'"),
        (dict(comparison_noise=True), r"comparison_noise must be a real number, got True \(bool\)"),
        (dict(rating_scale="1"), "rating_scale must be a real number, got '1'"),
        (dict(rating_precision=float("inf")), "rating_precision must be finite, got inf"),
        (dict(rating_eps=0.7), r"rating_eps must be a number in \(0, 0.5\), got 0.7"),
        (dict(rating_eps=-1.0), r"rating_eps must be a number in \(0, 0.5\), got -1.0"),
        (dict(laplace_dtype=torch.float16), "laplace_dtype must be None, torch.float32 or torch.float64"),
    ],
)
def test_constructor_arguments_of_the_wrong_type_or_range_are_named(kwargs, match):
    X, C = _data()
    with pytest.raises(ValueError, match=match):
        PreferenceGP(X, C, **kwargs)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_is_refused_by_name(dtype):
    X, C = _data()
    with pytest.raises(ValueError, match=f"train_X is {dtype}; PreferenceGP supports float32 and float64"):
        PreferenceGP(X.to(dtype), C)
    model = PreferenceGP(X, C).to(dtype)  # converted afterwards: refused at the first prediction
    with pytest.raises(ValueError, match=f"this model is {dtype}; PreferenceGP supports float32 and float64"):
        model.posterior(X.to(dtype))


def test_float32_and_numpy_flags_are_still_accepted():
    np = pytest.importorskip("numpy")
    X, C = _data()
    model = PreferenceGP(X.float(), C, ties_offered=np.bool_(True), comparison_noise=torch.tensor(0.5))
    assert model.ties_offered is True
    assert torch.isfinite(model.posterior(X.float()).mean).all()


@pytest.mark.parametrize("num_levels", [0, -3, 2.5, True, "5"])
def test_unit_to_likert_checks_num_levels_as_likert_to_unit_does(num_levels):
    with pytest.raises(ValueError, match="num_levels must be an integer of at least 2"):
        torchpref.unit_to_likert(torch.tensor([0.5]), num_levels=num_levels)
    with pytest.raises(ValueError, match="num_levels must be an integer of at least 2"):
        torchpref.likert_to_unit(torch.tensor([1.0]), num_levels=num_levels)


@pytest.mark.parametrize("dtype", [torch.complex128, torch.bool])
def test_complex_and_boolean_inputs_are_refused(dtype):
    X, C = _data()
    model = PreferenceGP(X, C)
    with pytest.raises(ValueError, match=f"X must hold real numbers, got {dtype}"):
        model.posterior(X.to(dtype))
    with pytest.raises(ValueError, match=f"X must hold real numbers, got {dtype}"):
        model.expected_rating(X.to(dtype))


@pytest.mark.parametrize("shape", [(0, 2), (3, 0, 2), (0, 4, 2)])
def test_empty_batches_give_empty_results(shape):
    X, C = _data()
    model = PreferenceGP(X, C)
    empty = torch.zeros(shape, dtype=F64)
    for f in (model.expected_rating, lambda x: model.marginals(x)[1]):
        out = f(empty)
        assert out.shape == shape[:-1] and out.dtype == F64
    assert model.posterior(empty).mean.shape == (*shape[:-1], 1)
    assert model.preference_probability(empty, empty).shape == shape[:-1]
    ordinal = PreferenceGP(X, C, torch.tensor([2.0]), torch.tensor([4]), rating_levels=5)
    assert ordinal.expected_level(empty).shape == shape[:-1]
    assert ordinal.level_probabilities(empty).shape == (*shape[:-1], 5)
