"""The compiled path's likelihood kinds beyond probit comparisons and Beta ratings (issue 52): the
models sessions, ``serve``, the study and person models build. Strict choices where ties were
offered (a probit shifted by ``-tau``), "no preference" ties and ordinal levels (Gaussian
intervals), comparisons with lapses and a person's rating link (gain and offset) are solved compiled
and agree with the torch solver (the reference); their compiled derivatives equal the likelihoods'
(tested against autograd in ``tests/likelihoods``); a compiled fit of a model that offers ties;
and a session's served answers are answered by the compiled solver."""

import math
import warnings

import numpy as np
import pytest
import torch
from botorch.fit import fit_gpytorch_mll

from torchpref import LaplaceMarginalLogLikelihood, PreferenceGP
from torchpref.inference import fast_path
from torchpref.inference.numerics import normal_interval
from torchpref.likelihoods.person import LapseProbitLikelihood
from torchpref.models.calibration import calibrate_person
from torchpref.sessions.session import PreferenceSession

D = torch.float64
needs_numba = pytest.mark.skipif(not fast_path.available(), reason="numba is not installed (the fast extra)")


@pytest.fixture(scope="module")
def compiled_path():
    with fast_path.fast_path("on"):
        functions = fast_path.warm_up()
    assert functions is not None, fast_path.status()
    return functions


@needs_numba
@pytest.mark.parametrize(
    "lower,upper,scale",
    [(-0.1, 0.1, 0.14), (-math.inf, -1.19, 0.2), (1.19, math.inf, 0.2), (-0.36, 0.36, 0.2), (0.1, math.inf, 0.5)],
)
def test_interval_derivatives_match_normal_interval(lower, upper, scale, compiled_path):
    """A Gaussian interval's compiled log probability and three derivatives equal
    :func:`~torchpref.inference.numerics.normal_interval`'s, from one tail to the other (``eta``
    up to 60 scales away: the tail branches and the continued fraction)."""
    from torchpref.inference import _compiled

    eta = torch.linspace(-60 * scale, 60 * scale, 241, dtype=D)
    lp, d1, d2, d3 = normal_interval(upper - eta, lower - eta, scale, third=True)
    got = np.array([_compiled.interval.py_func(float(e), lower, upper, scale) for e in eta])
    # the k-th derivative cancels terms of order (z / s)^k far in a tail (z the standardised
    # distance): both computations are good to about 1e-16 (1 + |z|)^k / s^k there
    z = (eta.abs().numpy() + max(abs(b) for b in (lower, upper) if math.isfinite(b))) / scale
    for col, ref in enumerate((lp, d1, -d2, -d3)):
        ref = ref.numpy()
        err = np.abs(got[:, col] - ref) / np.maximum(np.abs(ref), ((1 + z) / scale) ** col)
        assert err.max() < 1e-12, (col, err.max())


@needs_numba
def test_lapse_derivatives_match_the_likelihood(compiled_path):
    """The compiled lapse probit's log probability, derivatives and Fisher weight equal
    :class:`LapseProbitLikelihood`'s across its range (its negative exact weights included)."""
    from torchpref.inference import _compiled

    lik = LapseProbitLikelihood(0.3, 0.07).double()
    eta = torch.linspace(-12, 12, 121, dtype=D)
    lp, d1, d2 = lik.derivatives(eta)
    d3, fisher = lik.third_derivative(eta), lik.fisher(eta)
    s, eps = float(lik.scale), float(lik.lapse_rate)
    got = np.array([_compiled.lapse_probit.py_func(float(e), s, eps) for e in eta])
    assert (got[:, 2] < 0).any()  # the range reaches where the exact weight is negative
    for col, ref in enumerate((lp, d1, -d2, -d3, fisher)):
        ref = ref.detach().numpy()
        err = np.abs(got[:, col] - ref) / np.maximum(1.0, np.abs(ref))
        assert err.max() < 1e-12, (col, err.max())


def _data(seed: int, n: int):
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, 2, generator=g, dtype=D)
    u = torch.sin(5 * X[:, 0]) + X[:, 1]
    i = torch.randint(0, n, (2 * n,), generator=g)
    j = (i + torch.randint(1, n, (2 * n,), generator=g)) % n
    C = torch.stack([torch.where(u[i] > u[j], i, j), torch.where(u[i] > u[j], j, i)], -1)
    ties = torch.stack([torch.arange(0, n - 1, 3), torch.arange(1, n, 3)], -1)
    idx = torch.randperm(n, generator=g)[: n // 3]
    ratings = torch.special.ndtr(u[idx] / 1.5).clamp(0.02, 0.98)
    return X, C, ties, idx, ratings, u


def _models():
    """Each kind's model: ``(name, builder)``; builders take the data and return a model."""

    def session(X, C, T, idx, r, u):  # the session model: strict choices with ties offered, ties, Beta ratings
        return PreferenceGP(X, C, r, idx, ties=T, ties_offered=True, rating_precision=5.0)

    def ordinal(X, C, T, idx, r, u):  # ratings as levels 1..5 (the study's Likert answers)
        levels = (1 + (r * 5).floor().clamp(0, 4)).to(D)
        return PreferenceGP(X, C, levels, idx, ties=T, rating_levels=5, ties_offered=True)

    def person(X, C, T, idx, r, u):  # lapses on the comparisons, a person's gain and offset on the ratings
        model = PreferenceGP(X, C, r, idx, ties=T)
        return calibrate_person(model, rating_offset=0.3, rating_gain=1.4, lapse_rate=0.08)

    return [("session", session), ("ordinal", ordinal), ("person", person)]


@needs_numba
@pytest.mark.parametrize("seed,n", [(0, 9), (1, 40), (2, 120)])
@pytest.mark.parametrize("name,build", _models(), ids=[m[0] for m in _models()])
def test_each_kind_is_solved_compiled_and_agrees(name, build, seed, n, compiled_path):
    """The mode of each model is the compiled solver's (``mode.solver``) and equals the torch
    solver's: modes to 1e-9, ``B``'s factor and the weights to 1e-9 relative, the evidence to 1e-7."""
    data = _data(seed, n)
    out = {}
    for mode in ("off", "on"):
        with fast_path.fast_path(mode), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = build(*data)
            out[mode] = (model.mode, float(model.log_marginal_likelihood().detach()))
    (ref, e_ref), (got, e_got) = out["off"], out["on"]
    assert ref.solver == "torch" and got.solver == "compiled"
    assert float((got.f - ref.f).abs().max()) < 1e-9 * max(1.0, float(ref.f.abs().max()))
    assert float((got.M - ref.M).abs().max()) < 1e-9 * float(ref.M.abs().max())
    for w1, w0 in zip(got.weights, ref.weights):
        assert float((w1 - w0).abs().max()) < 1e-9 * max(1.0, float(w0.abs().max()))
    assert abs(e_got - e_ref) < 1e-7 * max(1.0, abs(e_ref))


@needs_numba
def test_a_model_that_offers_ties_is_fitted_compiled(compiled_path):
    """``fit_gpytorch_mll`` of a model with strict choices, ties and Beta ratings of precision 5 (its
    likelihood fixed): the compiled fit answers, and ends at least as high as BoTorch's routine on
    the torch solver (to 1e-6 relative)."""
    from gpytorch.kernels import RBFKernel, ScaleKernel
    from gpytorch.priors import GammaPrior, LogNormalPrior

    X, C, T, idx, r, _ = _data(5, 30)
    fitted = {}
    for mode in ("off", "on"):
        kernel = ScaleKernel(
            RBFKernel(ard_num_dims=2, lengthscale_prior=LogNormalPrior(1.76, 1.73)),
            outputscale_prior=GammaPrior(2.0, 1.0),
        ).to(D)
        model = PreferenceGP(X, C, r, idx, ties=T, ties_offered=True, rating_precision=5.0, covar_module=kernel)
        with fast_path.fast_path(mode), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fit_gpytorch_mll(LaplaceMarginalLogLikelihood(model))
            fitted[mode] = (model.last_fit, float(LaplaceMarginalLogLikelihood(model)().detach()))
    assert fitted["off"][0].solver == "torch" and fitted["on"][0].solver == "compiled"
    assert fitted["on"][0].status == "ok"
    assert fitted["on"][1] >= fitted["off"][1] - 1e-6 * abs(fitted["off"][1])


@needs_numba
def test_served_answers_are_answered_by_the_compiled_solver(compiled_path):
    """A session (the default model: strict choices where ties are offered, Beta ratings) told
    choices, a rating and a "no preference", each followed by the next question, as ``serve``
    does: every model that answered was solved by the compiled solver."""
    g = torch.Generator().manual_seed(0)
    X = torch.rand(30, 2, generator=g, dtype=D) * torch.tensor([100.0, 5.0], dtype=D)
    solvers = []
    with fast_path.fast_path("on"):
        session = PreferenceSession(X, seed=1)
        session.tell_choice(X[[0, 5, 10]], 1)
        solvers.append(session.model.mode.solver)
        session.tell_rating(X[3], 4)
        solvers.append(session.model.mode.solver)
        session.tell_no_preference(X[[20, 21]])
        solvers.append(session.model.mode.solver)
        for _ in range(3):
            q = session.ask()
            if q.kind == "rating":
                session.tell(q, 3)
            else:
                session.tell(q, 0)
            solvers.append(session.model.mode.solver)
        terms = {type(t.likelihood).__name__ for t in session.model._state().obs.terms}
    assert {"StrictPreferenceLikelihood", "TieLikelihood", "BetaRatingLikelihood"} <= terms
    assert solvers == ["compiled"] * len(solvers)


@needs_numba
@pytest.mark.parametrize("seed", range(6))
def test_hostile_ties_levels_and_lapses_agree_or_fall_back(seed, compiled_path):
    """Comparisons, ties and levels that contradict each other, a comparison noise of 1e-3 and a
    lapse rate of 0.3 (Newton meets the lapses' negative weights and takes Fisher steps), a
    prior mean far away: wherever the torch solver finds the mode, the compiled one finds the same
    (or hands the problem to the torch solver, whose answer it then is)."""
    from gpytorch.means import ConstantMean

    g = torch.Generator().manual_seed(100 + seed)
    n = 14
    X = torch.rand(n, 2, generator=g, dtype=D)
    C = torch.randint(0, n, (30, 2), generator=g)
    C = C[C[:, 0] != C[:, 1]]
    T = torch.cat([C[:4], C[:4].flip(-1)])  # ties of pairs also answered strictly, both ways
    levels = torch.randint(1, 6, (n,), generator=g).to(D)
    mean = ConstantMean().to(D).requires_grad_(False)
    mean.constant.fill_(5.0 * math.sin(seed))

    def build(kind: str):
        if kind == "levels":
            model = PreferenceGP(
                X,
                C,
                levels,
                torch.arange(n),
                ties=T,
                rating_levels=5,
                ties_offered=True,
                comparison_noise=1e-3,
                mean_module=mean,
            )
        else:
            model = PreferenceGP(X, C, ties=T, comparison_noise=1e-3, mean_module=mean)
            model = calibrate_person(model, lapse_rate=0.3)
        return model

    for kind in ("levels", "lapses"):
        out = {}
        for mode in ("off", "on"):
            with fast_path.fast_path(mode), warnings.catch_warnings():
                warnings.simplefilter("ignore")
                try:
                    model = build(kind)
                    out[mode] = (model.mode, float(model.log_marginal_likelihood().detach()))
                except Exception as err:  # the torch solver's own named errors, the same on both paths
                    out[mode] = type(err).__name__
        if isinstance(out["off"], str):
            assert out["on"] == out["off"]
            continue
        (ref, e_ref), (got, e_got) = out["off"], out["on"]
        assert float((got.f - ref.f).abs().max()) < 1e-8 * max(1.0, float(ref.f.abs().max())), kind
        assert abs(e_got - e_ref) < 1e-7 * max(1.0, abs(e_ref)), kind


def _learned_precision_model(X, C, T, idx, r, constraint: str):
    """A session-like model (strict choices with ties offered, ties, Beta ratings) whose rating
    precision is learned with a LogNormal prior, under GPyTorch's ``Interval`` (the library's
    default) or a ``GreaterThan`` constraint; the kernel's priors as BoTorch's."""
    from gpytorch.constraints import GreaterThan
    from gpytorch.kernels import RBFKernel, ScaleKernel
    from gpytorch.priors import GammaPrior, LogNormalPrior

    from torchpref.likelihoods.pairwise_beta import BetaRatingLikelihood
    from torchpref.models.defaults import PreferenceLikelihood

    kernel = ScaleKernel(
        RBFKernel(ard_num_dims=2, lengthscale_prior=LogNormalPrior(1.76, 1.73)), outputscale_prior=GammaPrior(2.0, 1.0)
    ).to(D)
    model = PreferenceGP(X, C, r, idx, ties=T, ties_offered=True, covar_module=kernel)
    lik = model.likelihood
    rating = BetaRatingLikelihood(
        1.0,
        12.0,
        learn=True,
        rating_precision_prior=LogNormalPrior(math.log(20.0), 1.0),
        rating_precision_constraint=GreaterThan(0.5) if constraint == "greater" else None,
    ).to(D)
    rating.raw_rating_scale.requires_grad_(False)
    model.likelihood = PreferenceLikelihood(lik.comparison, rating, lik.tie)
    return model


@needs_numba
@pytest.mark.parametrize("constraint", ["interval", "greater"])
def test_a_learned_rating_precision_loss_and_gradient_match_botorch_s(constraint, compiled_path):
    """With the Beta ratings' precision learned (and its prior), the compiled loss and its gradient
    in the raw parameters (lengthscales, outputscale, precision) equal BoTorch's loss ``-mll()`` and
    autograd through the torch solver (1e-10 and 1e-7), at a precision away from the start."""
    from torchpref.inference import fast_types
    from torchpref.models.fast_fit import compiled_problem

    X, C, T, idx, r, _ = _data(7, 25)
    model = _learned_precision_model(X, C, T, idx, r, constraint)
    model.likelihood.rating.rating_precision = 7.5
    mll = LaplaceMarginalLogLikelihood(model)
    problem = compiled_problem(mll)
    assert problem is not None and problem.spec.nu_index >= 0
    assert problem.spec.nu_transform == (fast_types.SIGMOID if constraint == "interval" else fast_types.SOFTPLUS)
    x = torch.cat([p.detach().reshape(-1) for p in problem.params.values()]).numpy()
    with fast_path.fast_path("off"):
        loss = -mll()
        grads = torch.autograd.grad(loss, list(problem.params.values()))
    state = fast_types.fit_state(problem.f0, problem.answers.first.shape[0])
    out = fast_path.call("fit_loss", x, problem.X, problem.answers, problem.spec, state, problem.tol, problem.max_iter)
    assert out.status == fast_types.OK
    assert abs(out.loss - float(loss.detach())) < 1e-10 * abs(float(loss.detach()))
    expected = torch.cat([g.reshape(-1) for g in grads]).numpy()
    assert abs(out.grad - expected).max() < 1e-7 * max(1.0, abs(expected).max()), (out.grad, expected)
    assert abs(expected[problem.spec.nu_index]) > 1e-3  # the precision's gradient is not trivially zero


@needs_numba
def test_a_learned_rating_precision_is_fitted_compiled(compiled_path):
    """``fit_gpytorch_mll`` of a model whose rating precision is learned with a prior: the compiled
    fit answers and ends at least as high as BoTorch's routine on the torch solver (1e-6
    relative), at the same precision (1e-2 relative)."""
    X, C, T, idx, r, _ = _data(8, 30)
    fitted = {}
    for mode in ("off", "on"):
        model = _learned_precision_model(X, C, T, idx, r, "interval")
        with fast_path.fast_path(mode), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fit_gpytorch_mll(LaplaceMarginalLogLikelihood(model))
            value = float(LaplaceMarginalLogLikelihood(model)().detach())
        fitted[mode] = (model.last_fit, value, float(model.likelihood.rating.rating_precision))
    assert fitted["off"][0].solver == "torch" and fitted["on"][0].solver == "compiled", fitted
    assert fitted["on"][1] >= fitted["off"][1] - 1e-6 * abs(fitted["off"][1])
    assert abs(fitted["on"][2] - fitted["off"][2]) < 1e-2 * fitted["off"][2]
    assert abs(fitted["on"][2] - 12.0) > 0.1  # the precision moved
