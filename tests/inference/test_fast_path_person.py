"""The compiled path for a population's person model (issue 42): a prior mean (the population's,
entering the solve as each answer's offset) and Beta ratings besides the comparisons. The torch
solver is the reference: the modes agree to 1e-9 and the evidence to 1e-7, and the compiled
Newton takes the torch solver's iterates, Fisher steps included, on hostile Beta ratings."""

import math
import warnings

import pytest
import torch

from torchpref import PreferenceGP
from torchpref.data.preference_data import PreferenceData
from torchpref.inference import fast_path
from torchpref.models.defaults import default_covar_module
from torchpref.models.recipe import NO_TIES_OFFERED
from torchpref.population.fit import fit_population

D = torch.float64
needs_numba = pytest.mark.skipif(not fast_path.available(), reason="numba is not installed (the fast extra)")


@pytest.fixture(scope="module")
def compiled_path():
    with fast_path.fast_path("on"):
        functions = fast_path.warm_up()
    assert functions is not None, fast_path.status()
    return functions


def _person(seed: int, n: int, ratings: int) -> PreferenceData:
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, 2, generator=g, dtype=D)
    u = torch.sin(5 * X[:, 0]) + X[:, 1]
    i = torch.randint(0, n, (2 * n,), generator=g)
    j = (i + torch.randint(1, n, (2 * n,), generator=g)) % n
    first = u[i] + 0.3 * torch.randn(2 * n, generator=g, dtype=D) > u[j]
    C = torch.stack([torch.where(first, i, j), torch.where(first, j, i)], -1)
    idx = torch.randperm(n, generator=g)[:ratings]
    r = torch.sigmoid(u[idx] + 0.2 * torch.randn(ratings, generator=g, dtype=D)).clamp(0.02, 0.98)
    return PreferenceData.create(X, C, r, idx)


@pytest.fixture(scope="module")
def population():
    k_m, k_g = default_covar_module(2).double(), default_covar_module(2).double()
    k_m.base_kernel.lengthscale, k_m.outputscale = 0.4, 1.3
    k_g.base_kernel.lengthscale, k_g.outputscale = 0.6, 0.5
    people = [_person(s, 8, 3) for s in range(6)]
    # choices without a "no preference" option: plain probit comparisons, which the compiled path
    # computes (a strict choice where ties are offered is the tie model's category: the torch solver's)
    return fit_population(people, k_m=k_m, k_g=k_g, fit=False, model=NO_TIES_OFFERED)


def _solve(model_of, mode: str):
    calls = []
    real = fast_path.call

    def counted(name, *args):
        out = real(name, *args)
        calls.append(out is not None and out.status == 0)
        return out

    fast_path.call = counted
    try:
        with fast_path.fast_path(mode), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = model_of()
            m = model.mode
            value = float(model.log_marginal_likelihood().detach())
    finally:
        fast_path.call = real
    return m, value, calls


@needs_numba
@pytest.mark.parametrize("seed,n,ratings", [(10, 20, 5), (11, 60, 15), (12, 120, 30), (13, 7, 7)])
def test_a_person_model_takes_the_compiled_path_and_agrees(seed, n, ratings, population, compiled_path):
    """A person model with comparisons and Beta ratings: the mode is solved compiled (offset by the
    population's mean), and agrees with the torch solver's: modes to 1e-9, ``B``'s factor and the
    weights to 1e-9 relative, the evidence to 1e-7."""
    data = _person(seed, n, ratings)
    ref, e_ref, off_calls = _solve(lambda: population.person_model(data), "off")
    got, e_got, on_calls = _solve(lambda: population.person_model(data), "on")
    assert off_calls == [] and on_calls and all(on_calls)
    assert float((got.f - ref.f).abs().max()) < 1e-9
    assert float((got.M - ref.M).abs().max()) < 1e-9 * float(ref.M.abs().max())
    for w1, w0 in zip(got.weights, ref.weights):
        assert float((w1 - w0).abs().max()) < 1e-9 * max(1.0, float(w0.abs().max()))
    assert abs(e_got - e_ref) < 1e-7 * max(1.0, abs(e_ref))


@needs_numba
@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("nu", [5.0, 200.0])
def test_hostile_beta_ratings_agree_or_fall_back(seed, nu, compiled_path):
    """Ratings at 0.01 and 0.99 of items far apart, a prior mean far from them, precisions from 5
    to 200 (Newton meets an indefinite Hessian and takes Fisher steps): wherever the torch solver
    finds the mode, the compiled one finds the same (or hands the problem to the torch solver)."""
    from gpytorch.means import ConstantMean

    g = torch.Generator().manual_seed(seed)
    n = 15
    X = torch.rand(n, 2, generator=g, dtype=D)
    r = torch.where(torch.rand(n, generator=g) > 0.5, 0.99, 0.01).to(D)
    mean = ConstantMean().to(D).requires_grad_(False)
    mean.constant.fill_(4.0 * math.cos(seed))

    def model():
        return PreferenceGP(
            X,
            torch.tensor([[0, 1], [2, 3]]),
            r,
            torch.arange(n),
            mean_module=mean,
            rating_precision=nu,
            rating_scale=0.3,
        )

    try:
        ref, e_ref, _ = _solve(model, "off")
    except Exception as err:  # the torch solver's own, named errors: nothing to compare
        pytest.skip(f"the torch solver raises {type(err).__name__}")
    got, e_got, calls = _solve(model, "on")
    assert calls  # the compiled path was tried
    assert float((got.f - ref.f).abs().max()) < 1e-9 * max(1.0, float(ref.f.abs().max()))
    assert abs(e_got - e_ref) < 1e-7 * max(1.0, abs(e_ref))


@needs_numba
def test_beta_derivatives_match_the_likelihood(compiled_path):
    """The compiled Beta rating's log density, derivatives and Fisher weight equal
    :class:`BetaRatingLikelihood`'s (which are tested against autograd) across the link's range."""
    import numpy as np

    from torchpref.inference import _compiled
    from torchpref.likelihoods.pairwise_beta import BetaRatingLikelihood

    lik = BetaRatingLikelihood(0.7, 30.0).double()
    eta = torch.linspace(-40, 40, 161, dtype=D)
    u = torch.full_like(eta, 0.83)
    lp, d1, d2 = lik.derivatives(eta, u)
    d3, fisher = lik.third_derivative(eta, u), lik.fisher(eta)
    c, nu = math.sqrt(2) * float(lik.rating_scale), float(lik.rating_precision)  # as stored (constrained)
    got = np.array([_compiled.beta_rating.py_func(float(e), 0.83, c, nu) for e in eta])
    for col, ref in enumerate((lp, d1, -d2, -d3, fisher)):
        # relative to each value; the weights and their slope through torch's trigamma, good to about 1e-9
        err = np.abs(got[:, col] - ref.numpy()) / np.maximum(1.0, np.abs(ref.numpy()))
        assert err.max() < (1e-12 if col < 2 else 1e-7), (col, err.max())
