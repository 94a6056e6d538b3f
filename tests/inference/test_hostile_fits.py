"""Every numerical failure a named error BoTorch understands (issue #26, item 3): no bare
``FloatingPointError`` escapes the solver, a warm start far from the new mode falls back to a cold
one, a non-finite evidence is raised by name, ``fit_gpytorch_mll`` retries what it should, and
hostile-start fits end in a usable model or a named error (``benchmarks/robustness/hostile_fits.py``)."""

import warnings

import pytest
import torch

import torchpref
from torchpref.inference import laplace
from torchpref.inference.numerics import LaplaceNumericalError, NotPSDError
from torchpref.testing import problems as hf

F64 = torch.float64


def _walk(seed, steps):
    """The hostile model of ``seed`` after ``steps`` evidence evaluations at raw hyperparameters
    drawn wide (``30 N(0, 1)``), as a line search may reach: each warm-starts the next."""
    _, model = hf.hostile_model(seed, 15)
    g = torch.Generator().manual_seed(seed)
    for step in range(steps):
        with torch.no_grad():
            for p in model.parameters():
                p.copy_(30 * torch.randn(p.shape, generator=g, dtype=p.dtype))
        if step < steps - 1:
            model.log_marginal_likelihood()
    return model


@pytest.mark.parametrize("seed, steps", [(32, 4), (35, 3)])
def test_a_warm_start_far_from_the_mode_falls_back_to_a_cold_one(seed, steps):
    """These walks raised FloatingPointError (a non-finite Newton step from the predicted mode);
    a model built afresh at the same hyperparameters solved them."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = _walk(seed, steps)
        value = model.log_marginal_likelihood()
        _, fresh = hf.hostile_model(seed, 15)
        fresh.load_state_dict(model.state_dict())
        torch.testing.assert_close(value, fresh.log_marginal_likelihood(), atol=1e-6, rtol=1e-9)


@pytest.mark.parametrize("error", [FloatingPointError("non-finite Newton step"), ZeroDivisionError("0")])
def test_no_bare_arithmetic_error_escapes_find_mode(monkeypatch, error):
    def failing(*args, **kwargs):
        raise error

    monkeypatch.setattr(laplace, "newton_mode", failing)
    L = torch.eye(3, dtype=F64)[None]
    model = torchpref.PreferenceGP(torch.rand(3, 1, dtype=F64), torch.tensor([[0, 1]]))
    # the torch solver's error wrapping: with the compiled path off (it does not call newton_mode)
    with (
        torchpref.fast_path("off"),
        pytest.raises(LaplaceNumericalError, match="the Laplace mode could not be found") as info,
    ):
        laplace.find_mode(L, model._observations())
    assert isinstance(info.value, NotPSDError) and isinstance(info.value, FloatingPointError)
    assert info.value.__cause__ is error


def test_a_non_finite_evidence_is_raised_by_name(monkeypatch):
    model = torchpref.PreferenceGP(torch.rand(4, 1, dtype=F64), torch.tensor([[0, 1], [2, 3]]))
    monkeypatch.setattr(
        "torchpref.models.preference_gp.laplace_evidence", lambda *a, **k: torch.full((1,), float("nan"), dtype=F64)
    )
    with pytest.raises(LaplaceNumericalError, match=r"the Laplace evidence is not finite \(\[nan\]"):
        model.log_marginal_likelihood()


def test_fit_gpytorch_mll_retries_a_laplace_numerical_error():
    from botorch.fit import fit_gpytorch_mll

    _, model = hf.hostile_model(0, 15)
    calls = {"n": 0}
    evidence = type(model).log_marginal_likelihood

    def first_fails(self):
        calls["n"] += 1
        if calls["n"] == 1:
            raise LaplaceNumericalError("a first attempt that fails")
        return evidence(self)

    model.log_marginal_likelihood = first_fails.__get__(model)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit_gpytorch_mll(torchpref.LaplaceMarginalLogLikelihood(model))
    assert calls["n"] > 1 and hf.usable(model) is None


@pytest.mark.parametrize("seed", range(4))
def test_hostile_start_fits_end_usable_or_in_a_named_error(seed):
    out = hf.fit_outcome(seed, max_n=15)
    assert out["outcome"] == "fit" or out["outcome"] in hf.NAMED, out
