"""Likelihoods (eqs. 3-7, 11): closed-form derivatives vs autograd, predictives vs quadrature."""

import math

import numpy as np
import pytest
import torch
from scipy import integrate, special, stats

from torchpref.likelihoods.pairwise_beta import BetaRatingLikelihood, PairwiseProbitLikelihood
from torchpref.testing import rand, randn

SQRT2 = math.sqrt(2.0)


def autograd_derivatives(fn, eta):
    """``fn(eta)`` (elementwise), its first and second derivatives by autograd."""
    eta = eta.clone().requires_grad_(True)
    y = fn(eta)
    (d1,) = torch.autograd.grad(y.sum(), eta, create_graph=True)
    (d2,) = torch.autograd.grad(d1.sum(), eta)
    return y.detach(), d1.detach(), d2


# ---------------------------------------------------------------- probit (eq. 3)
@pytest.mark.parametrize("sigma_R", [1e-3, 0.05, 0.2, 1.0, 10.0])
def test_probit_derivatives_match_autograd(sigma_R):
    lik = PairwiseProbitLikelihood(sigma_R)
    s = SQRT2 * sigma_R
    # z = eta / s from deep left tail through the centre to the right tail (+-8 "sigma" and more)
    z = torch.cat(
        [
            torch.linspace(-8.0, 8.0, 81, dtype=torch.float64),
            torch.tensor([-30.0, -15.0, -10.0, 10.0, 15.0], dtype=torch.float64),
        ]
    )
    eta = z * s
    lp, d1, d2 = lik.derivatives(eta)
    # log p against SciPy, derivatives against autograd of the documented closed form
    np.testing.assert_allclose(lp.numpy(), special.log_ndtr(z.numpy()), rtol=1e-12, atol=0)
    ref_lp, ref_d1, ref_d2 = autograd_derivatives(lambda e: torch.special.log_ndtr(e / s), eta)
    torch.testing.assert_close(lp, ref_lp, rtol=1e-12, atol=0)
    torch.testing.assert_close(d1, ref_d1, rtol=1e-9, atol=1e-300)
    torch.testing.assert_close(d2, ref_d2, rtol=1e-7, atol=1e-300)
    assert (d2 < 0).all(), "the probit log-likelihood is strictly log-concave"
    torch.testing.assert_close(lik.fisher(eta), -d2)
    # log_prob agrees with derivatives()[0]
    torch.testing.assert_close(lik.log_prob(eta), lp)


def test_probit_derivatives_far_tail_asymptotics():
    """For z -> -inf: d log Phi / dz ~ -z, d2 ~ -1 (no cancellation to 0 or NaN)."""
    lik = PairwiseProbitLikelihood(1.0 / SQRT2)  # s = 1
    z = torch.tensor([-40.0, -100.0, -1e3], dtype=torch.float64)
    lp, d1, d2 = lik.derivatives(z)
    assert torch.isfinite(lp).all() and torch.isfinite(d1).all() and torch.isfinite(d2).all()
    torch.testing.assert_close(d1, -z * (1 + 1 / z**2), rtol=1e-3, atol=0)  # Mills ratio expansion
    torch.testing.assert_close(d2, -torch.ones_like(z), rtol=2e-3, atol=0)


def test_probit_forward_and_marginal(generator):
    lik = PairwiseProbitLikelihood(0.3)
    f = randn(6, generator=generator)
    C = torch.tensor([[0, 1], [2, 5], [4, 3]])
    probs = lik.forward(f, C).probs
    expected = stats.norm.cdf((f[C[:, 0]] - f[C[:, 1]]).numpy() / (SQRT2 * 0.3))
    np.testing.assert_allclose(probs.numpy(), expected, rtol=1e-12)


@pytest.mark.parametrize("sigma_R", [0.05, 0.5, 2.0])
@pytest.mark.parametrize("m,v", [(0.0, 0.5), (0.7, 0.1), (-1.3, 2.0), (2.5, 1e-6)])
def test_preference_probability_vs_quadrature(sigma_R, m, v):
    lik = PairwiseProbitLikelihood(sigma_R)
    s = SQRT2 * sigma_R

    def integrand(x):
        return stats.norm.cdf(x / s) * stats.norm.pdf(x, m, math.sqrt(v))

    sd = math.sqrt(v)
    ref, _ = integrate.quad(
        integrand,
        m - 12 * sd,
        m + 12 * sd,
        epsabs=1e-13,
        epsrel=1e-12,
        points=[0.0] if abs(m) < 12 * sd else None,
        limit=200,
    )
    got = lik.preference_probability(torch.tensor(m, dtype=torch.float64), torch.tensor(v, dtype=torch.float64))
    assert abs(float(got) - ref) < 1e-9


def test_probit_marginal_uses_joint_covariance(generator):
    from gpytorch.distributions import MultivariateNormal

    lik = PairwiseProbitLikelihood(0.4)
    mean = randn(3, generator=generator)
    A = randn(3, 3, generator=generator)
    S = A @ A.T + 0.1 * torch.eye(3, dtype=torch.float64)
    C = torch.tensor([[0, 1], [2, 0]])
    # Monte Carlo with a fixed generator against the analytic marginal
    draws = mean + randn(400_000, 3, generator=generator) @ torch.linalg.cholesky(S).T
    mc = torch.special.ndtr((draws[:, C[:, 0]] - draws[:, C[:, 1]]) / (SQRT2 * 0.4)).mean(0)
    got = lik.marginal(MultivariateNormal(mean, S), C).probs
    torch.testing.assert_close(got, mc, rtol=0, atol=3e-3)
    # and the exact closed form with the pair's covariance
    i, j = C[:, 0], C[:, 1]
    var = S[i, i] + S[j, j] - 2 * S[i, j]
    exact = torch.special.ndtr((mean[i] - mean[j]) / torch.sqrt(2 * 0.16 + var))
    torch.testing.assert_close(got, exact, rtol=1e-12, atol=0)


# ------------------------------------------------------------ Beta rating (eqs. 4-7)
BETA_PARAMS = [(1.0, 80.0), (0.8, 60.0), (0.3, 5.0), (2.0, 1000.0), (0.5, 1.0)]


def beta_logpdf_reference(eta, u, sigma_B, nu):
    """The documented formula: alpha = nu mu, beta = nu (1 - mu), mu = Phi(eta / (sqrt2 sigma_B))."""
    t = np.asarray(eta) / (SQRT2 * sigma_B)
    mu, one_minus_mu = np.exp(special.log_ndtr(t)), np.exp(special.log_ndtr(-t))  # no 1 - 1 = 0
    return stats.beta.logpdf(u, nu * mu, nu * one_minus_mu)


@pytest.mark.parametrize("sigma_B,nu", BETA_PARAMS)
def test_beta_log_prob_is_documented_formula(sigma_B, nu, generator):
    lik = BetaRatingLikelihood(sigma_B, nu)
    eta = 2.0 * sigma_B * randn(50, generator=generator)
    u = rand(50, generator=generator, low=0.01, high=0.99)
    ref = beta_logpdf_reference(eta.numpy(), u.numpy(), sigma_B, nu)
    np.testing.assert_allclose(lik.log_prob(eta, u).numpy(), ref, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(lik.forward(eta).log_prob(u).numpy(), ref, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(lik.derivatives(eta, u)[0].numpy(), ref, rtol=1e-10, atol=1e-10)
    # the forward distribution's shape parameters themselves
    d = lik.forward(eta)
    mu = stats.norm.cdf(eta.numpy() / (SQRT2 * sigma_B))
    np.testing.assert_allclose(d.concentration1.numpy(), nu * mu, rtol=1e-12)
    np.testing.assert_allclose(d.concentration0.numpy(), nu * (1 - mu), rtol=1e-12)
    np.testing.assert_allclose(d.mean.numpy(), mu, rtol=1e-12)
    np.testing.assert_allclose(lik.mean_link(eta).numpy(), mu, rtol=1e-12)


@pytest.mark.parametrize("sigma_B,nu", BETA_PARAMS)
@pytest.mark.parametrize("u", [1e-3, 0.1, 0.5, 0.77, 0.999])
def test_beta_derivatives_match_autograd(sigma_B, nu, u):
    lik = BetaRatingLikelihood(sigma_B, nu)
    c = SQRT2 * sigma_B
    # t = eta / c over [-8, 8] (mu from 6e-16 to 1 - 6e-16) plus the centre densely
    t = torch.linspace(-8.0, 8.0, 65, dtype=torch.float64)
    eta = t * c
    uu = torch.full_like(eta, u)
    lp, d1, d2 = lik.derivatives(eta, uu)

    def ref(e):
        tt = e / c
        # torch.special.ndtr(-8) is only good to 2% (6.11e-16 vs 6.22e-16): go through log_ndtr
        a = nu * torch.exp(torch.special.log_ndtr(tt))
        b = nu * torch.exp(torch.special.log_ndtr(-tt))
        nu_t = torch.tensor(nu, dtype=torch.float64)
        return (a - 1) * math.log(u) + (b - 1) * math.log1p(-u) + torch.lgamma(nu_t) - torch.lgamma(a) - torch.lgamma(b)

    r0, r1, r2 = autograd_derivatives(ref, eta)
    ok = torch.isfinite(r2)  # autograd itself loses it once a or b underflows
    assert ok[16:49].all()  # |t| <= 4 must be finite in the reference
    torch.testing.assert_close(lp[ok], r0[ok], rtol=1e-9, atol=1e-9)
    scale1 = r1[ok].abs().max()
    scale2 = r2[ok].abs().max()
    torch.testing.assert_close(d1[ok], r1[ok], rtol=1e-7, atol=1e-9 * scale1)
    torch.testing.assert_close(d2[ok], r2[ok], rtol=1e-6, atol=1e-9 * scale2)
    assert torch.isfinite(d1).all() and torch.isfinite(d2).all(), "NaN/inf in the tails"


@pytest.mark.parametrize("sigma_B,nu", BETA_PARAMS)
@pytest.mark.parametrize("t", [-2.5, -0.7, 0.0, 0.4, 1.8])
def test_beta_fisher_is_expected_negative_hessian(sigma_B, nu, t):
    """fisher(eta) = E_u[-d2 log p / d eta2] under u ~ Beta(a, b), by quadrature in u."""
    lik = BetaRatingLikelihood(sigma_B, nu)
    eta = torch.tensor(t * SQRT2 * sigma_B, dtype=torch.float64)
    mu = stats.norm.cdf(t)
    a, b = nu * mu, nu * (1 - mu)

    # -d2 log p / d eta2 is affine in x = logit(u) (u enters only through log u - log(1 - u)):
    # read it off the library at two points, check a third, then take E[x] by quadrature.
    def neg_d2(x):
        return -float(lik.derivatives(eta, torch.tensor(special.expit(x), dtype=torch.float64))[2])

    A, B = neg_d2(0.0), neg_d2(1.0) - neg_d2(0.0)
    assert abs(neg_d2(-2.5) - (A - 2.5 * B)) <= 1e-9 * (abs(A) + abs(B))

    def density(x):  # Beta density of u = expit(x) times du/dx, in log space
        return math.exp(a * special.log_expit(x) + b * special.log_expit(-x) - special.betaln(a, b))

    total, _ = integrate.quad(density, -np.inf, np.inf, epsabs=0, epsrel=1e-12, limit=500)
    mean_x, _ = integrate.quad(lambda x: x * density(x), -np.inf, np.inf, epsabs=1e-13, epsrel=1e-12, limit=500)
    assert abs(total - 1) < 1e-9
    ref = A + B * mean_x
    err = None
    got = float(lik.fisher(eta))
    assert got >= 0
    assert abs(got - ref) <= 1e-7 * abs(ref) + 1e-12, (got, ref, err)


def test_beta_fisher_monte_carlo(generator):
    lik = BetaRatingLikelihood(0.8, 60.0)
    eta = torch.tensor([-1.0, 0.2, 1.5], dtype=torch.float64)
    d = lik.forward(eta)
    torch.manual_seed(0)  # torch.distributions.Beta has no generator argument
    u = d.sample((200_000,))
    neg_h = -lik.derivatives(eta.expand_as(u), u)[2]
    mc, se = neg_h.mean(0), neg_h.std(0) / math.sqrt(u.shape[0])
    assert ((lik.fisher(eta) - mc).abs() < 5 * se).all()


@pytest.mark.parametrize("sigma_B", [0.3, 0.8, 2.0])
@pytest.mark.parametrize("m,v", [(0.0, 1.0), (0.9, 0.05), (-1.7, 3.0), (3.0, 1e-8)])
def test_expected_rating_vs_quadrature(sigma_B, m, v):
    lik = BetaRatingLikelihood(sigma_B, 50.0)
    sd = math.sqrt(v)
    ref, _ = integrate.quad(
        lambda f: stats.norm.cdf(f / (SQRT2 * sigma_B)) * stats.norm.pdf(f, m, sd),
        m - 12 * sd,
        m + 12 * sd,
        epsabs=1e-13,
        epsrel=1e-12,
        limit=200,
    )
    got = lik.expected_rating(torch.tensor(m, dtype=torch.float64), torch.tensor(v, dtype=torch.float64))
    assert abs(float(got) - ref) < 1e-9
    # the moment-matched marginal has exactly this mean
    from gpytorch.distributions import MultivariateNormal

    mvn = MultivariateNormal(torch.tensor([m], dtype=torch.float64), torch.tensor([[v]], dtype=torch.float64))
    assert abs(float(lik.marginal(mvn).mean) - ref) < 1e-9


def log_predictive_density_reference(u, m, v, sigma_B, nu, half_width=40.0, num=2_000_001):
    """``log int Beta(u; f) N(f; m, v) df`` on a dense grid in log space (robust in the tails)."""
    sd = math.sqrt(v)
    f = np.linspace(m - half_width * sd, m + half_width * sd, num)
    t = f / (SQRT2 * sigma_B)
    a, b = nu * np.exp(special.log_ndtr(t)), nu * np.exp(special.log_ndtr(-t))
    lg = (
        (a - 1) * math.log(u)
        + (b - 1) * math.log1p(-u)
        + special.gammaln(nu)
        - special.gammaln(a)
        - special.gammaln(b)
        + stats.norm.logpdf(f, m, sd)
    )
    return float(special.logsumexp(lg) + math.log(f[1] - f[0]))


@pytest.mark.parametrize("sigma_B,nu", [(1.0, 80.0), (0.8, 60.0), (0.4, 200.0), (0.3, 5.0)])
@pytest.mark.parametrize(
    "u,m,v",
    [
        (0.5, 0.0, 0.3),
        (0.8, 1.0, 0.05),
        (0.2, 0.3, 0.5),
        (0.65, 0.5, 0.01),
        (0.5, 0.0, 1.0),
        (0.9, 1.0, 4.0),
        (0.02, 1.0, 0.01),
    ],
)
def test_predictive_log_density_vs_quadrature(sigma_B, nu, u, m, v):
    """Against scipy.integrate.quad of Beta pdf x normal pdf, and a dense log-space grid.

    v = 1 (the prior variance) is where plain Gauss-Hermite over N(m, v) with 40 nodes was off
    by 0.1-2 nats: the Beta factor is far narrower in f than the posterior.
    """
    lik = BetaRatingLikelihood(sigma_B, nu)
    ref = log_predictive_density_reference(u, m, v, sigma_B, nu)
    sd = math.sqrt(v)
    if ref > -30:  # quad in linear space is only meaningful when the integral is not tiny

        def integrand(f):
            val = math.exp(beta_logpdf_reference(f, u, sigma_B, nu)) * stats.norm.pdf(f, m, sd)
            return val if math.isfinite(val) else 0.0  # a or b underflowed to 0: density 0

        f_star = SQRT2 * sigma_B * stats.norm.ppf(u)  # the Beta factor peaks near here
        pts = [x for x in (f_star,) if m - 12 * sd < x < m + 12 * sd]
        q, _ = integrate.quad(
            integrand, m - 12 * sd, m + 12 * sd, points=pts or None, epsabs=0, epsrel=1e-11, limit=1000
        )
        assert abs(math.log(q) - ref) < 1e-6
    args = (torch.tensor(x, dtype=torch.float64) for x in (u, m, v))
    got = lik.predictive_log_density(*args)  # default number of nodes
    assert abs(float(got) - ref) < 1e-5, (float(got), ref)  # 40 adaptive nodes: ~1e-6 at v = 4


def test_predictive_log_density_batched_and_degenerate(generator):
    lik = BetaRatingLikelihood(0.8, 60.0)
    u = rand(4, 1, generator=generator, low=0.1, high=0.9)
    m = randn(3, generator=generator)
    v = rand(3, generator=generator, low=0.05, high=1.0)
    got = lik.predictive_log_density(u, m, v)
    assert got.shape == (4, 3)
    for i in range(4):
        for j in range(3):
            ref = log_predictive_density_reference(float(u[i, 0]), float(m[j]), float(v[j]), 0.8, 60.0, num=200_001)
            assert abs(float(got[i, j]) - ref) < 1e-6
    # zero variance: the likelihood itself
    zero = lik.predictive_log_density(u[:, 0], m[0], torch.zeros((), dtype=torch.float64))
    torch.testing.assert_close(zero, lik.log_prob(m[0], u[:, 0]))


# ------------------------------------------------------- parameters and their gradients
def test_parameters_constraints_and_validation():
    lik = BetaRatingLikelihood(0.8, 60.0)
    assert float(lik.rating_scale) == pytest.approx(0.8, rel=1e-12)
    assert float(lik.rating_precision) == pytest.approx(60.0, rel=1e-12)
    assert not lik.raw_rating_scale.requires_grad
    lik.rating_precision = 123.0
    assert float(lik.rating_precision) == pytest.approx(123.0, rel=1e-12)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="rating_scale"):
            lik.rating_scale = bad
        with pytest.raises(ValueError, match="comparison_noise"):
            PairwiseProbitLikelihood(bad)
    assert PairwiseProbitLikelihood(0.2, learn=True).raw_comparison_noise.requires_grad


def test_probit_parameter_gradient_vs_finite_differences():
    lik = PairwiseProbitLikelihood(0.3, learn=True)
    eta = torch.tensor([-1.0, -0.1, 0.2, 2.0], dtype=torch.float64)
    val = lik.log_prob(eta).sum()
    (g,) = torch.autograd.grad(val, [lik.raw_comparison_noise])
    raw = float(lik.raw_comparison_noise.detach())
    h = 1e-6

    def at(r):
        l2 = PairwiseProbitLikelihood(
            float(lik.raw_comparison_noise_constraint.transform(torch.tensor(r, dtype=torch.float64)))
        )
        return float(l2.log_prob(eta).sum())

    fd = (at(raw + h) - at(raw - h)) / (2 * h)
    assert abs(float(g) - fd) <= 1e-6 * abs(fd)
    # derivatives() is differentiable in sigma_R too (used by the evidence gradient)
    d1 = lik.derivatives(eta)[1].sum()
    (g1,) = torch.autograd.grad(d1, [lik.raw_comparison_noise])
    assert torch.isfinite(g1) and float(g1) != 0.0


def test_beta_parameter_gradients_vs_finite_differences(generator):
    lik = BetaRatingLikelihood(0.8, 40.0, learn=True)
    eta = randn(7, generator=generator)
    u = rand(7, generator=generator, low=0.05, high=0.95)
    params = [lik.raw_rating_scale, lik.raw_rating_precision]
    for k in range(3):  # value, first and second derivative all carry parameter gradients
        out = lik.derivatives(eta, u)[k].sum()
        grads = torch.autograd.grad(out, params)
        for p, g in zip(params, grads):
            h = 1e-6
            with torch.no_grad():
                p += h
                up = float(lik.derivatives(eta, u)[k].sum())
                p -= 2 * h
                down = float(lik.derivatives(eta, u)[k].sum())
                p += h
            fd = (up - down) / (2 * h)
            assert abs(float(g) - fd) <= 1e-6 * max(1.0, abs(fd)), (k, float(g), fd)


# ------------------------------------------------- third derivatives (evidence gradient)
def _autograd_third(second, eta):
    eta = eta.clone().requires_grad_(True)
    (d3,) = torch.autograd.grad(second(eta).sum(), eta)
    return d3


@pytest.mark.parametrize("sigma_R", [1e-3, 0.2, 1.0, 10.0])
def test_probit_third_derivative_matches_autograd(sigma_R):
    lik = PairwiseProbitLikelihood(sigma_R)
    eta = torch.linspace(-8.0, 8.0, 41, dtype=torch.float64) * SQRT2 * sigma_R
    # autograd of log Phi three times, independent of the closed forms
    x = eta.clone().requires_grad_(True)
    y = torch.special.log_ndtr(x / (SQRT2 * sigma_R))
    (g1,) = torch.autograd.grad(y.sum(), x, create_graph=True)
    (g2,) = torch.autograd.grad(g1.sum(), x, create_graph=True)
    (ref,) = torch.autograd.grad(g2.sum(), x)
    torch.testing.assert_close(lik.third_derivative(eta), ref, rtol=1e-6, atol=1e-12 / sigma_R**3)


@pytest.mark.parametrize("sigma_B,nu", BETA_PARAMS)
def test_beta_third_derivative_matches_autograd(sigma_B, nu, generator):
    lik = BetaRatingLikelihood(sigma_B, nu)
    eta = 2.0 * sigma_B * randn(40, generator=generator)
    u = rand(40, generator=generator, low=0.01, high=0.99)
    ref = _autograd_third(lambda e: lik.derivatives(e, u)[2], eta)
    torch.testing.assert_close(lik.third_derivative(eta, u), ref, rtol=1e-7, atol=1e-9)


def test_beta_fisher_is_finite_where_mu_rounds_to_0_or_1():
    """Far in the tails mu = Phi(t) rounds to 0 or 1, so nu^2 psi'(a) mu'^2 would be inf * 0;
    the weight stays finite, positive, and equal to the direct form where that is well
    conditioned (|t| <= 3), and grows like (t / c)^2 in the tails."""
    lik = BetaRatingLikelihood(0.8, 60.0)
    c = SQRT2 * 0.8
    t = torch.tensor([-60.0, -40.0, -9.0, -3.0, 0.0, 3.0, 9.0, 40.0, 60.0], dtype=torch.float64)
    got = lik.fisher(t * c)
    assert torch.isfinite(got).all() and (got > 0).all()
    mu = torch.special.ndtr(t)
    dmu = torch.exp(-0.5 * t * t) / math.sqrt(2 * math.pi) / c
    direct = 60.0**2 * (torch.polygamma(1, 60.0 * mu) + torch.polygamma(1, 60.0 * (1 - mu))) * dmu**2
    ok = torch.isfinite(direct) & (t.abs() <= 3)
    torch.testing.assert_close(got[ok], direct[ok], rtol=1e-10, atol=0)
    # the inverse Mills ratio phi(t) / Phi(t) ~ |t| as t -> -inf
    assert abs(float(got[0]) / (60.0 / c) ** 2 - 1) < 0.01


# ------------------------------------------------- shared default constraints (construction cost)
def _models(n=6):
    from torchpref import PreferenceGP

    X = torch.rand(n, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    C = torch.tensor([[0, 1], [2, 3], [4, 5]])
    return X, (
        PreferenceGP(X, comparisons=C, ratings=torch.tensor([0.3, 0.8]), rating_index=torch.tensor([0, 4]))
        for _ in iter(int, 1)
    )


def test_default_constraints_are_shared_but_never_changed_through_a_model():
    X, models = _models()
    a, b = next(models), next(models)
    lik_a, lik_b = a.likelihood.rating, b.likelihood.rating
    assert lik_a.raw_rating_precision_constraint is lik_b.raw_rating_precision_constraint  # one instance
    # the values a model's own new constraint gave (made in float32 by GPyTorch, then converted by ``to``)
    ref = BetaRatingLikelihood(1.0, 80.0).to(torch.float64)
    assert ref.raw_rating_precision_constraint is not lik_a.raw_rating_precision_constraint
    assert torch.equal(lik_a.raw_rating_precision, ref.raw_rating_precision)
    assert torch.equal(lik_a.rating_precision, ref.rating_precision)
    a.to(torch.float32)  # converts a private copy: b keeps float64 bounds
    assert lik_a.raw_rating_precision_constraint.lower_bound.dtype == torch.float32
    assert lik_b.raw_rating_precision_constraint.lower_bound.dtype == torch.float64
    assert a.posterior(X.float()).mean.dtype == torch.float32
    # loading other bounds gives the loading model a private copy; loading the same ones keeps sharing
    c = next(models)
    c.load_state_dict(b.state_dict())
    assert c.likelihood.rating.raw_rating_precision_constraint is lik_b.raw_rating_precision_constraint
    key = "likelihood.rating.raw_rating_precision_constraint.lower_bound"
    c.load_state_dict({**b.state_dict(), key: torch.tensor(0.5, dtype=torch.float64)})
    assert float(c.likelihood.rating.raw_rating_precision_constraint.lower_bound) == 0.5
    assert float(lik_b.raw_rating_precision_constraint.lower_bound) == pytest.approx(1e-2)
    assert float(next(models).likelihood.rating.raw_rating_precision_constraint.lower_bound) == pytest.approx(1e-2)
