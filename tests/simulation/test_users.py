"""Tests for torchpref.simulation.users: the user protocol, the simulated user and its samplers."""

import math

import numpy as np
import pytest
import torch
from scipy import stats

from torchpref.simulation.users import RATING_CLAMP, SimulatedUser, User, sample_beta, sample_log_gamma
from torchpref.simulation.utility_functions import WaveFunction, evaluation_grid


@pytest.fixture
def generator():
    return torch.Generator().manual_seed(31415)


def linear_utility(X):
    """f(x) = 2 x_0 - 1 on ``n x d`` inputs."""
    return 2.0 * X[..., 0] - 1.0


def binomial_tolerance(p, n, sds=4.0):
    return sds * math.sqrt(p * (1 - p) / n)


def test_protocol():
    user = SimulatedUser(linear_utility, 0.1, 0.8, 60.0)
    assert isinstance(user, User)

    class Human:
        def rate(self, x):
            return 0.5

        def choose(self, X):
            return 0

    assert isinstance(Human(), User)
    assert not isinstance(object(), User)


@pytest.mark.parametrize("sigma_r", [0.05, 0.2])
def test_pairwise_choice_frequency_matches_eq3(sigma_r, generator):
    user = SimulatedUser(
        linear_utility, comparison_noise=sigma_r, rating_scale=0.8, rating_precision=80.0, generator=generator
    )
    # latent gap f_a - f_b = 2 * (x_a - x_b)
    for xa, xb in [(0.52, 0.5), (0.5, 0.53), (0.6, 0.55)]:
        X = torch.tensor([[xa], [xb]], dtype=torch.float64)
        n = 4000
        freq = sum(user.choose(X) == 0 for _ in range(n)) / n
        p = stats.norm.cdf((linear_utility(X[:1]) - linear_utility(X[1:])).item() / (sigma_r * math.sqrt(2)))
        assert 0.02 < p < 0.98  # informative pairs
        assert abs(freq - p) < binomial_tolerance(p, n), (xa, xb, freq, p)
    assert user.n_choices == 3 * 4000 and user.n_ratings == 0


def test_best_of_m_frequency(generator):
    # m = 3: P(i wins) = E[prod_{j != i} Phi((f_i + e_i - f_j) / sigma_R)], by quadrature
    sigma_r = 0.1
    user = SimulatedUser(linear_utility, sigma_r, 0.8, 80.0, generator=generator)
    X = torch.tensor([[0.50], [0.53], [0.56]], dtype=torch.float64)
    f = linear_utility(X).numpy()
    nodes, weights = np.polynomial.hermite_e.hermegauss(60)
    p = []
    for i in range(3):
        e = sigma_r * nodes
        prod = np.prod([stats.norm.cdf((f[i] + e - f[j]) / sigma_r) for j in range(3) if j != i], axis=0)
        p.append(np.sum(weights * prod) / math.sqrt(2 * math.pi))
    assert sum(p) == pytest.approx(1.0, abs=1e-10)
    n = 4000
    counts = np.bincount([user.choose(X) for _ in range(n)], minlength=3)
    for i in range(3):
        assert abs(counts[i] / n - p[i]) < binomial_tolerance(p[i], n)


@pytest.mark.parametrize("alpha, beta", [(0.05, 79.95), (0.7, 2.0), (3.0, 1.0), (40.0, 40.0), (75.0, 5.0)])
def test_beta_sampler_moments_and_ks(alpha, beta, generator):
    n = 20_000
    x = sample_beta(torch.full((n,), alpha, dtype=torch.float64), torch.tensor(beta, dtype=torch.float64), generator)
    assert x.shape == (n,) and x.dtype == torch.float64
    assert ((x >= 0) & (x <= 1)).all()
    mean = alpha / (alpha + beta)
    var = alpha * beta / ((alpha + beta) ** 2 * (alpha + beta + 1))
    # the sample mean's standard error is sqrt(var / n)
    assert abs(x.mean().item() - mean) < 4 * math.sqrt(var / n)
    assert x.var().item() == pytest.approx(var, rel=0.08)
    assert stats.kstest(x.numpy(), stats.beta(alpha, beta).cdf).pvalue > 1e-3


@pytest.mark.parametrize("a", [0.01, 0.3, 1.0, 2.5, 50.0])
def test_log_gamma_sampler(a, generator):
    n = 20_000
    g = sample_log_gamma(torch.full((n,), a, dtype=torch.float64), generator).exp()
    assert stats.kstest(g.numpy(), stats.gamma(a).cdf).pvalue > 1e-3
    # tiny shapes do not underflow to -inf in log space
    assert torch.isfinite(sample_log_gamma(torch.full((1000,), 1e-3, dtype=torch.float64), generator)).all()


def test_samplers_bad_input(generator):
    with pytest.raises(ValueError, match="concentration"):
        sample_log_gamma(torch.tensor([1.0, 0.0]), generator)
    with pytest.raises(ValueError, match="beta"):
        sample_beta(torch.tensor(1.0), torch.tensor(-2.0), generator)


def test_rating_distribution(generator):
    sigma_b, nu = 0.8, 80.0
    user = SimulatedUser(linear_utility, 0.05, sigma_b, nu, generator=generator)
    x = torch.tensor([0.7], dtype=torch.float64)  # f = 0.4
    mu = stats.norm.cdf(0.4 / (sigma_b * math.sqrt(2)))
    torch.testing.assert_close(user.mean_rating(x.unsqueeze(0)), torch.tensor([mu], dtype=torch.float64))
    u = np.array([user.rate(x) for _ in range(3000)])
    assert isinstance(user.rate(x), float)
    assert stats.kstest(u, stats.beta(nu * mu, nu * (1 - mu)).cdf).pvalue > 1e-3
    assert abs(u.mean() - mu) < 4 * math.sqrt(mu * (1 - mu) / (nu + 1) / 3000)
    assert user.n_ratings == 3001 and user.n_choices == 0
    user.reset_counts()
    assert user.n_ratings == 0


def test_ratings_strictly_inside_unit_interval(generator):
    # |f| so large that mu is 0 or 1 in float64; the answer is still inside (0, 1)
    user = SimulatedUser(lambda X: 40.0 * (2 * X[..., 0] - 1), 0.05, 0.8, 80.0, generator=generator)
    lo = [user.rate(torch.tensor([0.0], dtype=torch.float64)) for _ in range(50)]
    hi = [user.rate(torch.tensor([1.0], dtype=torch.float64)) for _ in range(50)]
    assert min(lo) >= RATING_CLAMP and max(hi) <= 1 - RATING_CLAMP
    assert 0 < min(lo) and max(hi) < 1


def test_noiseless(generator):
    truth = WaveFunction.random(generator=generator)
    user = SimulatedUser.paper_wave(lambda X: truth(X, noise=False), noiseless=True)
    X = evaluation_grid(21)
    f = truth(X, noise=False)
    state = user.generator.get_state()
    assert user.choose(X) == int(f.argmax())
    x = X[7]
    assert user.rate(x) == pytest.approx(stats.norm.cdf(f[7].item() / (0.8 * math.sqrt(2))), abs=1e-15)
    assert torch.equal(state, user.generator.get_state())  # nothing drawn
    assert (user.n_ratings, user.n_choices) == (1, 1)


def test_paper_wave_defaults():
    truth = WaveFunction.random(generator=torch.Generator().manual_seed(0))
    user = SimulatedUser.paper_wave(truth, generator=torch.Generator().manual_seed(1))
    assert (user.comparison_noise, user.rating_scale, user.rating_precision) == (0.05, 0.8, 80.0)
    assert not user.noiseless
    assert 0 <= user.choose(evaluation_grid(5)) < 5  # a WaveFunction is a valid utility


def test_determinism_and_no_global_rng():
    def run(seed):
        g = torch.Generator().manual_seed(seed)
        truth = WaveFunction.random(generator=g)
        user = SimulatedUser.paper_wave(lambda X: truth(X, noise=False), generator=g)
        Xs = torch.rand(20, 5, 1, generator=g, dtype=torch.float64)
        return [user.choose(X) for X in Xs], [user.rate(X[0]) for X in Xs]

    state = torch.get_rng_state()
    a, b, c = run(5), run(5), run(6)
    assert a == b
    assert a != c
    assert torch.equal(state, torch.get_rng_state())


def test_bad_input():
    with pytest.raises(ValueError, match="comparison_noise"):
        SimulatedUser(linear_utility, 0.0, 0.8, 80.0)
    with pytest.raises(ValueError, match="rating_scale"):
        SimulatedUser(linear_utility, 0.1, -0.8, 80.0)
    with pytest.raises(ValueError, match="rating_precision"):
        SimulatedUser(linear_utility, 0.1, 0.8, float("inf"))
    with pytest.raises(ValueError, match="utility"):
        SimulatedUser(3.0, 0.1, 0.8, 80.0)
    user = SimulatedUser(linear_utility, 0.1, 0.8, 80.0)
    with pytest.raises(ValueError, match="m >= 2"):
        user.choose(torch.zeros(1, 1, dtype=torch.float64))
    with pytest.raises(ValueError, match="single item"):
        user.rate(torch.zeros(3, 1, dtype=torch.float64))
    bad = SimulatedUser(lambda X: X, 0.1, 0.8, 80.0)  # returns n x d, not n
    with pytest.raises(ValueError, match="utility must map"):
        bad.choose(torch.zeros(3, 2, dtype=torch.float64))
    # a 1 x d item is accepted by rate
    assert 0 < user.rate(torch.zeros(1, 1, dtype=torch.float64)) < 1


def test_scalar_gamma_path_matches_tensor_path():
    """One shape (a simulated rating) takes a Python-float path: same values, same draws."""
    from torchpref.simulation.users import _log_gamma_scalar, _log_gamma_tensor

    for seed in range(200):
        a = [0.01, 0.3, 0.99, 1.0, 2.5, 40.0, 79.9][seed % 7]
        g1, g2 = torch.Generator().manual_seed(seed), torch.Generator().manual_seed(seed)
        x1 = _log_gamma_scalar(a, torch.float64, g1)
        x2 = _log_gamma_tensor(torch.tensor([a], dtype=torch.float64), g2)
        assert float(x1) == pytest.approx(float(x2), rel=1e-12, abs=1e-12)
        assert torch.equal(g1.get_state(), g2.get_state())
    assert sample_log_gamma(torch.tensor(3.0, dtype=torch.float64), torch.Generator()).shape == ()
