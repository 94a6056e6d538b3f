"""Errors BoTorch understands: a fit from any start the optimiser can reach ends in a usable
model or a named error (docs/botorch.md)."""

import warnings

import pytest
import torch
from botorch.exceptions.errors import ModelFittingError
from botorch.fit import fit_gpytorch_mll
from botorch.models.transforms.input import Normalize
from linear_operator.utils.errors import NotPSDError as LinearOperatorNotPSDError

from torchpref.inference.numerics import NotPSDError, cholesky_jittered
from torchpref.models.preference_gp import MIN_LENGTHSCALE, LaplaceMarginalLogLikelihood, PreferenceGP


def loop_data(seed: int, n: int = 54, d: int = 4, repeats: int = 11):
    """What a preference-BO loop piles up: ``n`` items, one corner of the cube proposed
    ``repeats`` times, each pair compared once (noisy ``sum sqrt(i) x_i``)."""
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, d, generator=g, dtype=torch.float64)
    X[n - 2 * repeats :: 2] = 1.0
    u = (X * torch.arange(1, d + 1, dtype=torch.float64).sqrt()).sum(-1)
    C = torch.arange(n).view(-1, 2)
    noisy = u[C] + 0.1 * torch.randn(C.shape, generator=g, dtype=torch.float64)
    flip = noisy[:, 0] < noisy[:, 1]
    C[flip] = C[flip].flip(-1)
    return X, C


def usable(model: PreferenceGP, X: torch.Tensor) -> bool:
    post = model.posterior(X)
    return bool(
        torch.isfinite(post.mean).all()
        and (post.variance > 0).all()
        and torch.isfinite(model.log_marginal_likelihood())
    )


def test_not_psd_error_is_linear_operators():
    assert issubclass(NotPSDError, LinearOperatorNotPSDError) and issubclass(NotPSDError, RuntimeError)
    with pytest.raises(LinearOperatorNotPSDError):
        cholesky_jittered(torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=torch.float64))


def test_fit_retries_after_not_psd_error():
    """A start where the kernel matrix cannot be factorised (NaN outputscale) raises our
    NotPSDError; fit_gpytorch_mll catches it and retries from hyperparameters drawn from their
    priors, ending in a usable model."""
    X, C = loop_data(0)
    model = PreferenceGP(X, C, input_transform=Normalize(d=X.shape[-1]))
    with torch.no_grad():
        model.covar_module.raw_outputscale.fill_(float("nan"))
    with pytest.raises(NotPSDError):
        model.log_marginal_likelihood()
    with torch.random.fork_rng():
        torch.manual_seed(0)  # the priors are sampled from torch's global generator
        fit_gpytorch_mll(LaplaceMarginalLogLikelihood(model))
    assert usable(model, X)


def test_lengthscale_floor():
    """The optimiser's step towards lengthscale 0 (raw value -1e4) stops at the floor 1e-4,
    where the kernel matrix of 54 items with 11 repeats is still factorised (with jitter)."""
    X, C = loop_data(0)
    model = PreferenceGP(X, C, input_transform=Normalize(d=X.shape[-1]))
    with torch.no_grad():
        model.covar_module.base_kernel.raw_lengthscale.fill_(-1e4)
    assert torch.allclose(
        model.covar_module.base_kernel.lengthscale, torch.tensor(MIN_LENGTHSCALE, dtype=torch.float64)
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert usable(model, X)
        fit_gpytorch_mll(LaplaceMarginalLogLikelihood(model))
    assert usable(model, X)


GRID = [(seed, start, noise) for seed in (0, 1) for start in (2e-4, 1e-2, None, 1e3) for noise in (0.1, 1.0)]
QUICK = [(0, 2e-4, 0.1), (0, 1e3, 1.0)]


@pytest.mark.parametrize(
    "seed,start,comparison_noise", QUICK + [pytest.param(*c, marks=pytest.mark.slow) for c in GRID if c not in QUICK]
)
def test_fit_from_extreme_starts_with_repeated_items(seed, start, comparison_noise):
    X, C = loop_data(seed)
    model = PreferenceGP(X, C, input_transform=Normalize(d=X.shape[-1]), comparison_noise=comparison_noise)
    if start is not None:
        model.covar_module.base_kernel.lengthscale = start
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # jitter and optimiser warnings are expected here
        try:
            fit_gpytorch_mll(LaplaceMarginalLogLikelihood(model))
        except ModelFittingError:  # every attempt failed: a named error, the model as it was
            pass
        assert usable(model, X)
