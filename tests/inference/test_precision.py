"""float32 against float64: Newton's stopping rule at round-off (docs/precision.md)."""

import warnings

import pytest
import torch
from botorch.exceptions.warnings import InputDataWarning
from gpytorch.kernels import RBFKernel, ScaleKernel

from torchpref import PreferenceGP
from torchpref.inference.laplace import LaplaceConvergenceWarning
from torchpref.inference.numerics import default_tolerance, roundoff_floor

F32, F64 = torch.float32, torch.float64


def extreme_ratings_model(dtype: torch.dtype) -> PreferenceGP:
    """One item rated ``1e-6`` three times with ``nu`` about 500: a log posterior of about 32 whose
    parts (``lgamma(nu)`` and its kin) are a hundred times larger (fuzz seed 413)."""
    k = ScaleKernel(RBFKernel()).to(dtype)
    k.base_kernel.lengthscale, k.outputscale = 0.0017, 1.49
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputDataWarning)  # float32 inputs
        return PreferenceGP(
            torch.tensor([[0.63, 0.92, 0.80]], dtype=dtype),
            ratings=torch.full((3,), 1e-6, dtype=dtype),
            rating_index=torch.zeros(3, dtype=torch.long),
            covar_module=k,
            rating_scale=0.2044,
            rating_precision=495.78,
        )


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


# ------------------------------------------------------------ mixed precision


def long_lengthscale_models(laplace_dtype=None, kernel=None):
    """Ratings of 120 items at lengthscale 40 on the unit cube (``K`` numerically of rank a few):
    float32 needs a relative jitter of 1e-5 that float64 does not, so the native float32 model
    is another model (fuzz seed 250 is of this kind). Returns ``(float32 model, float64 twin)``."""
    g = torch.Generator().manual_seed(3)
    X = torch.rand(120, 2, generator=g, dtype=F64).float().double()
    idx = torch.randint(0, 120, (150,), generator=g)
    u = torch.where(X[idx, 0] > 0.5, 1 - 1e-6, 1e-6).float().double()  # a steep step: f is large
    models = []
    for dtype in (F32, F64):
        k = (kernel() if kernel is not None else ScaleKernel(RBFKernel())).to(dtype)
        if kernel is None:
            k.base_kernel.lengthscale, k.outputscale = 40.0, 2.0
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", InputDataWarning)
            models.append(
                PreferenceGP(
                    X.to(dtype),
                    ratings=u.to(dtype),
                    rating_index=idx,
                    covar_module=k,
                    rating_precision=300.0,
                    laplace_dtype=laplace_dtype if dtype == F32 else None,
                )
            )
    return models


def moments(model, X, grad=False):
    X = X.clone().requires_grad_(grad)
    with torch.set_grad_enabled(grad):
        mvn = model.posterior(X).distribution
        mean, cov = mvn.mean, mvn.covariance_matrix
        if grad:
            mean.sum().backward()
    return mean.detach(), cov.detach(), X.grad


def relative_gap(a, b):
    """Largest mean and covariance differences, relative to the reference's scale."""
    return max(
        float((a[0].double() - b[0]).abs().max()) / float(b[0].abs().max()),
        float((a[1].double() - b[1]).abs().max()) / float(b[1].diagonal().max()),
    )


@pytest.mark.parametrize("grad", [False, True])
def test_float32_model_solves_in_float64_and_agrees_with_its_twin(grad):
    # before: float32 solved natively, with jitter 1e-5 of the outputscale, 0.4 away from float64
    m32, m64 = long_lengthscale_models()
    assert m32.laplace_dtype == F64 and m32.mode.f.dtype == F64
    Xq = torch.rand(10, 2, generator=torch.Generator().manual_seed(4), dtype=F64)
    Xq = torch.cat([Xq, m64.train_X[:3]])
    a, b = moments(m32, Xq.float(), grad), moments(m64, Xq, grad)
    assert a[0].dtype == a[1].dtype == F32  # float32 in, float32 out
    assert relative_gap(a, b) < 1e-5
    if grad:
        assert a[2].dtype == F32 and torch.allclose(a[2].double(), b[2], rtol=1e-3, atol=1e-4 * float(b[2].abs().max()))


def test_native_float32_is_a_different_model_at_long_lengthscales():
    # the documented limit (docs/precision.md): what laplace_dtype=torch.float32 gives up
    m32, m64 = long_lengthscale_models(laplace_dtype=F32)
    assert m32.laplace_dtype == F32 and m32.mode.f.dtype == F32
    Xq = m64.train_X[:20]
    assert relative_gap(moments(m32, Xq.float()), moments(m64, Xq)) > 1e-3  # the 1e-3 target, missed
    assert m32._state().jitter >= 1e-6 * 2.0 > m64._state().jitter


def test_mixed_precision_evidence_and_its_gradient_match_float64():
    m32, m64 = long_lengthscale_models()
    e32, e64 = m32.log_marginal_likelihood(), m64.log_marginal_likelihood()
    assert e32.dtype == F32
    assert abs(float(e32) - float(e64)) < 1e-5 * abs(float(e64))
    e32.backward(), e64.backward()
    for p32, p64 in zip(m32.covar_module.parameters(), m64.covar_module.parameters()):
        assert p32.grad.dtype == F32
        torch.testing.assert_close(p32.grad.double(), p64.grad, rtol=1e-4, atol=1e-6)


def test_mixed_precision_with_a_kernel_that_does_not_promote_dtypes():
    # PolynomialKernel's addmm refuses float32 parameters with float64 inputs: the parameters are
    # converted for the call instead (precision.call_in_dtype)
    from gpytorch.kernels import PolynomialKernel

    m32, m64 = long_lengthscale_models(kernel=lambda: ScaleKernel(PolynomialKernel(2)))
    Xq = m64.train_X[:5]
    assert relative_gap(moments(m32, Xq.float()), moments(m64, Xq)) < 1e-5


def test_laplace_dtype_is_validated_and_switches_the_solve():
    m32, _ = long_lengthscale_models()
    with pytest.raises(ValueError, match="laplace_dtype.*'float32'"):
        m32.laplace_dtype = "float32"
    with pytest.raises(ValueError, match="laplace_dtype.*torch.int64"):
        PreferenceGP(torch.rand(3, 2), laplace_dtype=torch.long)
    assert m32.laplace_dtype == F64
    m32.laplace_dtype = F32  # a new solve, natively
    assert m32.mode.f.dtype == F32
    m32.laplace_dtype = None
    assert m32.mode.f.dtype == F64
    m64 = m32.double()  # never below the model's own precision
    m64.laplace_dtype = F32
    assert m64.laplace_dtype == F64


def test_laplace_dtype_survives_a_checkpoint_and_a_batch_trial(tmp_path):
    from torchpref.models.batch import BatchedPreferenceGP
    from torchpref.models.checkpoint import load_model, save_model

    m32, _ = long_lengthscale_models(laplace_dtype=F32)
    save_model(m32, tmp_path / "m.pt")
    loaded = load_model(tmp_path / "m.pt", covar_module=ScaleKernel(RBFKernel()))
    assert loaded.laplace_dtype == F32 and loaded.utility.dtype == F32
    torch.testing.assert_close(loaded.posterior(m32.train_X[:4]).mean, m32.posterior(m32.train_X[:4]).mean)
    trials = BatchedPreferenceGP(m32, [m32.data, m32.data])
    assert trials.trial_model(1).laplace_dtype == F32


# ------------------------------------------- the Beta likelihood where mu rounds to 0 or 1


@pytest.mark.parametrize("dtype, eta", [(F32, -3.3331), (F32, -10.0), (F64, -10.0), (F64, 9.0)])
def test_beta_derivatives_are_finite_where_phi_underflows(dtype, eta):
    # Phi(eta / (sqrt 2 sigma_B)) underflows below t ~ -13 (float32) and -37 (float64): psi(nu mu)
    # was infinite there, the gradient inf or NaN, and Newton raised FloatingPointError (fuzz
    # seeds 456 and 522). Reference: mpmath's derivatives of the direct log density.
    mp = pytest.importorskip("mpmath")
    from torchpref.likelihoods.pairwise_beta import BetaRatingLikelihood

    lik = BetaRatingLikelihood(0.1724578, 933.7958).to(dtype)
    u = torch.tensor([1 - 1e-6, 0.3], dtype=dtype)
    e = torch.full_like(u, eta)
    out = [*lik.derivatives(e, u), lik.third_derivative(e, u)]
    assert all(bool(torch.isfinite(x).all()) for x in out)
    sB, nu = float(lik.rating_scale), float(lik.rating_precision)
    mp.mp.dps = 60

    def logp(x, ui):
        mu, mu_c = mp.ncdf(x / (mp.sqrt(2) * sB)), mp.ncdf(-x / (mp.sqrt(2) * sB))  # mu, 1 - mu
        return (
            (nu * mu - 1) * mp.log(ui)
            + (nu * mu_c - 1) * mp.log(1 - ui)
            + mp.loggamma(nu)
            - mp.loggamma(nu * mu)
            - mp.loggamma(nu * mu_c)
        )

    for i, ui in enumerate(u.double().tolist()):
        ref = [float(mp.diff(lambda x: logp(x, mp.mpf(ui)), mp.mpf(eta), k)) for k in range(3)]
        # float64: to round-off; float32: the value and slope to its own resolution of the parts
        rtol = (1e-9, 1e-9, 1e-6) if dtype == F64 else (1e-5, 1e-3, None)
        for k, tol in enumerate(rtol):
            if tol is not None:
                assert abs(float(out[k][i]) - ref[k]) <= tol * max(abs(ref[k]), 1.0), (k, float(out[k][i]), ref[k])


def test_native_float32_solves_ratings_where_phi_underflows():
    # fuzz seed 456 (sigma_B 0.17, nu 934, 27 items): FloatingPointError before
    from torchpref.testing import problems as fp

    rec = fp.check(fp.make_problem(456), pairwisegp=False)
    assert rec["f32n_error"] is None and rec["f32n_converged"] and rec["f64_converged"]
    assert max(rec["f32_gap_mean_nograd"], rec["f32_gap_cov_nograd"]) < 1e-5
