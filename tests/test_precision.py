"""float32 against float64: Newton's stopping rule at round-off (docs/precision.md)."""

import warnings

import pytest
import torch
from botorch.exceptions.warnings import InputDataWarning
from gpytorch.kernels import RBFKernel, ScaleKernel

from torchpref import PreferenceGP
from torchpref.laplace import LaplaceConvergenceWarning
from torchpref.numerics import default_tolerance, roundoff_floor

F32, F64 = torch.float32, torch.float64


def extreme_ratings_model(dtype: torch.dtype) -> PreferenceGP:
    """One item rated ``1e-6`` three times with ``nu`` about 500: a log posterior of about 32 whose
    parts (``lgamma(nu)`` and its kin) are a hundred times larger (fuzz seed 413)."""
    k = ScaleKernel(RBFKernel()).to(dtype)
    k.base_kernel.lengthscale, k.outputscale = 0.0017, 1.49
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputDataWarning)  # float32 inputs
        return PreferenceGP(torch.tensor([[0.63, 0.92, 0.80]], dtype=dtype), ratings=torch.full((3,), 1e-6, dtype=dtype),
                            rating_index=torch.zeros(3, dtype=torch.long), covar_module=k,
                            rating_scale=0.2044, rating_precision=495.78)


def test_float32_newton_stops_at_its_roundoff_floor():
    # before: the decrement stalled at 1e-4 (float32 cannot resolve less of this log posterior),
    # 100 iterations and a LaplaceConvergenceWarning
    with warnings.catch_warnings():
        warnings.simplefilter("error", LaplaceConvergenceWarning)
        mode32 = extreme_ratings_model(F32).mode
        mode64 = extreme_ratings_model(F64).mode
    assert bool(mode32.converged) and mode32.iterations < 20
    assert bool(mode64.converged) and mode64.iterations < 20
    # where it stops, float32's own round-off of the likelihood's gradient leaves 1e-3 of the mode
    assert torch.allclose(mode32.f.double(), mode64.f, rtol=2e-3, atol=0)


def test_roundoff_floor_scales_with_the_parts_and_dtype():
    ll, prior = torch.tensor([-1e4, 30.0], dtype=F64), torch.tensor([10.0, 0.5], dtype=F64)
    floor64, floor32 = roundoff_floor(ll, prior), roundoff_floor(ll.float(), prior.float())
    assert torch.allclose(floor64, 100 * torch.finfo(F64).eps * (ll.abs() + prior))
    assert torch.allclose(floor32.double(), 100 * torch.finfo(F32).eps * (ll.abs() + prior), rtol=1e-6)
    # float64's floor is under its tolerance until the parts reach about 450
    small = roundoff_floor(torch.tensor([-440.0], dtype=F64), torch.tensor([0.0], dtype=F64))
    assert float(small) < default_tolerance(F64) < float(floor64[0])


@pytest.mark.parametrize("dtype", [F32, F64])
def test_stall_rule_does_not_stop_a_solve_far_from_the_mode(dtype):
    # one Newton iteration is not a stall: a cold start from a decrement of 1e4 runs to convergence
    model = extreme_ratings_model(dtype)
    model.max_newton_iter = 3
    with pytest.warns(LaplaceConvergenceWarning):
        assert not bool(model.mode.converged)
