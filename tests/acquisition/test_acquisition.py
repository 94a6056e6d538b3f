"""QueryInformation and the sample-based information against independent computations."""

import math

import numpy as np
import pytest
import torch
from scipy import integrate, stats

from torchpref.acquisition.functions import (
    QueryInformation,
    QueryUCB,
    choice_probabilities,
    greedy_choice_set,
    latent_ucb,
    membership_information,
    rating_bin_probabilities,
    sample_information,
    top_set_membership,
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


def test_query_ucb_is_botorch_ucb_of_the_best_item(model):
    X = torch.linspace(0, 1, 12, dtype=torch.float64).reshape(4, 3, 1)  # 4 queries of 3 items
    with torch.no_grad():
        per_item = latent_ucb(model, 3.0)(X.reshape(12, 1, 1)).reshape(4, 3)  # BoTorch's UCB
        torch.testing.assert_close(QueryUCB(model, 3.0)(X), per_item.max(-1).values)


def test_top_set_membership_counts():
    g = torch.Generator().manual_seed(3)
    F = torch.randn(40, 25, generator=g, dtype=torch.float64)
    Z = top_set_membership(F, 6)
    assert (Z.sum(-1) == 6).all()
    # members are at least as large as every non-member, sample by sample
    lo = torch.where(Z, F, torch.inf).amin(-1)
    hi = torch.where(Z, -torch.inf, F).amax(-1)
    assert (lo > hi).all()
    with pytest.raises(ValueError, match="k must be"):
        top_set_membership(F, 0)


def test_membership_information_identities():
    g = torch.Generator().manual_seed(4)
    S, N = 200, 7
    Z = torch.rand(S, N, generator=g) < torch.linspace(0.2, 0.8, N)
    # an answer independent of every label: no information (plug-in: exactly 0)
    P = torch.softmax(torch.randn(3, 1, 5, generator=g, dtype=torch.float64), -1).expand(3, S, 5)
    torch.testing.assert_close(membership_information(P, Z, bias_correction=False), torch.zeros(3, dtype=torch.float64))
    # without correction each item's term is sample_information with that item's labels
    P = torch.softmax(2 * torch.randn(4, S, 3, generator=g, dtype=torch.float64), -1)
    per_item = torch.stack([sample_information(P, Z[:, i].long(), 2) for i in range(N)], -1)
    torch.testing.assert_close(membership_information(P, Z, min_count=1, bias_correction=False), per_item.sum(-1))
    # an answer that reveals item 0's label (and nothing else): its binary entropy, plus (nearly) nothing
    z0 = Z[:, 0]
    Z2 = torch.stack([z0, torch.rand(S, generator=g) < 0.5], -1)
    P = torch.nn.functional.one_hot(z0.long(), 2).to(torch.float64).unsqueeze(0)
    p = z0.double().mean()
    h = -(p * p.log() + (1 - p) * (1 - p).log())
    info = membership_information(P, Z2[:, :1], min_count=1, bias_correction=False)
    torch.testing.assert_close(info, h.reshape(1))
    # the correction leaves a deterministic answer's information (no variance within labels) as is
    torch.testing.assert_close(membership_information(P, Z2[:, :1], min_count=1), h.reshape(1), atol=0.01, rtol=0)
    # items whose rarer label has fewer than min_count samples do not count
    Zr = torch.zeros(S, 1, dtype=torch.bool)
    Zr[:3] = True
    P = torch.nn.functional.one_hot(Zr[:, 0].long(), 2).to(torch.float64).unsqueeze(0)
    assert float(membership_information(P, Zr, min_count=4)) == 0.0
    assert float(membership_information(P, Zr, min_count=3, bias_correction=False)) > 0.05


def test_membership_information_bias_correction():
    """One item whose label the answer informs and 60 unrelated items: from 128 samples the
    plug-in sum is biased well above the information (a 20000-sample estimate for the one item,
    the rest carry none); the corrected sum is close to it."""
    g = torch.Generator().manual_seed(5)

    def draw(S):
        f = torch.randn(S, 1, generator=g, dtype=torch.float64)  # what the answer depends on
        other = torch.randn(S, 60, generator=g, dtype=torch.float64)  # unrelated items
        F = torch.cat([f + 0.3 * torch.randn(S, 1, generator=g, dtype=torch.float64), other], -1)
        Z = F > 0.5
        P = torch.softmax(torch.cat([3 * f, torch.zeros_like(f), -3 * f], -1), -1).unsqueeze(0)  # 1 x S x 3
        return P, Z

    P, Z = draw(20000)
    ref = float(membership_information(P, Z[:, :1], bias_correction=False))  # item 0 alone, no bias to speak of
    plug, corr = [], []
    for _ in range(30):
        P, Z = draw(128)
        plug.append(float(membership_information(P, Z, bias_correction=False)))
        corr.append(float(membership_information(P, Z)))
    plug, corr = np.mean(plug), np.mean(corr)
    assert ref > 0.1
    assert plug > ref + 0.1  # 60 unrelated items, each biased upwards
    assert abs(corr - ref) < 0.04
    assert abs(corr - ref) < 0.25 * abs(plug - ref)


def test_greedy_choice_set_matches_brute_force():
    g = torch.Generator().manual_seed(6)
    F = torch.randn(64, 8, generator=g, dtype=torch.float64) + torch.linspace(-1, 1, 8, dtype=torch.float64)
    labels = F.argmax(-1)
    seen = []

    def value(P):
        seen.append(P)
        return sample_information(P, labels, 8)

    chosen, best = greedy_choice_set(F, 0.2, 4, value, start=None)
    assert len(set(chosen)) == 4
    # the final set's probabilities are choice_probabilities' (log space, Gauss-Hermite)
    f_final = F[:, chosen].unsqueeze(0)
    P_final = choice_probabilities(f_final, 0.2)
    assert best == pytest.approx(float(sample_information(P_final, labels, 8)), rel=1e-9)
    # every step: the best set of its candidates, by brute force
    import itertools

    pairs = list(itertools.combinations(range(8), 2))
    vals = sample_information(choice_probabilities(F[:, torch.tensor(pairs)].permute(1, 0, 2), 0.2), labels, 8)
    assert set(chosen[:2]) == set(pairs[int(vals.argmax())])
    for r in (3, 4):
        rest = [c for c in range(8) if c not in chosen[: r - 1]]
        sets = torch.tensor([chosen[: r - 1] + [c] for c in rest])
        vals = sample_information(choice_probabilities(F[:, sets].permute(1, 0, 2), 0.2), labels, 8)
        assert chosen[r - 1] == rest[int(vals.argmax())]
    # a fixed start is kept
    assert greedy_choice_set(F, 0.2, 3, value, start=5)[0][0] == 5
    with pytest.raises(ValueError, match="m="):
        greedy_choice_set(F, 0.2, 9, value)
