"""PreferenceGP as a BoTorch model: shapes, predictives, fitting, updates, transforms, caching."""

import copy
import math

import pytest
import torch
from gpytorch.kernels import RBFKernel, ScaleKernel

from torchpref.models.preference_gp import LaplaceMarginalLogLikelihood, PreferenceGP
from torchpref.testing import rand, random_comparisons

SQRT2 = math.sqrt(2.0)


def kernel(d, lengthscale=0.4, outputscale=1.0):
    k = ScaleKernel(RBFKernel(ard_num_dims=d)).to(torch.float64)
    k.base_kernel.lengthscale = lengthscale
    k.outputscale = outputscale
    return k


def problem(generator, n=9, d=2, p=6, q=4):
    X = rand(n, d, generator=generator)
    C = random_comparisons(n, p, generator)
    ri = torch.randperm(n, generator=generator)[:q]
    u = rand(q, generator=generator, low=0.1, high=0.9)
    return X, C, u, ri


@pytest.fixture
def model(generator):
    X, C, u, ri = problem(generator)
    return PreferenceGP(
        X, C, u, ri, covar_module=kernel(2), comparison_noise=0.2, rating_scale=0.8, rating_precision=40.0
    )


@pytest.mark.parametrize("batch", [(), (3,), (2, 3)])
def test_posterior_batch_shapes(model, generator, batch):
    q = 4
    X = rand(*batch, q, 2, generator=generator)
    post = model.posterior(X)
    assert post.mean.shape == (*batch, q, 1)
    assert post.variance.shape == (*batch, q, 1)
    assert post.distribution.covariance_matrix.shape == (*batch, q, q)
    # each batch element equals an unbatched call
    flat = X.reshape(-1, q, 2)
    means = post.mean.reshape(-1, q)
    covs = post.distribution.covariance_matrix.reshape(-1, q, q)
    for b in range(flat.shape[0]):
        single = model.posterior(flat[b])
        torch.testing.assert_close(means[b], single.mean.squeeze(-1), rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(covs[b], single.distribution.covariance_matrix, rtol=1e-10, atol=1e-12)
    assert (post.variance > 0).all()
    s = post.rsample(torch.Size([5]))
    assert s.shape == (5, *batch, q, 1)


def test_expected_rating_and_preference_probability(model, generator):
    X = rand(2, 5, 2, generator=generator)
    er = model.expected_rating(X)
    assert er.shape == (2, 5)
    post = model.posterior(X.unsqueeze(-2))
    m, v = post.mean.reshape(2, 5), post.variance.reshape(2, 5)
    torch.testing.assert_close(er, torch.special.ndtr(m / torch.sqrt(2 * 0.8**2 + v)))
    Xa, Xb = rand(6, 2, generator=generator), rand(6, 2, generator=generator)
    pp = model.preference_probability(Xa, Xb)
    assert pp.shape == (6,)
    for k in range(6):  # row by row, with the pair's joint covariance
        mvn = model.posterior(torch.stack([Xa[k], Xb[k]])).distribution
        S = mvn.covariance_matrix
        var = S[0, 0] + S[1, 1] - 2 * S[0, 1]
        ref = torch.special.ndtr((mvn.mean[0] - mvn.mean[1]) / torch.sqrt(2 * 0.2**2 + var))
        torch.testing.assert_close(pp[k], ref)
    torch.testing.assert_close(model.preference_probability(Xb, Xa), 1 - pp)
    with pytest.raises(ValueError, match="same shape"):
        model.preference_probability(Xa, Xb[:3])


def test_fit_gpytorch_mll_increases_evidence(generator):
    from botorch.fit import fit_gpytorch_mll

    X, C, u, ri = problem(generator, n=10, p=8, q=5)
    model = PreferenceGP(
        X,
        C,
        u,
        ri,
        covar_module=kernel(2, lengthscale=0.05, outputscale=0.3),
        comparison_noise=0.2,
        rating_scale=0.8,
        rating_precision=40.0,
    )
    mll = LaplaceMarginalLogLikelihood(model)
    before = float(mll().detach())
    ls_before = model.covar_module.base_kernel.lengthscale.detach().clone()
    fit_gpytorch_mll(mll)
    after = float(mll().detach())
    assert after > before + 1e-3
    assert not torch.equal(model.covar_module.base_kernel.lengthscale.detach(), ls_before)
    assert model.mode.converged


def test_changing_hyperparameters_resolves_with_warm_start(model, generator):
    Xs = rand(5, 2, generator=generator)
    m0 = model.posterior(Xs).mean.detach().clone()
    cold_iters = model.mode.iterations
    model.covar_module.base_kernel.lengthscale = model.covar_module.base_kernel.lengthscale * 1.02
    m1 = model.posterior(Xs).mean.detach()
    assert not torch.allclose(m0, m1, atol=1e-6)
    assert model.mode.iterations < cold_iters  # warm-started from the previous mode
    fresh = PreferenceGP(
        model.train_X,
        model.comparisons,
        model.ratings,
        model.rating_index,
        covar_module=copy.deepcopy(model.covar_module),
        comparison_noise=0.2,
        rating_scale=0.8,
        rating_precision=40.0,
    )
    torch.testing.assert_close(m1, fresh.posterior(Xs).mean.detach(), rtol=0, atol=1e-6)


def test_add_observations_equals_from_scratch(generator):
    X, C, u, ri = problem(generator)
    kw = dict(comparison_noise=0.2, rating_scale=0.8, rating_precision=40.0)
    model = PreferenceGP(X[:6], C[(C < 6).all(-1)], u[ri < 6], ri[ri < 6], covar_module=kernel(2), **kw)
    Xs = rand(7, 2, generator=generator)
    # new items (rows of X_new; indices refer to X_new), one of them a duplicate of an old item
    X_new = torch.cat([X[6:], X[:1]])  # items 6, 7, 8 and a copy of item 0
    C_new = torch.tensor([[0, 3], [2, 1]])  # 6 > 0, 8 > 7
    model.add_observations(
        X_new, comparisons=C_new, ratings=torch.tensor([0.7], dtype=torch.float64), rating_index=torch.tensor([1])
    )
    assert model.train_X.shape[0] == 9  # the copy of item 0 reused its index
    C_all = torch.cat([C[(C < 6).all(-1)], torch.tensor([[6, 0], [8, 7]])])
    u_all = torch.cat([u[ri < 6], torch.tensor([0.7], dtype=torch.float64)])
    ri_all = torch.cat([ri[ri < 6], torch.tensor([7])])
    scratch = PreferenceGP(X, C_all, u_all, ri_all, covar_module=kernel(2), **kw)
    torch.testing.assert_close(model.train_X, scratch.train_X)
    torch.testing.assert_close(model.comparisons, scratch.comparisons)
    p1, p2 = model.posterior(Xs), scratch.posterior(Xs)
    torch.testing.assert_close(p1.mean, p2.mean, rtol=0, atol=1e-6)
    torch.testing.assert_close(p1.variance, p2.variance, rtol=0, atol=1e-6)
    torch.testing.assert_close(model.log_marginal_likelihood(), scratch.log_marginal_likelihood(), rtol=0, atol=1e-8)
    # indices into train_X when X is not given
    model.add_observations(comparisons=torch.tensor([[1, 2]]))
    assert model.comparisons.shape[0] == scratch.comparisons.shape[0] + 1


def test_condition_on_observations_leaves_original_unchanged(model, generator):
    Xs = rand(4, 2, generator=generator)
    before = model.posterior(Xs).mean.detach().clone()
    n, p, q = model.train_X.shape[0], model.comparisons.shape[0], model.ratings.shape[0]
    Xn = rand(2, 2, generator=generator)
    new = model.condition_on_observations(
        Xn, ratings=torch.tensor([0.9, 0.2], dtype=torch.float64), comparisons=torch.tensor([[0, 1]])
    )
    assert new is not model
    assert (model.train_X.shape[0], model.comparisons.shape[0], model.ratings.shape[0]) == (n, p, q)
    assert (new.train_X.shape[0], new.comparisons.shape[0], new.ratings.shape[0]) == (n + 2, p + 1, q + 2)
    torch.testing.assert_close(model.posterior(Xs).mean.detach(), before, rtol=0, atol=0)
    assert not torch.allclose(new.posterior(Xs).mean.detach(), before, atol=1e-4)


def test_normalize_input_transform_equals_manual(generator):
    from botorch.models.transforms.input import Normalize

    X, C, u, ri = problem(generator)
    lo = torch.tensor([-3.0, 10.0], dtype=torch.float64)
    hi = torch.tensor([5.0, 10.5], dtype=torch.float64)
    Xraw = lo + (hi - lo) * X
    kw = dict(comparison_noise=0.2, rating_scale=0.8, rating_precision=40.0)
    tf_model = PreferenceGP(Xraw, C, u, ri, covar_module=kernel(2), input_transform=Normalize(2), **kw)
    assert tf_model.comparisons.shape[0] == C.shape[0] and tf_model.ratings.shape[0] == u.shape[0]
    torch.testing.assert_close(tf_model.train_X, Xraw)
    mn, mx = Xraw.min(0).values, Xraw.max(0).values
    manual = PreferenceGP((Xraw - mn) / (mx - mn), C, u, ri, covar_module=kernel(2), **kw)
    Xs = lo + (hi - lo) * rand(3, 5, 2, generator=generator)
    p1, p2 = tf_model.posterior(Xs), manual.posterior((Xs - mn) / (mx - mn))
    torch.testing.assert_close(p1.mean, p2.mean, rtol=0, atol=1e-9)
    torch.testing.assert_close(p1.variance, p2.variance, rtol=0, atol=1e-9)
    torch.testing.assert_close(tf_model.log_marginal_likelihood(), manual.log_marginal_likelihood())


@pytest.mark.parametrize("q", [1, 2])
def test_optimize_acqf_ucb_in_bounds(model, q):
    from botorch.acquisition import UpperConfidenceBound, qUpperConfidenceBound
    from botorch.optim import optimize_acqf
    from botorch.sampling import SobolQMCNormalSampler

    bounds = torch.tensor([[0.0, 0.0], [1.0, 1.0]], dtype=torch.float64)
    if q == 1:
        acqf = UpperConfidenceBound(model, beta=9.0)
    else:
        acqf = qUpperConfidenceBound(model, beta=9.0, sampler=SobolQMCNormalSampler(torch.Size([64]), seed=0))
    torch.manual_seed(0)  # optimize_acqf's raw samples use the global generator
    cand, val = optimize_acqf(acqf, bounds, q=q, num_restarts=2, raw_samples=32)
    assert cand.shape == (q, 2)
    assert ((cand >= 0) & (cand <= 1)).all()
    assert torch.isfinite(val).all()
    if q == 1:  # UCB with beta = 9: mean + 3 sd, and the optimum beats random points
        post = model.posterior(cand)
        torch.testing.assert_close(acqf(cand.unsqueeze(0)), (post.mean + 3 * post.variance.sqrt()).reshape(1))
        Xr = rand(50, 1, 2, generator=torch.Generator().manual_seed(1))
        assert float(val) >= float(acqf(Xr).max().detach()) - 1e-6


def test_state_dict_restores_posterior(model, generator):
    model.covar_module.base_kernel.lengthscale = torch.tensor([0.3, 0.55], dtype=torch.float64)
    model.covar_module.outputscale = 1.7
    Xs = rand(5, 2, generator=generator)
    ref = model.posterior(Xs)
    sd = copy.deepcopy(model.state_dict())
    other = PreferenceGP(
        model.train_X,
        model.comparisons,
        model.ratings,
        model.rating_index,
        covar_module=kernel(2),
        comparison_noise=0.2,
        rating_scale=0.8,
        rating_precision=40.0,
    )
    assert not torch.allclose(other.posterior(Xs).mean, ref.mean, atol=1e-4)
    other.load_state_dict(sd)
    p = other.posterior(Xs)
    # the two modes were reached from different starting points; both stop at a Newton
    # decrement below 1e-11 (|df| ~ 1e-7), hence 1e-6 rather than round-off
    torch.testing.assert_close(p.mean, ref.mean, rtol=0, atol=1e-6)
    torch.testing.assert_close(p.variance, ref.variance, rtol=0, atol=1e-6)


def test_repeated_posterior_calls_do_not_refactorise(model, generator, monkeypatch):
    Xs = rand(4, 2, generator=generator)
    model.posterior(Xs)
    cache = model._cache
    calls = {"n": 0}
    real = torch.linalg.cholesky_ex

    def counting(*args, **kwargs):
        calls["n"] += 1
        return real(*args, **kwargs)

    monkeypatch.setattr(torch.linalg, "cholesky_ex", counting)
    for _ in range(3):
        model.posterior(Xs)
        model.expected_rating(Xs)
    assert calls["n"] == 0
    assert model._cache is cache
    # a hyperparameter change does refactorise
    model.covar_module.outputscale = 0.5
    model.posterior(Xs)
    assert calls["n"] > 0 and model._cache is not cache


def test_likelihood_parameters_learnable(generator):
    X, C, u, ri = problem(generator)
    fixed = PreferenceGP(X, C, u, ri, covar_module=kernel(2))
    learn = PreferenceGP(X, C, u, ri, covar_module=kernel(2), learn_likelihood=True)
    names_fixed = {n for n, p in fixed.named_parameters() if p.requires_grad}
    names_learn = {n for n, p in learn.named_parameters() if p.requires_grad}
    assert not any("comparison_noise" in n or "rating_" in n for n in names_fixed)
    assert {
        "likelihood.comparison.raw_comparison_noise",
        "likelihood.rating.raw_rating_scale",
        "likelihood.rating.raw_rating_precision",
    } <= names_learn


def test_posterior_rejects_wrong_dimension(model):
    with pytest.raises(ValueError, match="columns"):
        model.posterior(torch.zeros(3, 5, dtype=torch.float64))


def test_model_without_items_is_the_prior_and_accepts_data(generator):
    model = PreferenceGP(torch.zeros(0, 2, dtype=torch.float64), covar_module=kernel(2))
    Xs = rand(4, 1, 2, generator=generator)
    post = model.posterior(Xs)
    torch.testing.assert_close(post.mean, torch.zeros_like(post.mean))
    prior_var = model.covar_module(Xs.squeeze(-2)).to_dense().diagonal()
    torch.testing.assert_close(post.variance.reshape(-1), prior_var.detach())
    model.add_observations(rand(2, 2, generator=generator), comparisons=torch.tensor([[0, 1]]))
    mean = model.posterior(model.train_X.unsqueeze(-2)).mean.reshape(-1)
    assert mean[0] > mean[1]


def test_marginals_equal_the_posteriors_diagonal(model, generator):
    """``marginals`` (the fast path of ``expected_rating``) against ``posterior``: plain, with a
    Normalize input transform, a kernel on selected ``active_dims``, and with no data (prior)."""
    from botorch.models.transforms.input import Normalize
    from gpytorch.kernels import RBFKernel, ScaleKernel

    X = rand(3, 4, 2, generator=generator)
    d = model.data
    models = [
        model,
        PreferenceGP(
            3 * d.train_X + 1,
            d.comparisons,
            d.ratings,
            d.rating_index,
            covar_module=kernel(2),
            input_transform=Normalize(2),
        ),
        PreferenceGP(
            d.train_X,
            d.comparisons,
            d.ratings,
            d.rating_index,
            covar_module=ScaleKernel(RBFKernel(active_dims=[1])).to(torch.float64),
        ),
        PreferenceGP(torch.zeros(0, 2, dtype=torch.float64), covar_module=kernel(2)),
    ]
    for m in models:
        mean, var = m.marginals(X)
        post = m.posterior(X.unsqueeze(-2))
        assert mean.shape == var.shape == (3, 4)
        torch.testing.assert_close(mean, post.mean.reshape(3, 4), rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(var, post.variance.reshape(3, 4), rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match="columns"):
        model.marginals(rand(4, 3, generator=generator))


def test_a_dropped_model_is_freed_without_the_cycle_collector(model, generator):
    """No reference cycle in the model's own modules (GPyTorch's load_state_dict hook holds them
    weakly), so a model and its mode's matrices go when the last reference does; loading a state
    dict still runs that hook (it ignores shapes)."""
    import gc
    import weakref

    d = model.data
    m = PreferenceGP(d.train_X, d.comparisons, d.ratings, d.rating_index, covar_module=kernel(2))
    mll = LaplaceMarginalLogLikelihood(m)
    m.mode  # noqa: B018
    refs = [weakref.ref(x) for x in (m, mll, m.likelihood, m.likelihood.rating, m.likelihood.strict, m._cache)]
    gc.disable()
    try:
        del m, mll
        assert all(r() is None for r in refs)
    finally:
        gc.enable()
    other = PreferenceGP(d.train_X, d.comparisons, d.ratings, d.rating_index, covar_module=kernel(2))
    other.load_state_dict(model.state_dict())
    torch.testing.assert_close(other.posterior(d.train_X).mean, model.posterior(d.train_X).mean)
