"""Twins of a population (torchpref.simulation.twins): the Matérn deviation, the draw's distribution,
the pool lookup."""

import math

import pytest
import torch
from gpytorch.kernels import MaternKernel

import torchpref
from torchpref.data.preference_data import PreferenceData
from torchpref.simulation.twins import (
    PoolUtility,
    draw_twin,
    matern_covariance,
    population_mean_posterior,
    twin_deviation_covariance,
)

D = torch.float64


@pytest.fixture(scope="module")
def pop_and_pool():
    g = torch.Generator().manual_seed(3)
    pool = torch.rand(10, 2, generator=g, dtype=D)
    u = pool[:, 0] - 0.5 * pool[:, 1]
    people = []
    for _ in range(12):
        idx = torch.randperm(10, generator=g)[:6]
        C = [[i, j] if u[idx[i]] > u[idx[j]] else [j, i] for i, j in [(0, 1), (2, 3), (4, 5), (1, 2)]]
        people.append(PreferenceData.create(pool[idx], torch.tensor(C)))
    return torchpref.fit_population(people, max_iter=5), pool


@pytest.mark.parametrize("nu", [0.5, 1.5, 2.5])
def test_matern_covariance_is_gpytorchs(nu):
    X = torch.rand(7, 3, generator=torch.Generator().manual_seed(1), dtype=D)
    ls = torch.tensor([0.3, 0.7, 1.4], dtype=D)
    k = MaternKernel(nu=nu, ard_num_dims=3).double()
    k.lengthscale = ls
    torch.testing.assert_close(matern_covariance(X, ls, 2.0, nu), 2.0 * k(X).to_dense().detach())


def test_matern_covariance_refuses_bad_input():
    X = torch.rand(4, 2, dtype=D)
    with pytest.raises(ValueError, match="nu must be"):
        matern_covariance(X, torch.ones(2), 1.0, 1.0)
    with pytest.raises(ValueError, match="positive lengthscales"):
        matern_covariance(X, torch.tensor([1.0, -1.0]), 1.0, 1.5)


def test_mean_posterior_is_the_person_prior_less_the_deviation(pop_and_pool):
    pop, pool = pop_and_pool
    mean, cov = population_mean_posterior(pop, pool)
    prior = pop.person_model(pool).posterior(pool)
    torch.testing.assert_close(mean, prior.mean.reshape(-1).detach())
    kg = pop.k_g(pool).to_dense().detach()
    torch.testing.assert_close(cov + kg, prior.distribution.covariance_matrix.detach())
    assert float(torch.linalg.eigvalsh(cov).min()) > -1e-8  # Cov[m | D] is a covariance


def test_twin_draws_have_the_twin_distribution_not_the_learners(pop_and_pool):
    """Conditional on the drawn kernel, many twins' utilities have mean E[m | D] and covariance
    Cov[m | D] + the Matérn deviation's; the deviation is not the learner's k_g."""
    pop, pool = pop_and_pool
    mean, cov_m = population_mean_posterior(pop, pool)
    n = 1500
    draws, covs = [], []
    for s in range(n):
        g = torch.Generator().manual_seed(s)
        K, _ = twin_deviation_covariance(pop, pool, torch.Generator().manual_seed(s))
        u, _ = draw_twin(pop, pool, g, prior=(mean, cov_m))
        draws.append(u.f)
        covs.append(K)
    F = torch.stack(draws)
    expected = cov_m + torch.stack(covs).mean(0)
    scale = expected.diagonal().mean()
    assert float((F.mean(0) - mean).abs().max()) < 4 * math.sqrt(float(scale) / n)
    emp = torch.cov(F.T)
    assert float((emp - expected).abs().max() / scale) < 0.15
    kg = pop.k_g(pool).to_dense().detach()
    apart = torch.stack([(K - kg).norm() / kg.norm() for K in covs])
    assert float(apart.median()) > 0.2  # a twin's deviation is not the learner's k_g
    one, _ = draw_twin(pop, pool, torch.Generator().manual_seed(0))  # computing the prior itself
    torch.testing.assert_close(one.f, draws[0])


def test_twin_draw_is_reproducible_and_records_the_kernel(pop_and_pool):
    pop, pool = pop_and_pool
    a, da = draw_twin(pop, pool, torch.Generator().manual_seed(9))
    b, db = draw_twin(pop, pool, torch.Generator().manual_seed(9))
    torch.testing.assert_close(a.f, b.f)
    assert da == db and da.nu in (0.5, 1.5) and all(0.5 <= c <= 2.0 for c in da.lengthscale_factors)


def test_pool_utility_looks_items_up_and_refuses_others():
    X = torch.rand(30, 3, generator=torch.Generator().manual_seed(2), dtype=D)
    f = torch.randn(30, generator=torch.Generator().manual_seed(4), dtype=D)
    u = PoolUtility(X, f)
    idx = torch.tensor([5, 0, 29, 5])
    torch.testing.assert_close(u(X[idx]), f[idx], rtol=0, atol=0)
    with pytest.raises(ValueError, match="not in the twin's pool"):
        u(X[:2] + 1e-6)
    with pytest.raises(ValueError, match="N finite utilities"):
        PoolUtility(X, f[:3])
