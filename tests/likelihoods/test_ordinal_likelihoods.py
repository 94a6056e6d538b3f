"""Tie and ordinal likelihoods: closed-form derivatives vs autograd and high-precision references,
predictives vs quadrature, bad input."""

import math

import mpmath
import numpy as np
import pytest
import torch
from gpytorch.distributions import MultivariateNormal
from scipy import integrate, stats

from torchpref.inference.numerics import normal_interval
from torchpref.likelihoods.ordinal import OrdinalRatingLikelihood, TieLikelihood, default_cut_points
from torchpref.likelihoods.pairwise_beta import PairwiseProbitLikelihood

SQRT2 = math.sqrt(2.0)
T = dict(dtype=torch.float64)


def autograd3(fn, eta):
    """``fn(eta)`` and its first three elementwise derivatives by autograd."""
    eta = eta.clone().requires_grad_(True)
    y = fn(eta)
    (d1,) = torch.autograd.grad(y.sum(), eta, create_graph=True)
    (d2,) = torch.autograd.grad(d1.sum(), eta, create_graph=True)
    (d3,) = torch.autograd.grad(d2.sum(), eta)
    return y.detach(), d1.detach(), d2.detach(), d3


def naive_interval(upper, lower, s):
    """``log(Phi(upper / s) - Phi(lower / s))`` as written (fine away from the tails)."""
    return torch.log(torch.special.ndtr(upper / s) - torch.special.ndtr(lower / s))


def mp_derivatives(upper: float, lower: float, s: float) -> list[float]:
    """``log P`` and three derivatives in the location, in 60-digit arithmetic."""
    mpmath.mp.dps = 60
    up = mpmath.mpf(upper) if math.isfinite(upper) else mpmath.inf
    lo = mpmath.mpf(lower) if math.isfinite(lower) else -mpmath.inf

    def logp(m):  # an upper-tail interval as a lower-tail one (1 - 1 would vanish in 60 digits)
        if lower > 0:
            return mpmath.log(mpmath.ncdf((m - lo) / s) - mpmath.ncdf((m - up) / s))
        return mpmath.log(mpmath.ncdf((up - m) / s) - mpmath.ncdf((lo - m) / s))

    return [float(mpmath.diff(logp, 0, k, h=mpmath.mpf("1e-15"))) for k in range(4)]


@pytest.mark.parametrize("tau,sigma_R", [(0.1, 0.1), (0.02, 0.3), (1.0, 0.05), (0.5, 1.0)])
def test_tie_derivatives_match_autograd(tau, sigma_R):
    lik = TieLikelihood(tau, PairwiseProbitLikelihood(sigma_R))
    s = SQRT2 * sigma_R
    eta = torch.linspace(-3.5 * s - tau, 3.5 * s + tau, 61, **T)  # tails: against mpmath below
    lp, d1, d2 = lik.derivatives(eta)
    ref = autograd3(lambda e: naive_interval(tau - e, -tau - e, s), eta)
    torch.testing.assert_close(lp, ref[0], rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(d1, ref[1], rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(d2, ref[2], rtol=1e-7, atol=1e-9)
    torch.testing.assert_close(lik.third_derivative(eta), ref[3], rtol=1e-6, atol=1e-8)
    assert (d2 < 0).all(), "an interval probability is log-concave"
    torch.testing.assert_close(lik.fisher(eta), -d2)
    torch.testing.assert_close(lik.log_prob(-eta), lp)  # symmetric in eta
    torch.testing.assert_close(lik.derivatives(-eta)[1], -d1)


@pytest.mark.parametrize(
    "upper,lower,s",
    [
        (-4.0, -5.0, 0.5),  # deep lower tail of a short interval
        (12.0, 11.0, 1.0),  # deep upper tail
        (1e-7, -1e-7, 1.0),  # a tiny interval across zero (0.5 - 0.5 would cancel)
        (math.inf, 6.0, 0.7),  # one-sided, far
        (-3.0, -math.inf, 0.2),  # one-sided, far on the other side
        (0.4, -math.inf, 1.0),
        (2.0, 1.9, 0.01),  # 190 scales into the upper tail
        (-30.0, -30.0001, 1.0),  # short and deep: close to a Gaussian density
    ],
)
def test_normal_interval_against_high_precision(upper, lower, s):
    got = normal_interval(torch.tensor(upper, **T), torch.tensor(lower, **T), s, third=True)
    ref = mp_derivatives(upper, lower, s)
    z = max(abs(x) for x in (upper, lower) if math.isfinite(x)) / s  # derivatives cancel terms ~ z^k
    for k, (g, r) in enumerate(zip(got, ref)):
        assert math.isfinite(float(g))
        assert abs(float(g) - r) <= 1e-12 * max(1.0, abs(r)) + 1e-12 * (1 + z) ** k / s**k, (k, float(g), r)


def test_normal_interval_gradients_finite_at_infinite_bounds():
    """Gradients in the bounds (the cut points) are finite where the other bound is infinite."""
    c = torch.tensor([-0.5, 0.5], **T, requires_grad=True)
    inf = torch.tensor([math.inf], **T)
    ext = torch.cat([-inf, c, inf])
    eta = torch.tensor([3.0, -30.0, 0.2, 40.0], **T)
    lp, d1, d2, d3 = normal_interval(ext[1:][[0, 0, 1, 2]] - eta, ext[:-1][[0, 0, 1, 2]] - eta, 0.3, third=True)
    (g,) = torch.autograd.grad((lp + d1 + d2 + d3).sum(), c)
    assert torch.isfinite(g).all() and torch.isfinite(lp).all()


@pytest.mark.parametrize("K", [2, 5, 7])
@pytest.mark.parametrize("sigma", [0.05, 0.2, 1.0])
def test_ordinal_derivatives_match_autograd(K, sigma):
    lik = OrdinalRatingLikelihood(K, level_noise=sigma)
    c = torch.cat([torch.tensor([-1e6], **T), lik.cut_points.detach(), torch.tensor([1e6], **T)])
    eta = torch.linspace(-3.0, 3.0, 41, **T)
    for k in range(1, K + 1):
        y = torch.full_like(eta, k)
        # keep the reference where its naive form is accurate (P not tiny)
        keep = naive_interval(c[k] - eta, c[k - 1] - eta, sigma) > -8
        e = eta[keep]
        ref = autograd3(lambda x: naive_interval(c[k] - x, c[k - 1] - x, sigma), e)
        lp, d1, d2 = lik.derivatives(e, y[keep])
        torch.testing.assert_close(lp, ref[0], rtol=1e-9, atol=1e-11)
        torch.testing.assert_close(d1, ref[1], rtol=1e-7, atol=1e-9)
        torch.testing.assert_close(d2, ref[2], rtol=1e-6, atol=1e-8)
        torch.testing.assert_close(lik.third_derivative(e, y[keep]), ref[3], rtol=1e-5, atol=1e-7)
        assert (lik.derivatives(eta, y)[2] <= 0).all()


def test_ordinal_probabilities_sum_to_one_and_batch_shapes(generator):
    lik = OrdinalRatingLikelihood(5)
    for shape in [(), (3,), (2, 4)]:
        f = torch.randn(shape, generator=generator, **T)
        dist = lik(f)
        assert dist.probs.shape == (*shape, 5)
        torch.testing.assert_close(dist.probs.sum(-1), torch.ones(shape, **T))
        lp, d1, d2 = lik.derivatives(f, torch.full(shape, 3))
        assert lp.shape == shape and d2.shape == shape


def test_ordinal_fisher_is_expected_negative_hessian():
    lik = OrdinalRatingLikelihood(4, level_noise=0.3)
    eta = torch.linspace(-2.5, 2.5, 11, **T)
    probs = lik(eta).probs
    ref = torch.zeros_like(eta)
    for k in range(1, 5):
        _, d1, d2 = lik.derivatives(eta, torch.full_like(eta, k))
        ref = ref + probs[..., k - 1] * d1 * d1  # E[(d log p)^2] = E[-d^2 log p]
    torch.testing.assert_close(lik.fisher(eta), ref, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("m,v", [(0.0, 0.5), (0.7, 0.1), (-1.3, 2.0), (2.5, 1e-6)])
def test_ordinal_predictives_vs_quadrature(m, v):
    lik = OrdinalRatingLikelihood(5, level_noise=0.25)
    c = [-math.inf] + lik.cut_points.tolist() + [math.inf]
    sd = math.sqrt(v)
    probs = lik.level_probabilities(torch.tensor(m, **T), torch.tensor(v, **T))
    ref = []
    for k in range(1, 6):

        def integrand(x, k=k):
            return (stats.norm.cdf((c[k] - x) / 0.25) - stats.norm.cdf((c[k - 1] - x) / 0.25)) * stats.norm.pdf(
                x, m, sd
            )

        val, _ = integrate.quad(
            integrand,
            m - 12 * sd,
            m + 12 * sd,
            epsabs=1e-13,
            epsrel=1e-12,
            limit=400,
            points=[x for x in c[1:-1] if abs(x - m) < 12 * sd] or None,
        )
        ref.append(val)
    np.testing.assert_allclose(probs.numpy(), ref, atol=1e-9)
    expected = float(lik.expected_level(torch.tensor(m, **T), torch.tensor(v, **T)))
    assert abs(expected - sum(k * p for k, p in zip(range(1, 6), ref))) < 1e-8
    assert abs(float(lik.expected_rating(torch.tensor(m, **T), torch.tensor(v, **T))) - (expected - 0.5) / 5) < 1e-12


@pytest.mark.parametrize("m,v", [(0.0, 0.5), (0.15, 0.01), (-1.3, 2.0), (0.05, 0.0)])
def test_tie_probability_vs_quadrature(m, v):
    lik = TieLikelihood(0.2, PairwiseProbitLikelihood(0.1))
    s = SQRT2 * 0.1
    got = float(lik.tie_probability(torch.tensor(m, **T), torch.tensor(v, **T)))
    if v == 0:
        ref = stats.norm.cdf((0.2 - m) / s) - stats.norm.cdf((-0.2 - m) / s)
    else:
        sd = math.sqrt(v)
        ref, _ = integrate.quad(
            lambda x: (stats.norm.cdf((0.2 - x) / s) - stats.norm.cdf((-0.2 - x) / s)) * stats.norm.pdf(x, m, sd),
            m - 12 * sd,
            m + 12 * sd,
            epsabs=1e-13,
            limit=400,
            points=[-0.2, 0.2] if abs(m) < 12 * sd else None,
        )
    assert abs(got - ref) < 1e-9


def test_marginals_use_the_joint_covariance():
    lik = TieLikelihood(0.3)
    mean = torch.tensor([0.1, 0.4, -0.2], **T)
    S = torch.tensor([[1.0, 0.8, 0.1], [0.8, 1.0, 0.0], [0.1, 0.0, 0.5]], **T)
    got = lik.marginal(MultivariateNormal(mean, S), torch.tensor([[0, 1], [2, 0]])).probs
    want = lik.tie_probability(torch.tensor([-0.3, -0.3], **T), torch.tensor([0.4, 1.3], **T))
    torch.testing.assert_close(got, want)
    olik = OrdinalRatingLikelihood(3)
    probs = olik.marginal(MultivariateNormal(mean, S)).probs
    torch.testing.assert_close(probs, olik.level_probabilities(mean, S.diagonal()))


def test_cut_points_stay_ordered_and_round_trip():
    lik = OrdinalRatingLikelihood(5, learn=True)
    torch.testing.assert_close(lik.cut_points, default_cut_points(5))
    np.testing.assert_allclose(default_cut_points(5).numpy(), SQRT2 * stats.norm.ppf([0.2, 0.4, 0.6, 0.8]))
    with torch.no_grad():
        lik.raw_cut_points.copy_(torch.tensor([0.3, -20.0, 3.0, -1.0], **T))  # any raw values
    assert (lik.cut_points.diff() > 0).all()
    lik.cut_points = torch.tensor([-2.0, -0.1, 0.0, 3.0], **T)
    torch.testing.assert_close(lik.cut_points, torch.tensor([-2.0, -0.1, 0.0, 3.0], **T))
    # the default prior is on the cut points and has a gradient
    ((name, _, prior, closure, _),) = [p for p in lik.named_priors()]
    assert name == "cut_points_prior"
    (g,) = torch.autograd.grad(prior.log_prob(closure(lik)).sum(), lik.raw_cut_points)
    assert torch.isfinite(g).all() and g.abs().sum() > 0


def test_bad_input_is_a_value_error():
    lik = OrdinalRatingLikelihood(5)
    eta = torch.zeros(2, **T)
    with pytest.raises(ValueError, match=r"1\.\.5.*\[6"):
        lik.log_prob(eta, torch.tensor([1, 6]))
    with pytest.raises(ValueError, match="0"):
        lik.derivatives(eta, torch.tensor([0, 2]))
    with pytest.raises(ValueError, match="2.5"):
        lik.derivatives(eta, torch.tensor([2.5, 2.0], **T))
    with pytest.raises(ValueError, match="strictly increasing"):
        OrdinalRatingLikelihood(4, cut_points=[0.0, -1.0, 2.0])
    with pytest.raises(ValueError, match="3 finite"):
        OrdinalRatingLikelihood(4, cut_points=[0.0, 1.0])
    with pytest.raises(ValueError, match="at least 2"):
        OrdinalRatingLikelihood(1)
    with pytest.raises(ValueError, match="positive"):
        TieLikelihood(-0.1)
    with pytest.raises(ValueError, match="positive"):
        OrdinalRatingLikelihood(5, level_noise=0.0)


def test_tie_shares_the_comparison_noise():
    comp = PairwiseProbitLikelihood(0.1)
    tie = TieLikelihood(0.1, comp)
    before = tie.log_prob(torch.tensor(0.05, **T))
    comp.comparison_noise = 0.5
    assert float(tie.log_prob(torch.tensor(0.05, **T))) != float(before)
    assert float(tie.tie_probability(torch.tensor(0.0, **T), torch.tensor(0.0, **T))) == pytest.approx(
        stats.norm.cdf(0.1 / (SQRT2 * 0.5)) - stats.norm.cdf(-0.1 / (SQRT2 * 0.5)), rel=1e-12
    )


@pytest.mark.parametrize("tau,sigma_R", [(0.1, 0.1), (0.5, 1.0)])
def test_strict_preference_is_the_tie_upper_category(tau, sigma_R):
    from torchpref.likelihoods.ordinal import StrictPreferenceLikelihood

    tie = TieLikelihood(tau, PairwiseProbitLikelihood(sigma_R))
    strict = StrictPreferenceLikelihood(tie)
    s = SQRT2 * sigma_R
    eta = torch.linspace(-3.5 * s - tau, 3.5 * s + tau, 41, **T)
    total = strict.log_prob(eta).exp() + tie.log_prob(eta).exp() + strict.log_prob(-eta).exp()
    torch.testing.assert_close(total, torch.ones_like(eta), rtol=0, atol=1e-14)
    ref = autograd3(lambda e: torch.special.log_ndtr((e - tau) / s), eta)
    lp, d1, d2 = strict.derivatives(eta)
    torch.testing.assert_close(lp, ref[0], rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(d1, ref[1], rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(d2, ref[2], rtol=1e-8, atol=1e-11)
    torch.testing.assert_close(strict.third_derivative(eta), ref[3], rtol=1e-6, atol=1e-9)
    # predictive: the three categories' predictive probabilities also sum to one
    m, v = torch.tensor([0.3, -0.1], **T), torch.tensor([0.2, 1.0], **T)
    total = strict.preference_probability(m, v) + tie.tie_probability(m, v) + strict.preference_probability(-m, v)
    torch.testing.assert_close(total, torch.ones_like(m), rtol=0, atol=1e-14)
    zero = StrictPreferenceLikelihood(TieLikelihood(1e-300, PairwiseProbitLikelihood(sigma_R)))
    torch.testing.assert_close(zero.log_prob(eta), PairwiseProbitLikelihood(sigma_R).log_prob(eta))  # tau = 0: eq. 3
