"""The compiled small-problem path (issues 33 and 42) against the torch solver, its reference: the
same problems through both agree on the mode, the evidence and its gradient, and the fitted
hyperparameters, on random problems and on hostile ones, with comparisons and with Beta ratings;
the compiled fit hands its mode to the model's cache; the package works without numba and
``import torchpref`` does not load it. The cache, the setting and the processes:
``test_fast_path_cache.py``; person models: ``test_fast_path_person.py``."""

import math
import os
import subprocess
import sys
import warnings

import pytest
import torch
from botorch.fit import fit_gpytorch_mll
from gpytorch.kernels import MaternKernel, RBFKernel, ScaleKernel
from gpytorch.priors import GammaPrior, LogNormalPrior

from torchpref import LaplaceMarginalLogLikelihood, PreferenceGP
from torchpref.inference import fast_path
from torchpref.testing import problems

F64 = torch.float64
needs_numba = pytest.mark.skipif(not fast_path.available(), reason="numba is not installed (the fast extra)")


@pytest.fixture(scope="module")
def compiled_path():
    """The compiled path loaded in this process (built first if no usable cache exists: a minute)."""
    with fast_path.fast_path("on"):
        functions = fast_path.warm_up()
    assert functions is not None, fast_path.status()
    return functions


def _kernel(kind: str, d: int, ls: float = 0.3, os_: float = 1.0):
    prior = LogNormalPrior(math.sqrt(2) + 0.5 * math.log(d), math.sqrt(3))
    base = (
        RBFKernel(ard_num_dims=d, lengthscale_prior=prior)
        if kind == "rbf"
        else MaternKernel(nu={"m12": 0.5, "m32": 1.5, "m52": 2.5}[kind], ard_num_dims=d, lengthscale_prior=prior)
    )
    k = ScaleKernel(base, outputscale_prior=GammaPrior(2.0, 1.0)).to(F64)
    k.base_kernel.lengthscale, k.outputscale = ls, os_
    return k


def _problem(seed: int, n: int, d: int = 2, p: int | None = None):
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, d, generator=g, dtype=F64)
    p = 2 * n if p is None else p
    i = torch.randint(0, n, (p,), generator=g)
    j = (i + torch.randint(1, n, (p,), generator=g)) % n
    u = torch.sin(6 * X).sum(-1)
    first = u[i] + torch.randn(p, generator=g, dtype=F64) > u[j]
    return X, torch.stack([torch.where(first, i, j), torch.where(first, j, i)], -1)


def _model(X, C, kind="rbf", noise=1.0, ls=0.3, os_=1.0):
    return PreferenceGP(X, comparisons=C, covar_module=_kernel(kind, X.shape[-1], ls, os_), comparison_noise=noise)


def _evidence_and_grad(model):
    mll = LaplaceMarginalLogLikelihood(model)
    params = [p for p in mll.parameters() if p.requires_grad]
    value = mll()
    grads = torch.autograd.grad(value, params)
    return float(value.detach()), torch.cat([g.reshape(-1) for g in grads])


def test_setting_values_and_errors(monkeypatch):
    monkeypatch.delenv(fast_path.ENV, raising=False)
    assert fast_path.setting() == "auto"
    with fast_path.fast_path("off"):
        assert fast_path.setting() == "off"
        with fast_path.fast_path("on"):
            assert fast_path.setting() == "on"
        assert fast_path.setting() == "off"
    assert fast_path.setting() == "auto"
    monkeypatch.setenv(fast_path.ENV, "off")
    assert fast_path.setting() == "off" and fast_path.compiled() is None
    monkeypatch.setenv(fast_path.ENV, "fast")
    with pytest.raises(ValueError, match="TORCHPREF_FAST_PATH='fast'.*auto, on, off"):
        fast_path.setting()
    with pytest.raises(ValueError, match="TORCHPREF_FAST_PATH"):
        fast_path.check_setting()
    with pytest.raises(ValueError, match="'sometimes'"):
        fast_path.fast_path("sometimes")


@needs_numba
@pytest.mark.parametrize(
    "seed,n,kind,noise", [(0, 20, "rbf", 1.0), (1, 60, "m52", 0.1), (2, 7, "m32", 3.0), (3, 150, "rbf", 0.5)]
)
def test_mode_evidence_and_gradient_agree(seed, n, kind, noise, compiled_path):
    X, C = _problem(seed, n)
    out = {}
    for mode in ("off", "on"):
        with fast_path.fast_path(mode):
            model = _model(X, C, kind, noise)
            m = model.mode
            out[mode] = (m.f, m.M, m.weights[0], *_evidence_and_grad(model))
    f0, M0, w0, e0, g0 = out["off"]
    f1, M1, w1, e1, g1 = out["on"]
    tol = 1e-9 if n < 128 else 1e-6  # from n = 128 the torch solver takes chord steps: other iterates
    assert torch.allclose(f1, f0, atol=tol, rtol=0)
    assert torch.allclose(M1, M0, atol=tol, rtol=0) and torch.allclose(w1, w0, atol=tol, rtol=0)
    assert abs(e1 - e0) < 1e-9 * max(1.0, abs(e0))  # second-order accurate in the mode
    assert torch.allclose(g1, g0, atol=100 * tol, rtol=100 * tol)


@needs_numba
@pytest.mark.parametrize("kind", ["rbf", "m12", "m32", "m52"])
@pytest.mark.parametrize("ratings", [False, True])
def test_compiled_loss_matches_the_torch_mll_and_autograd(kind, ratings, compiled_path):
    """The compiled fit's loss and raw-parameter gradient against BoTorch's loss (``-mll()``) and
    autograd through it at the same point, for each kernel, with comparisons only and with Beta
    ratings and a fixed prior mean besides; the specification crosses as named fields."""
    from gpytorch.means import ConstantMean

    from torchpref.inference import fast_types
    from torchpref.models.fast_fit import compiled_problem

    X, C = _problem(4, 30, d=3)
    model = _model(X, C, kind, ls=0.4, os_=1.7)
    if ratings:
        u = torch.linspace(0.05, 0.95, 9, dtype=F64)
        mean = ConstantMean().to(F64).requires_grad_(False)
        mean.constant.fill_(0.4)
        model = PreferenceGP(X, C, u, torch.arange(9) * 3, covar_module=model.covar_module, mean_module=mean)
    model.covar_module.base_kernel.lengthscale = torch.tensor([[0.2, 0.5, 0.9]], dtype=F64)
    mll = LaplaceMarginalLogLikelihood(model)
    problem = compiled_problem(mll)
    assert problem is not None and isinstance(problem.spec, fast_types.FitSpec)
    assert problem.spec.ls_count == 3 and problem.spec.os_prior.kind == fast_types.GAMMA
    assert (problem.answers.kind == fast_types.BETA).sum() == (9 if ratings else 0)
    x = torch.cat([p.detach().reshape(-1) for p in problem.params.values()]).numpy()
    with fast_path.fast_path("off"):
        loss = -mll()
        grads = torch.autograd.grad(loss, list(problem.params.values()))
    state = fast_types.fit_state(problem.f0, problem.answers.first.shape[0])
    value, grad, status = fast_path.call(
        "fit_loss", x, problem.X, problem.answers, problem.spec, state, problem.tol, problem.max_iter
    )
    assert status == fast_types.OK
    assert abs(value - float(loss.detach())) < 1e-10 * abs(float(loss.detach()))
    expected = torch.cat([g.reshape(-1) for g in grads]).numpy()
    assert abs(grad - expected).max() < 1e-7 * max(1.0, abs(expected).max())


def _fit(X, C, mode, kind="rbf", noise=1.0):
    with fast_path.fast_path(mode), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = _model(X, C, kind, noise)
        fit_gpytorch_mll(LaplaceMarginalLogLikelihood(model))
        with fast_path.fast_path("off"), torch.no_grad():
            value = float(LaplaceMarginalLogLikelihood(model)())
    k = model.covar_module
    return torch.cat([k.base_kernel.lengthscale.reshape(-1), k.outputscale.reshape(-1)]).detach(), value, model


@needs_numba
@pytest.mark.parametrize("seed,n,kind", [(5, 20, "rbf"), (6, 50, "rbf"), (7, 35, "m52"), (8, 100, "rbf")])
def test_fitted_hyperparameters_agree(seed, n, kind, compiled_path):
    """The compiled fit (its own L-BFGS with SciPy's L-BFGS-B stopping rules) reaches the torch
    fit's optimum: the same objective to 1e-7 relative, hyperparameters to L-BFGS's tolerance."""
    X, C = _problem(seed, n)
    h0, v0, _ = _fit(X, C, "off", kind)
    h1, v1, m1 = _fit(X, C, "on", kind)
    assert not m1.training
    assert abs(v1 - v0) < 1e-7 * abs(v0)
    assert torch.allclose(h1, h0, rtol=2e-3, atol=0)


@needs_numba
@pytest.mark.parametrize("seed", range(12))
def test_hostile_problems_agree_or_fall_back(seed, compiled_path):
    """The fuzz's hostile comparison problems (duplicated items, contradictions, noise from 1e-3,
    lengthscales from 1e-3 to 1e3): the compiled mode agrees with the torch one wherever the
    torch solver succeeds, and a compiled fit ends usable wherever the torch fit does."""
    p = problems.make_problem(seed, max_n=40, pairwise_likelihood=False)
    if not p.comparisons.numel():
        pytest.skip("a ratings-only problem: the compiled path does not apply")
    noise = p.likelihood["comparison_noise"]
    modes = {}
    for mode in ("off", "on"):
        with fast_path.fast_path(mode), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = _model(p.X, p.comparisons, "rbf", noise, p.lengthscale, p.outputscale)
            try:
                modes[mode] = model.mode.f
            except Exception as err:  # the torch solver's own errors, named
                modes[mode] = type(err).__name__
    if isinstance(modes["off"], torch.Tensor):
        assert isinstance(modes["on"], torch.Tensor)
        scale = max(1.0, float(modes["off"].abs().max()))
        assert float((modes["on"] - modes["off"]).abs().max()) < 1e-6 * scale
    outcome = {}
    for mode in ("off", "on"):
        try:
            _, value, model = _fit(p.X, p.comparisons, mode, "rbf", noise)
            outcome[mode] = problems.usable(model) or value
        except Exception as err:
            outcome[mode] = type(err).__name__
    if isinstance(outcome["off"], float):
        assert isinstance(outcome["on"], float), outcome
        assert outcome["on"] > outcome["off"] - 1e-6 * max(1.0, abs(outcome["off"])), outcome


@needs_numba
def test_unsupported_models_use_the_torch_solver(compiled_path):
    """A likelihood subclass that does not declare itself compiled (it may change the derivatives)
    and float32 go to the torch solver even when the compiled path is forced (bit for bit the same
    results; the model's mode and last fit say so). Ordinal levels, ties and lapses are compiled:
    ``test_fast_path_kinds.py``."""
    from torchpref.likelihoods.pairwise_beta import PairwiseProbitLikelihood
    from torchpref.models.defaults import PreferenceLikelihood

    class OwnProbit(PairwiseProbitLikelihood):
        pass

    X, C = _problem(9, 15)
    ref = {}
    for mode in ("off", "on"):
        with fast_path.fast_path(mode), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = PreferenceGP(X, comparisons=C, covar_module=_kernel("rbf", 2))
            lik = model.likelihood
            model.likelihood = PreferenceLikelihood(
                OwnProbit(float(lik.comparison.comparison_noise)), lik.rating, lik.tie
            )
            fit_gpytorch_mll(LaplaceMarginalLogLikelihood(model))
            assert model.last_fit.solver == "torch" and model.mode.solver == "torch"
            ref[mode] = model.covar_module.outputscale.detach().clone()
            m32 = PreferenceGP(
                X.float(), comparisons=C, covar_module=_kernel("rbf", 2).float(), laplace_dtype=torch.float32
            )
            ref[mode + "32"] = m32.mode.f
            assert m32.mode.solver == "torch"
    assert torch.equal(ref["on"], ref["off"]) and torch.equal(ref["on32"], ref["off32"])


def _run(code: str, **env) -> subprocess.CompletedProcess:
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    full = {**os.environ, "PYTHONPATH": root, **env}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=full, timeout=300)


def test_import_does_not_load_numba():
    out = _run(
        "import sys, torchpref; torchpref.PreferenceGP; torchpref.LaplaceMarginalLogLikelihood; print('numba' in sys.modules)"
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


def test_package_works_without_numba():
    """numba blocked (as if not installed) and the compiled path asked for: the torch solver fits."""
    code = (
        "import sys; sys.modules['numba'] = None\n"
        "import torch, warnings; warnings.simplefilter('ignore')\n"
        "from botorch.fit import fit_gpytorch_mll\n"
        "from torchpref import PreferenceGP, LaplaceMarginalLogLikelihood\n"
        "from torchpref.inference import fast_path\n"
        "X = torch.rand(12, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))\n"
        "C = torch.tensor([[0, 1], [2, 3], [4, 5], [6, 7], [1, 2], [3, 9]])\n"
        "m = PreferenceGP(X, comparisons=C)\n"
        "fit_gpytorch_mll(LaplaceMarginalLogLikelihood(m))\n"
        "assert not fast_path.available() and fast_path.compiled() is None\n"
        "assert bool(torch.isfinite(m.posterior(X).mean).all())\n"
        "print('ok')"
    )
    out = _run(code, TORCHPREF_FAST_PATH="on")
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().endswith("ok")


@needs_numba
def test_custom_fit_routes_only_the_default_fit_of_a_supported_model(monkeypatch, compiled_path):
    """BoTorch's ``fit_gpytorch_mll`` comes to ``custom_fit``: the compiled fit runs for the default
    call of a supported model; arguments, learnable likelihoods and a failed compiled fit go to
    BoTorch's own routine, which still fits; the model's ``last_fit`` says which solver fitted and
    why, and its mode which solver found it."""
    from torchpref.models import fast_fit

    calls = []
    real = fast_fit.run
    monkeypatch.setattr(fast_fit, "run", lambda p: calls.append(1) or real(p))
    X, C = _problem(10, 12)
    with fast_path.fast_path("on"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        compiled = _model(X, C)
        assert compiled.last_fit is None
        fit_gpytorch_mll(LaplaceMarginalLogLikelihood(compiled))
        assert calls == [1]
        assert compiled.last_fit.solver == "compiled" and compiled.last_fit.status == "ok"
        assert compiled.last_fit.evaluations >= compiled.last_fit.iterations >= 1
        assert compiled.mode.solver == "compiled"
        asked = _model(X, C)
        fit_gpytorch_mll(LaplaceMarginalLogLikelihood(asked), optimizer_kwargs={"options": {"maxiter": 5}})
        assert asked.last_fit.solver == "torch" and "arguments" in asked.last_fit.status
        learnable = PreferenceGP(X, comparisons=C, covar_module=_kernel("rbf", 2), learn_likelihood=True)
        fit_gpytorch_mll(LaplaceMarginalLogLikelihood(learnable))
        assert calls == [1] and learnable.last_fit.solver == "torch"
        assert "does not apply" in learnable.last_fit.status
        gave_up = fast_fit.FitReport("torch", "the compiled fit stopped: not positive definite")
        monkeypatch.setattr(fast_fit, "run", lambda p: (None, gave_up))  # a compiled fit that gave up
        model = _model(X, C)
        mll = fit_gpytorch_mll(LaplaceMarginalLogLikelihood(model))
    assert not mll.training and float(model.covar_module.outputscale) != 1.0
    assert model.last_fit is gave_up
    with fast_path.fast_path("off"):
        assert _model(X, C).mode.solver == "torch"


@needs_numba
def test_a_compiled_arithmetic_error_falls_back_for_that_call_only(monkeypatch, compiled_path):
    """numba raises ``ZeroDivisionError`` where torch gives inf or NaN: the torch solver then
    answers that call, with its own results, and the compiled path stays on (no warning)."""

    def raising(*args):
        raise ZeroDivisionError("division by zero")

    X, C = _problem(11, 10)
    with fast_path.fast_path("off"):
        f_ref = _model(X, C).mode.f
    monkeypatch.setattr(fast_path.STATE, "functions", {**compiled_path, "newton": raising, "fit_lbfgs": raising})
    with fast_path.fast_path("on"), warnings.catch_warnings():
        warnings.simplefilter("error", fast_path.FastPathWarning)
        model = _model(X, C)
        assert torch.equal(model.mode.f, f_ref)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            warnings.simplefilter("error", fast_path.FastPathWarning)
            fit_gpytorch_mll(LaplaceMarginalLogLikelihood(model))
    assert float(model.covar_module.outputscale) != 1.0
    assert fast_path.STATE.failed is None


@needs_numba
@pytest.mark.parametrize("ratings", [False, True])
def test_the_compiled_fit_hands_its_mode_to_the_model(monkeypatch, ratings, compiled_path):
    """After a compiled fit the model's posterior cache holds the fit's last mode and factors, for
    the fitted hyperparameters: the next prediction solves nothing, and it is the prediction of a
    fresh torch solve at those hyperparameters."""
    from torchpref.inference import solver

    X, C = _problem(12, 25)
    kw = dict(ratings=torch.linspace(0.1, 0.9, 6, dtype=F64), rating_index=torch.arange(6) * 4) if ratings else {}
    model = PreferenceGP(X, C, covar_module=_kernel("rbf", 2), **kw)
    with fast_path.fast_path("on"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit_gpytorch_mll(LaplaceMarginalLogLikelihood(model))
    solves = []
    real = solver.find_mode
    monkeypatch.setattr(solver, "find_mode", lambda *a, **k: solves.append(1) or real(*a, **k))
    Xt = torch.rand(7, 2, generator=torch.Generator().manual_seed(3), dtype=F64)
    with torch.no_grad():
        post = model.posterior(Xt)
        mean, var = post.mean.clone(), post.variance.clone()
    assert solves == []
    # the kept mode is converged by the torch solver's own test (half the Newton decrement below tol)
    from torchpref.inference.newton import Problem

    state = model._cache
    point = Problem(state.pred.L, state.obs).evaluate(state.mode.a)
    step = torch.cholesky_solve(point.grad.unsqueeze(-1), state.mode.M).squeeze(-1)
    assert float((point.grad * step).sum()) / 2 < 1e-11
    model._cache = None  # a fresh solve by the torch solver at the fitted hyperparameters
    with fast_path.fast_path("off"), torch.no_grad():
        ref = model.posterior(Xt)
    assert solves == [1]
    # two modes that each pass that test: equal to the solver's tolerance, not to round-off
    assert float((mean - ref.mean).abs().max()) < 1e-6 and float((var - ref.variance).abs().max()) < 1e-6
