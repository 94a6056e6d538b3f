"""The person's likelihoods (learned rating offset, gain and noise; comparison lapses): closed-form
derivatives against autograd and SciPy, the evidence's gradient against finite differences, the
calibration fit and its rollback."""

import math

import numpy as np
import pytest
import torch
from scipy import stats

from torchpref import PreferenceGP
from torchpref.likelihoods.pairwise_beta import BetaRatingLikelihood, PairwiseProbitLikelihood
from torchpref.likelihoods.person import LapseProbitLikelihood, PersonRatingLikelihood
from torchpref.models.calibration import calibrate_person, fit_person, person_parameters
from torchpref.testing import assert_evidence_gradient

SQRT2 = math.sqrt(2.0)


def autograd_123(fn, eta):
    eta = eta.clone().requires_grad_(True)
    y = fn(eta)
    (d1,) = torch.autograd.grad(y.sum(), eta, create_graph=True)
    (d2,) = torch.autograd.grad(d1.sum(), eta, create_graph=True)
    (d3,) = torch.autograd.grad(d2.sum(), eta)
    return y.detach(), d1.detach(), d2.detach(), d3


@pytest.mark.parametrize("eps", [1e-4, 0.05, 0.3])
@pytest.mark.parametrize("sigma_R", [0.05, 0.5])
def test_lapse_probit_against_scipy_and_autograd(eps, sigma_R):
    lik = LapseProbitLikelihood(sigma_R, eps)
    z = torch.cat([torch.linspace(-8, 8, 65, dtype=torch.float64), torch.tensor([-30.0, 25.0], dtype=torch.float64)])
    eta = z * SQRT2 * sigma_R
    lp, d1, d2 = (t.detach() for t in lik.derivatives(eta))
    p = eps / 2 + (1 - eps) * stats.norm.cdf(z.numpy())
    np.testing.assert_allclose(lp.numpy(), np.log(p), rtol=1e-6, atol=1e-12)  # eps is stored through its constraint
    _, a1, a2, a3 = autograd_123(lambda e: lik.log_prob(e), eta)
    scale = torch.as_tensor(1 / (SQRT2 * sigma_R))
    torch.testing.assert_close(d1, a1, rtol=1e-9, atol=1e-10 * scale)
    torch.testing.assert_close(d2, a2, rtol=1e-8, atol=1e-9 * scale**2)
    torch.testing.assert_close(lik.third_derivative(eta).detach(), a3, rtol=1e-7, atol=1e-8 * scale**3)
    # Fisher: p'^2 / (p (1 - p)), p' from SciPy's density
    dp = (1 - eps) * stats.norm.pdf(z.numpy()) / (SQRT2 * sigma_R)
    np.testing.assert_allclose(lik.fisher(eta).detach().numpy(), dp**2 / (p * (1 - p)), rtol=1e-6, atol=1e-300)
    assert (lik.fisher(eta) >= 0).all()
    # the floor makes the exact weight negative in the far left tail (not log-concave)
    assert not lik.log_concave and bool((d2 > 0).any())


def test_lapse_probit_reduces_to_probit_and_predicts():
    lik, base = LapseProbitLikelihood(0.2, 1e-6, lapse_rate_prior=False), PairwiseProbitLikelihood(0.2)
    eta = torch.linspace(-0.5, 2, 9, dtype=torch.float64)  # Phi(z) >= 0.04 >> eps / 2
    for a, b in zip(lik.derivatives(eta), base.derivatives(eta)):
        torch.testing.assert_close(a.detach(), b, rtol=1e-4, atol=1e-6)
    lik.lapse_rate = 0.2
    m, v = torch.tensor([0.3, -1.0], dtype=torch.float64), torch.tensor([0.2, 0.5], dtype=torch.float64)
    x = stats.norm.rvs(size=(400_000, 2), random_state=1) * np.sqrt(v.numpy()) + m.numpy()
    mc = (0.1 + 0.8 * stats.norm.cdf(x / (SQRT2 * 0.2))).mean(0)
    np.testing.assert_allclose(lik.preference_probability(m, v).detach().numpy(), mc, atol=3e-3)


@pytest.mark.parametrize("gain,offset", [(1.0, 0.0), (1.6, 0.4), (0.6, -0.5)])
def test_person_rating_against_scipy_and_autograd(gain, offset, generator):
    lik = PersonRatingLikelihood(0.8, 25.0, offset, gain)
    eta = torch.linspace(-2.5, 2.5, 21, dtype=torch.float64)
    u = 0.05 + 0.9 * torch.rand(21, generator=generator, dtype=torch.float64)
    mu = stats.norm.cdf((gain * eta.numpy() + offset) / (SQRT2 * 0.8))
    ref = stats.beta.logpdf(u.numpy(), 25 * mu, 25 * (1 - mu))
    lp, d1, d2 = (t.detach() for t in lik.derivatives(eta, u))
    np.testing.assert_allclose(lp.numpy(), ref, rtol=1e-7, atol=1e-7)
    _, a1, a2, a3 = autograd_123(lambda e: lik.log_prob(e, u), eta)
    torch.testing.assert_close(d1, a1, rtol=1e-8, atol=1e-8)
    torch.testing.assert_close(d2, a2, rtol=1e-8, atol=1e-8)
    torch.testing.assert_close(lik.third_derivative(eta, u).detach(), a3, rtol=1e-7, atol=1e-7)
    # the person's predictive mean rating, against quadrature; the reference one ignores g and b
    m, v = torch.tensor([0.4], dtype=torch.float64), torch.tensor([0.3], dtype=torch.float64)
    x, w = np.polynomial.hermite_e.hermegauss(60)
    f = 0.4 + math.sqrt(0.3) * x
    quad = (w * stats.norm.cdf((gain * f + offset) / (SQRT2 * 0.8))).sum() / w.sum()
    assert abs(float(lik.expected_rating(m, v)) - quad) < 1e-10
    quad0 = (w * stats.norm.cdf(gain * f / (SQRT2 * 0.8))).sum() / w.sum()
    assert abs(float(lik.unbiased_rating(m, v)) - quad0) < 1e-10


def test_person_rating_unit_gain_is_the_beta_likelihood():
    lik, base = PersonRatingLikelihood(0.8, 40.0), BetaRatingLikelihood(0.8, 40.0)
    eta = torch.linspace(-3, 3, 13, dtype=torch.float64)
    u = torch.full_like(eta, 0.3)
    for a, b in zip(lik.derivatives(eta, u), base.derivatives(eta, u)):
        torch.testing.assert_close(a.detach(), b, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(lik.fisher(eta).detach(), base.fisher(eta))
    torch.testing.assert_close(
        lik.predictive_log_density(u, eta, torch.full_like(eta, 0.2)).detach(),
        base.predictive_log_density(u, eta, torch.full_like(eta, 0.2)),
    )


def _model(generator, lapse_flip=True):
    X = torch.rand(12, 2, generator=generator, dtype=torch.float64)
    f = torch.sin(4 * X[:, 0]) + X[:, 1]
    pairs = [(0, 1), (2, 3), (4, 5), (6, 7), (1, 8), (3, 9), (5, 10), (7, 11)]
    comps = torch.tensor([[i, j] if f[i] > f[j] else [j, i] for i, j in pairs])
    if lapse_flip:
        comps[0] = comps[0].flip(0)
    r = torch.special.ndtr((1.3 * f[:8] + 0.4) / (SQRT2 * 0.8)).clamp(0.02, 0.98)
    return PreferenceGP(
        X, comps, ratings=r, rating_index=torch.arange(8), comparison_noise=0.2, rating_scale=0.8, rating_precision=20.0
    )


def test_person_evidence_gradient_matches_finite_differences(generator):
    model = calibrate_person(_model(generator), rating_offset=0.1, rating_gain=1.2, lapse_rate=0.1)
    params = person_parameters(model)
    assert len(params) == 4
    assert_evidence_gradient(model, params)
    # and with the kernel's parameters learned at the same time
    assert_evidence_gradient(model, {"raw_lengthscale": model.covar_module.base_kernel.raw_lengthscale})


def test_calibrate_person_keeps_the_posterior_at_unit_gain(generator):
    model = _model(generator, lapse_flip=False)
    mean0 = model.posterior(model.train_X).mean.detach()
    calibrate_person(model, lapse_rate=1e-6)
    torch.testing.assert_close(model.posterior(model.train_X).mean.detach(), mean0, rtol=1e-4, atol=1e-5)


def test_calibrate_person_rejects_ordinal_models_and_fit_needs_calibration(generator):
    X = torch.rand(4, 1, generator=generator, dtype=torch.float64)
    ordinal = PreferenceGP(X, torch.tensor([[0, 1]]), ratings=torch.tensor([2.0]), rating_index=[2], rating_levels=5)
    with pytest.raises(ValueError, match="levels"):
        calibrate_person(ordinal)
    with pytest.raises(ValueError, match="calibrate_person"):
        fit_person(_model(generator))


def test_fit_person_moves_towards_the_truth_and_restores_on_failure(generator):
    model = calibrate_person(_model(generator))
    before = -float(model.log_marginal_likelihood())
    fit_person(model, max_iter=30)
    lik = model.likelihood
    # the ratings were made with g 1.3 (b 0.4, which 8 ratings of 12 items barely tell from the utility's level)
    assert float(lik.rating.rating_gain) > 1.1
    assert -float(model.log_marginal_likelihood()) < before
    # at the MAP: the objective's gradient in the person's parameters vanishes
    from torchpref.models.preference_gp import LaplaceMarginalLogLikelihood

    grads = torch.autograd.grad(LaplaceMarginalLogLikelihood(model)(), list(person_parameters(model).values()))
    assert max(float(g.abs()) for g in grads) < 1e-3
    lik.rating.rating_offset, lik.rating.rating_gain = 0.5, 0.7  # away from the MAP: the fit moves them
    saved = {k: p.detach().clone() for k, p in person_parameters(model).items()}

    class Boom(RuntimeError):
        pass

    orig = model.log_marginal_likelihood
    calls = []

    def failing():
        calls.append(1)
        if len(calls) > 2:
            raise Boom("interrupted")
        return orig()

    model.log_marginal_likelihood = failing
    with pytest.raises(Boom):
        fit_person(model)
    del model.log_marginal_likelihood
    for k, p in person_parameters(model).items():
        torch.testing.assert_close(p.detach(), saved[k])
    assert all(p.requires_grad for p in model.covar_module.parameters())
