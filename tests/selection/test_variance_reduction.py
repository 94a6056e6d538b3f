"""The top region's variance reduction per effort: its formulas against brute force and Laplace
refits, and its choice between a rating and a ranking in cases checked by hand."""

import math

import numpy as np
import pytest
import torch
from scipy.optimize import minimize
from scipy.stats import beta

from torchpref import BatchedPreferenceGP, PreferenceGP
from torchpref.data.queries import RankingQuery, RatingQuery
from torchpref.likelihoods.pairwise_beta import PairwiseProbitLikelihood
from torchpref.models.fantasy import condition_batch
from torchpref.models.kernels import fixed_rbf_kernel
from torchpref.selection.samples import joint_samples
from torchpref.selection.top_profile import ProfileVariancePerEffort
from torchpref.selection.variance_reduction import (
    VariancePerEffort,
    choice_answer_probabilities,
    ranking_mode_hessians,
    rating_hessian,
    variance_reduction,
)

D = torch.float64


def _spd(n, g):
    A = torch.randn(n, n, generator=g, dtype=D)
    return A @ A.T / n + 0.1 * torch.eye(n, dtype=D)


def test_variance_reduction_is_the_posterior_covariance_update(generator):
    """sum_i w_i s_i^2 (Sigma - (Sigma^-1 + E H E^T)^-1)_ii, with dense inverses."""
    N, q = 7, 3
    cov = _spd(N, generator)
    w, s = torch.rand(N, generator=generator, dtype=D), torch.rand(N, generator=generator, dtype=D)
    rows = torch.tensor([[0, 3, 5], [6, 1, 2]])
    Hs = torch.stack([_spd(q, generator), _spd(q, generator)])
    got = variance_reduction(cov.unsqueeze(0), w.unsqueeze(0), rows.unsqueeze(0), Hs.unsqueeze(0), s.unsqueeze(0))[0]
    for r in range(2):
        E = torch.zeros(N, q, dtype=D)
        E[rows[r], torch.arange(q)] = 1.0
        post = torch.linalg.inv(torch.linalg.inv(cov) + E @ Hs[r] @ E.T)
        want = (w * s * s * (cov - post).diagonal()).sum()
        assert float(got[r]) == pytest.approx(float(want), rel=1e-9)


def test_ranking_mode_hessians_against_scipy_and_autograd(generator):
    """For each answer j, the mode of log N(f; m, C) + sum_{k != j} log Phi((f_j - f_k) / s) by
    SciPy, and the likelihood's Hessian there by autograd."""
    q = 4
    m = torch.randn(q, generator=generator, dtype=D)
    C = _spd(q, generator)
    lik = PairwiseProbitLikelihood(comparison_noise=0.1)
    got = ranking_mode_hessians(m, C, lik)  # q x q x q
    Ci = torch.linalg.inv(C)

    def loglik(f, j):
        eta = torch.stack([f[j] - f[k] for k in range(q) if k != j])
        return lik.log_prob(eta).sum()

    for j in range(q):

        def obj(x):
            f = torch.tensor(x, dtype=D, requires_grad=True)
            val = -(loglik(f, j) - 0.5 * (f - m) @ Ci @ (f - m))
            val.backward()
            return float(val.detach()), f.grad.numpy()

        res = minimize(obj, m.numpy(), jac=True, method="BFGS", options={"gtol": 1e-10})
        f_hat = torch.tensor(res.x, dtype=D)
        H = -torch.autograd.functional.hessian(lambda f: loglik(f, j), f_hat)
        assert torch.allclose(got[j], H, atol=1e-5 * float(H.abs().max()) + 1e-8)
        assert torch.allclose(got[j].sum(-1), torch.zeros(q, dtype=D), atol=1e-9)  # differences only


def test_choice_answer_probabilities_pairs_match_quadrature(generator):
    F = torch.randn(50, 2, generator=generator, dtype=D)
    from torchpref.acquisition.functions import choice_probabilities

    noise = torch.tensor(0.3, dtype=D)
    assert torch.allclose(choice_answer_probabilities(F, noise), choice_probabilities(F, noise, 12).mean(0), atol=1e-6)


def _model(X, comparisons=None, ratings=None, rating_index=None, **kw):
    settings = dict(comparison_noise=0.1, rating_scale=0.8, rating_precision=10.0)
    settings.update(kw)
    return PreferenceGP(X, comparisons, ratings, rating_index, covar_module=fixed_rbf_kernel(0.1, 1.0, X), **settings)


def _plateau_case():
    g = torch.Generator().manual_seed(3)
    util = lambda X: 2 * torch.sigmoid((0.25 - (X - 0.5).norm(dim=-1)) / 0.03)  # noqa: E731
    X = torch.rand(12, 2, generator=g, dtype=D)
    C = []
    for _ in range(6):
        idx = torch.randperm(12, generator=g)[:5]
        w = idx[util(X[idx]).argmax()]
        C += [[int(w), int(k)] for k in idx if k != w]
    return _model(X, torch.tensor(C)), torch.rand(40, 2, generator=g, dtype=D)


def test_values_match_laplace_refits_on_fantasies():
    """The rating's value against Laplace refits on Monte Carlo answers (f from the posterior, a
    Beta rating given f); the ranking's against the m refits, one per answer, weighted by the
    answer's predictive probability. Both within 10 % (the refits re-linearise the old data
    too; the formula keeps the old posterior Gaussian)."""
    model, Xc = _plateau_case()
    sel = VariancePerEffort(m=5, num_samples=512, num_hessian_samples=512)
    with torch.no_grad():
        post = model.posterior(Xc)
        mean, cov = post.mean.reshape(1, -1), post.distribution.covariance_matrix.unsqueeze(0)
        F, _ = joint_samples(mean, cov, [torch.Generator().manual_seed(1)], 512)
        w, s = sel.weights(F, mean, cov.diagonal(dim1=-2, dim2=-1), model.likelihood.rating)

        def loss(m):
            return (m.posterior(Xc).variance.reshape(-1, 40) * w * s * s).sum(-1)

        L0 = float(loss(model))
        h = rating_hessian(F, model.likelihood.rating)
        red = variance_reduction(cov, w, torch.arange(40).reshape(1, 40, 1), h.reshape(1, 40, 1, 1), s)[0]
        i = int(red.argmax())
        mu = model.likelihood.rating.mean_link(F[0, :, i])
        u = torch.from_numpy(beta.rvs(10 * mu.numpy(), 10 * (1 - mu.numpy()), random_state=np.random.default_rng(0)))
        u = u.clamp(1e-3, 1 - 1e-3)  # as the model stores ratings at 0 or 1
        refit = condition_batch(model, Xc[i : i + 1], ratings=u.reshape(-1, 1), rating_index=torch.zeros(512, 1).long())
        assert float(red[i]) == pytest.approx(L0 - float(loss(refit).mean()), rel=0.1)

        _, _, rows, value = sel.values(model, Xc.unsqueeze(0), [torch.Generator().manual_seed(2)])
        Q = rows[0]
        P = choice_answer_probabilities(F[0][:, Q], model.likelihood.comparison.comparison_noise)
        comps = torch.stack([torch.tensor([[j, k] for k in range(5) if k != j]) for j in range(5)])
        refit = condition_batch(model, Xc[Q], comparisons=comps)
        assert float(value[0]) * sel.ranking_cost == pytest.approx(L0 - float((P * loss(refit)).sum()), rel=0.1)


def _line(n=8):
    return torch.linspace(0.3, 0.7, n, dtype=D).unsqueeze(-1)


BOTH = pytest.mark.parametrize("selector", [VariancePerEffort, ProfileVariancePerEffort], ids=lambda c: c.__name__)


@BOTH
def test_rating_when_the_scale_is_uncalibrated(selector):
    """Items close together, their order known from many precise comparisons, no rating: a
    ranking can only repeat what is known (differences, the top set), a rating gives the level."""
    X = _line()
    C = torch.tensor([[k + 1, k] for k in range(7)] * 4)
    model = _model(X, C, comparison_noise=0.05)
    q = selector(m=4).select(model, X, None, 0, 10, torch.Generator().manual_seed(0))
    assert isinstance(q, RatingQuery)


@BOTH
def test_ranking_when_the_top_is_unresolved(selector):
    """The same items, each rated 3 times (0.7): the level is known, the order of the items is
    not (ratings are imprecise, nu = 10); precise comparisons resolve it."""
    X = _line()
    idx = torch.arange(8).repeat(3)
    model = _model(X, ratings=torch.full((24,), 0.7, dtype=D), rating_index=idx, comparison_noise=0.05)
    q = selector(m=4).select(model, X, None, 0, 10, torch.Generator().manual_seed(0))
    assert isinstance(q, RankingQuery)


def test_costs_decide_and_batch_matches_single_trials():
    """With rankings made very expensive the selector rates; a batch of trials gives each
    trial's single-trial query."""
    X = _line()
    idx = torch.arange(8).repeat(3)
    model = _model(X, ratings=torch.full((24,), 0.7, dtype=D), rating_index=idx, comparison_noise=0.05)
    gen = torch.Generator().manual_seed(0)
    assert isinstance(VariancePerEffort(m=4, ranking_cost=1e3).select(model, X, None, 0, 10, gen), RatingQuery)
    model2, _ = _plateau_case()
    g = torch.Generator().manual_seed(5)
    Xc = torch.rand(2, 30, 2, generator=g, dtype=D)
    models = [_model(model2.train_X, model2.comparisons), model2]
    batch = BatchedPreferenceGP.from_models(models)
    sel = VariancePerEffort(m=4)
    many = sel.select_batch(batch, Xc, [None, None], 0, 10, [torch.Generator().manual_seed(b) for b in range(2)])
    for b in range(2):
        one = sel.select(models[b], Xc[b], None, 0, 10, torch.Generator().manual_seed(b))
        assert type(one) is type(many[b])
        items = (one.item, many[b].item) if isinstance(one, RatingQuery) else (one.items, many[b].items)
        assert torch.allclose(*items)


def test_bad_arguments():
    with pytest.raises(ValueError, match="costs"):
        VariancePerEffort(rating_cost=0)
    with pytest.raises(ValueError, match="top_fraction"):
        VariancePerEffort(top_fraction=1.5)
    with pytest.raises(ValueError, match="m >= 2"):
        VariancePerEffort(m=1)
    assert math.isclose(VariancePerEffort(m=5).ranking_cost, 2.0)


def test_rating_slopes_and_an_ordinal_model(generator):
    """The slope of the expected rating is phi(m / s) / s for Beta ratings (s = sqrt(2 sigma_B^2
    + v)); an ordered-probit model (ratings as levels) is served through its own
    ``expected_rating`` and ``fisher``."""
    sel = VariancePerEffort(m=3)
    mean, var = torch.randn(1, 9, generator=generator, dtype=D), torch.rand(1, 9, generator=generator, dtype=D)
    X = _line()
    lik = _model(X).likelihood.rating
    _, g = sel.weights(torch.randn(1, 16, 9, generator=generator, dtype=D), mean, var, lik)
    s = (2 * 0.8**2 + var).sqrt()
    assert torch.allclose(g, torch.exp(-0.5 * (mean / s) ** 2) / (s * math.sqrt(2 * math.pi)), rtol=1e-6)
    ordinal = PreferenceGP(
        X,
        torch.tensor([[1, 0], [5, 2]]),
        torch.tensor([4.0, 2.0]),
        torch.tensor([3, 6]),
        covar_module=fixed_rbf_kernel(0.1, 1.0, X),
        rating_levels=5,
    )
    q = sel.select(ordinal, X, None, 0, 5, generator)
    assert isinstance(q, (RatingQuery, RankingQuery))
