"""QueryInformation and the sample-based information against independent computations."""

import math

import numpy as np
import pytest
import torch
from scipy import integrate, stats

from torchpref.acquisition import (
    QueryInformation,
    choice_probabilities,
    latent_ucb,
    rating_bin_probabilities,
    sample_information,
)
from torchpref.experiments.wave import make_model


@pytest.fixture
def model():
    X = torch.tensor([[0.1], [0.3], [0.35], [0.6]], dtype=torch.float64)
    m = make_model(X, torch.tensor([[1, 0], [2, 3]]))
    m.covar_module.base_kernel.lengthscale = 0.2
    m.add_observations(torch.tensor([[0.32]], dtype=torch.float64), ratings=[0.7], rating_index=[0])
    return m


def test_rating_information_vs_scipy(model):
    X = torch.tensor([[[0.05]], [[0.33]], [[0.9]]], dtype=torch.float64)
    info = QueryInformation(model, num_quadrature=40, num_grid=2000)(X)
    post = model.posterior(X)
    lik = model.likelihood.rating
    s_b, nu = float(lik.rating_scale), float(lik.rating_precision)
    for b in range(3):
        m, v = float(post.mean[b, 0, 0]), float(post.variance[b, 0, 0])
        sd = math.sqrt(v)

        def beta_of(f):
            mu = stats.norm.cdf(f / (s_b * math.sqrt(2)))
            return stats.beta(nu * mu, nu * (1 - mu))

        # brute force on grids: f in m +- 8 sd, u in (0, 1); SciPy's Beta densities and entropies
        f = np.linspace(m - 8 * sd, m + 8 * sd, 3001)
        pf = stats.norm.pdf(f, m, sd)
        mu = np.clip(stats.norm.cdf(f / (s_b * math.sqrt(2))), 1e-300, 1 - 1e-16)
        cond = integrate.trapezoid(pf * stats.beta(nu * mu, nu * (1 - mu)).entropy(), f)
        u = np.linspace(1e-5, 1 - 1e-5, 3000)
        dens = stats.beta.pdf(u[:, None], nu * mu[None, :], nu * (1 - mu[None, :]))
        pu = integrate.trapezoid(dens * pf[None, :], f, axis=1)
        h = -integrate.trapezoid(np.where(pu > 0, pu * np.log(np.maximum(pu, 1e-300)), 0.0), u)
        assert float(info[b]) == pytest.approx(h - cond, rel=1e-2)  # Gauss-Hermite vs grids


def test_ranking_information_q2_independent(model):
    X = torch.tensor([[[0.3], [0.6]], [[0.1], [0.35]]], dtype=torch.float64)
    info = QueryInformation(model, num_samples=20000, generator=torch.Generator().manual_seed(1))(X)
    mvn = model.posterior(X).distribution
    s_r = float(model.likelihood.comparison.comparison_noise)
    for b in range(2):
        mean, cov = mvn.mean[b].detach().numpy(), mvn.covariance_matrix[b].detach().numpy()
        # the answer depends on f only through d = f_0 - f_1 ~ N(md, vd); P(0 | d) = Phi(d / (sqrt2 s_r))
        md, sd = mean[0] - mean[1], math.sqrt(cov[0, 0] + cov[1, 1] - 2 * cov[0, 1])
        p = lambda d: stats.norm.cdf(d / (math.sqrt(2) * s_r))  # noqa: E731
        H = lambda q: -(q * np.log(max(q, 1e-300)) + (1 - q) * np.log(max(1 - q, 1e-300)))  # noqa: E731
        p0 = integrate.quad(lambda d: stats.norm.pdf(d, md, sd) * p(d), md - 10 * sd, md + 10 * sd)[0]
        cond = integrate.quad(lambda d: stats.norm.pdf(d, md, sd) * H(p(d)), md - 10 * sd, md + 10 * sd)[0]
        assert float(info[b]) == pytest.approx(H(p0) - cond, abs=0.01)


def test_choice_probabilities_q2_is_probit():
    f = torch.tensor([[0.3, -0.1], [0.0, 0.0], [1.0, -2.0]], dtype=torch.float64)
    p = choice_probabilities(f, 0.2, num_quadrature=20)
    expected = torch.special.ndtr((f[:, 0] - f[:, 1]) / (math.sqrt(2) * 0.2))
    torch.testing.assert_close(p[:, 0], expected, atol=1e-6, rtol=0)
    # q = 3 against Monte Carlo of the argmax of noisy utilities
    g = torch.Generator().manual_seed(0)
    f3 = torch.tensor([0.1, 0.0, 0.25], dtype=torch.float64)
    noisy = f3 + 0.2 * torch.randn(200000, 3, generator=g, dtype=torch.float64)
    mc = torch.bincount(noisy.argmax(-1), minlength=3).double() / 200000
    torch.testing.assert_close(choice_probabilities(f3, 0.2, num_quadrature=20), mc, atol=5e-3, rtol=0)


def test_sample_information_identities(model):
    g = torch.Generator().manual_seed(0)
    # answer independent of the target: zero information
    P = torch.softmax(torch.randn(3, 1, 4, generator=g, dtype=torch.float64), -1).expand(3, 50, 4)
    labels = torch.randint(0, 5, (50,), generator=g)
    torch.testing.assert_close(sample_information(P, labels), torch.zeros(3, dtype=torch.float64))
    # answer determined by the label: information = entropy of the label
    labels = torch.arange(4).repeat(25)
    P = torch.nn.functional.one_hot(labels, 4).double().unsqueeze(0)
    torch.testing.assert_close(sample_information(P, labels), torch.tensor([math.log(4)], dtype=torch.float64))
    # I(y; label) <= I(y; f)
    P = torch.softmax(3 * torch.randn(2, 60, 5, generator=g, dtype=torch.float64), -1)
    labels = torch.randint(0, 3, (60,), generator=g)
    assert (sample_information(P, labels) <= sample_information(P) + 1e-12).all()
    bins = rating_bin_probabilities(torch.tensor([-1.0, 0.0, 2.0], dtype=torch.float64), model.likelihood.rating, 10)
    torch.testing.assert_close(bins.sum(-1), torch.ones(3, dtype=torch.float64))
    assert bins[0].argmax() < bins[1].argmax() < bins[2].argmax()


def test_optimize_acqf_with_latent_ucb(model):
    from botorch.optim import optimize_acqf

    bounds = torch.tensor([[0.0], [1.0]], dtype=torch.float64)
    x, val = optimize_acqf(latent_ucb(model, 3.0), bounds=bounds, q=1, num_restarts=4, raw_samples=64)
    grid = torch.linspace(0, 1, 2001, dtype=torch.float64).reshape(-1, 1, 1)
    with torch.no_grad():
        ucb = latent_ucb(model, 3.0)(grid)
    assert 0 <= float(x) <= 1
    assert float(val) >= float(ucb.max()) - 1e-3
