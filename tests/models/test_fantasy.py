"""Batched training data, conditioning on batches and fantasy models, each problem against a
model of that problem alone; BoTorch's look-ahead acquisition functions on fantasy models."""

import pytest
import torch
from botorch.acquisition import qKnowledgeGradient, qNegIntegratedPosteriorVariance
from botorch.sampling.normal import SobolQMCNormalSampler
from botorch.sampling.pairwise_samplers import PairwiseSobolQMCNormalSampler
from gpytorch.kernels import RBFKernel, ScaleKernel

from torchpref import PreferenceGP
from torchpref.testing import random_comparisons


def kernel(device):
    k = ScaleKernel(RBFKernel(ard_num_dims=2)).to(device=device, dtype=torch.float64)
    k.base_kernel.lengthscale = torch.tensor([0.3, 0.5])
    k.outputscale = 1.5
    return k


def make_model(device, generator, n=8, p=6):
    X = torch.rand(n, 2, generator=generator, dtype=torch.float64).to(device)
    C = random_comparisons(n, p, generator).to(device)
    return PreferenceGP(
        X,
        C,
        ratings=torch.tensor([0.3, 0.8], device=device),
        rating_index=[0, n - 1],
        covar_module=kernel(device),
        comparison_noise=0.5,
    )


def single(model, X, **kw):
    """The unbatched model conditioned on ``X`` and observations, one problem."""
    return model.condition_on_observations(X, **kw)


def test_batched_training_data_equals_separate_models(device, generator):
    b, n = 3, 7
    X = torch.rand(b, n, 2, generator=generator, dtype=torch.float64).to(device)
    C = torch.stack([random_comparisons(n, 5, generator) for _ in range(b)]).to(device)
    u = torch.rand(b, 2, generator=generator, dtype=torch.float64).to(device) * 0.8 + 0.1
    ri = torch.randint(0, n, (b, 2), generator=generator).to(device)
    batched = PreferenceGP(X, C, u, ri, covar_module=kernel(device))
    assert batched.batch_shape == torch.Size([b]) and batched.train_X.shape == (b, n, 2)
    Xq = torch.rand(4, b, 3, 2, generator=generator, dtype=torch.float64).to(device)
    post = batched.posterior(Xq)
    assert post.mean.shape == (4, b, 3, 1)
    evidence = batched.log_marginal_likelihood()
    assert evidence.shape == (b,)
    (grad,) = torch.autograd.grad(evidence.sum(), batched.covar_module.raw_outputscale)
    total = 0.0
    for k in range(b):
        one = PreferenceGP(X[k], C[k], u[k], ri[k], covar_module=kernel(device))
        torch.testing.assert_close(batched.mode.f[k], one.mode.f, rtol=0, atol=1e-6)
        ref = one.posterior(Xq[:, k])
        torch.testing.assert_close(post.mean[:, k], ref.mean, rtol=0, atol=1e-6)
        torch.testing.assert_close(post.variance[:, k], ref.variance, rtol=0, atol=1e-6)
        torch.testing.assert_close(evidence[k], one.log_marginal_likelihood(), rtol=0, atol=1e-6)
        total = total + torch.autograd.grad(one.log_marginal_likelihood(), one.covar_module.raw_outputscale)[0]
    torch.testing.assert_close(grad, total, rtol=1e-8, atol=1e-10)
    # q x d test points broadcast over the batch
    assert batched.posterior(Xq[0, 0]).mean.shape == (b, 3, 1)


def test_batched_training_data_of_different_lengths(generator):
    X = torch.rand(2, 5, 1, generator=generator, dtype=torch.float64)
    model = PreferenceGP(
        X,
        [torch.tensor([[0, 1]]), torch.tensor([[1, 2], [3, 4], [0, 4]])],
        covar_module=ScaleKernel(RBFKernel()).to(torch.float64),
    )
    one = PreferenceGP(X[1], torch.tensor([[1, 2], [3, 4], [0, 4]]), covar_module=model.covar_module)
    torch.testing.assert_close(model.mode.f[1], one.mode.f, rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="expected 2 per-problem entries, got 1"):
        PreferenceGP(X, [torch.tensor([[0, 1]])])


@pytest.mark.parametrize("kind", ["comparisons", "ratings"])
def test_fantasy_model_equals_conditioned_single_models(kind, device, generator):
    model = make_model(device, generator)
    Xc = torch.rand(5, 3, 2, generator=generator, dtype=torch.float64).to(device)
    if kind == "comparisons":
        sampler = PairwiseSobolQMCNormalSampler(torch.Size([4]), seed=1)
    else:
        sampler = SobolQMCNormalSampler(torch.Size([4]), seed=1)
    fantasy = model.fantasize(Xc, sampler)
    assert fantasy.batch_shape == torch.Size([4, 5])
    assert fantasy.mode.converged.all()
    Xt = torch.rand(6, 2, generator=generator, dtype=torch.float64).to(device)
    post = fantasy.posterior(Xt)
    assert post.mean.shape == (4, 5, 6, 1)
    n = model.train_X.shape[0]
    for s, j in [(0, 0), (3, 4), (2, 1)]:
        if kind == "comparisons":
            C = fantasy.comparisons[s, j, model.comparisons.shape[0] :] - n
            assert C.shape == (3, 2)  # all pairs of the three points
            ref = single(model, Xc[j], comparisons=C)
        else:
            u = fantasy.ratings[s, j, 2:]
            assert ((u > 0) & (u < 1)).all()
            ref = single(model, Xc[j], ratings=u, rating_index=torch.arange(3, device=device))
        torch.testing.assert_close(post.mean[s, j], ref.posterior(Xt).mean, rtol=0, atol=1e-6)
        torch.testing.assert_close(post.variance[s, j], ref.posterior(Xt).variance, rtol=0, atol=1e-6)
    assert model.batch_shape == torch.Size([])  # the model itself is unchanged


def test_comparison_fantasies_follow_the_probit(generator):
    """Fantasised comparisons of two points are drawn from the perceived utilities, so their
    frequency matches the model's preference probability (eq. 3 with the posterior)."""
    model = make_model(torch.device("cpu"), generator)
    Xc = torch.tensor([[[0.2, 0.3], [0.7, 0.6]]], dtype=torch.float64)
    fantasy = model.fantasize(Xc, PairwiseSobolQMCNormalSampler(torch.Size([4096]), seed=3))
    n = model.train_X.shape[0]
    first_wins = (fantasy.comparisons[:, 0, -1, 0] == n).double().mean()
    expected = model.preference_probability(Xc[0, :1], Xc[0, 1:]).detach()
    assert 0.03 < float(expected) < 0.97
    assert abs(float(first_wins) - float(expected)) < 0.01


def test_conditioning_a_fantasy_batch(generator):
    model = make_model(torch.device("cpu"), generator)
    Xc = torch.rand(2, 2, 2, generator=generator, dtype=torch.float64)
    fantasy = model.fantasize(Xc, PairwiseSobolQMCNormalSampler(torch.Size([3]), seed=0))
    Xn = torch.rand(2, 2, generator=generator, dtype=torch.float64)
    again = fantasy.condition_on_observations(Xn, comparisons=torch.tensor([[1, 0]]))
    assert again.batch_shape == torch.Size([3, 2]) and again.train_X.shape[-2] == model.train_X.shape[0] + 4
    Xt = torch.rand(5, 2, generator=generator, dtype=torch.float64)
    n = model.train_X.shape[0]
    C = fantasy.comparisons[1, 0, -1:] - n
    ref = single(single(model, Xc[0], comparisons=C), Xn, comparisons=torch.tensor([[1, 0]]))
    torch.testing.assert_close(again.posterior(Xt).mean[1, 0], ref.posterior(Xt).mean, rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="integer indices into the 2 rows"):
        fantasy.condition_on_observations(Xn, comparisons=torch.tensor([[0, 2]]))


def test_knowledge_gradient_on_comparison_fantasies(device, generator):
    """qKnowledgeGradient with BoTorch's pairwise sampler equals the look-ahead written out with
    one conditioned model per fantasy."""
    model = make_model(device, generator)
    nf = 4
    acqf = qKnowledgeGradient(model, num_fantasies=nf, sampler=PairwiseSobolQMCNormalSampler(torch.Size([nf]), seed=2))
    X = torch.rand(3, 2 + nf, 2, generator=generator, dtype=torch.float64).to(device)  # 3 batches, q = 2
    value = acqf(X)
    assert value.shape == (3,) and torch.isfinite(value).all()
    fantasy = model.fantasize(X[:, :2], PairwiseSobolQMCNormalSampler(torch.Size([nf]), seed=2))
    n = model.train_X.shape[0]
    for b in range(3):
        best = []
        for s in range(nf):
            C = fantasy.comparisons[s, b, -1:] - n
            ref = single(model, X[b, :2], comparisons=C)
            best.append(ref.posterior(X[b, 2 + s].unsqueeze(0)).mean.reshape(()))
        torch.testing.assert_close(value[b], torch.stack(best).mean(), rtol=0, atol=1e-6)


def test_integrated_posterior_variance_on_rating_fantasies(device, generator):
    model = make_model(device, generator)
    mc = torch.rand(64, 2, generator=generator, dtype=torch.float64).to(device)
    acqf = qNegIntegratedPosteriorVariance(model, mc_points=mc)
    X = torch.rand(5, 2, 2, generator=generator, dtype=torch.float64).to(device)
    value = acqf(X)
    assert value.shape == (5,)
    prior = -model.posterior(mc).variance.mean()
    assert (value > prior).all()  # two more ratings reduce the integrated variance
    fantasy = model.fantasize(X, acqf.sampler)
    torch.testing.assert_close(
        value, -fantasy.posterior(mc).variance.mean(dim=(-2, -1)).reshape(5), rtol=1e-10, atol=1e-12
    )


def test_batched_kernel_hyperparameters_per_problem(generator):
    """A kernel of batch shape ``[b]`` (BoTorch's batched models): each problem with its own values."""
    b, n = 3, 8
    X = torch.rand(b, n, 2, generator=generator, dtype=torch.float64)
    C = torch.stack([random_comparisons(n, 5, generator) for _ in range(b)])
    k = ScaleKernel(RBFKernel(ard_num_dims=2, batch_shape=torch.Size([b])), batch_shape=torch.Size([b])).double()
    k.outputscale = torch.tensor([0.5, 1.0, 2.0])
    k.base_kernel.lengthscale = torch.tensor([[[0.2, 0.4]], [[0.3, 0.3]], [[0.6, 0.1]]])
    model = PreferenceGP(X, C, covar_module=k)
    Xt = torch.rand(4, b, 5, 2, generator=generator, dtype=torch.float64)
    post, evidence = model.posterior(Xt), model.log_marginal_likelihood()
    for j in range(b):
        kj = ScaleKernel(RBFKernel(ard_num_dims=2)).double()
        kj.outputscale = float(k.outputscale[j])
        kj.base_kernel.lengthscale = k.base_kernel.lengthscale[j]
        one = PreferenceGP(X[j], C[j], covar_module=kj)
        torch.testing.assert_close(post.mean[:, j], one.posterior(Xt[:, j]).mean, rtol=0, atol=1e-6)
        torch.testing.assert_close(evidence[j], one.log_marginal_likelihood(), rtol=0, atol=1e-6)


#: The traced derivative is the implicit-function one at the mode as solved (Newton decrement below
#: 1e-11, a gradient of order 1e-7 left), so it is exact only to first order in that residual:
#: about 3e-5 relative where a Beta rating (nu = 80, large third derivatives) sits on a fantasy point.
MODE_TOL_RTOL = 2e-4


def _central_difference(fn, X: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """``d fn / d X`` by central differences, entry by entry (float64)."""
    grad = torch.zeros_like(X)
    for i in range(X.numel()):
        d = torch.zeros_like(X).reshape(-1)
        d[i] = eps
        d = d.reshape(X.shape)
        grad.reshape(-1)[i] = (fn(X + d) - fn(X - d)) / (2 * eps)
    return grad


@pytest.mark.parametrize("kind", ["ratings", "comparisons"])
def test_fantasy_posterior_gradient_in_the_fantasy_points(kind, generator):
    """A fantasy model's posterior is differentiable in the fantasy points ``X`` through its mode
    (implicit function theorem): autograd equals central differences in float64."""
    model = make_model("cpu", generator)
    Xt = torch.rand(3, 2, generator=generator, dtype=torch.float64)
    X0 = torch.rand(2, 3, 2, generator=generator, dtype=torch.float64)  # 2 batches of q = 3

    def value(X):
        sampler = (PairwiseSobolQMCNormalSampler if kind == "comparisons" else SobolQMCNormalSampler)(
            torch.Size([4]), seed=5
        )
        post = model.fantasize(X, sampler).posterior(Xt)
        return post.mean.sum() + post.distribution.covariance_matrix.sum()

    X = X0.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(value(X), X)
    with torch.no_grad():
        fd = _central_difference(value, X0)
    assert grad.abs().max() > 1e-3  # the fantasy points matter
    torch.testing.assert_close(grad, fd, rtol=MODE_TOL_RTOL, atol=1e-6)


def test_knowledge_gradient_gradient_in_the_candidates(generator):
    """qKnowledgeGradient's gradient with respect to all its inputs, ``X_actual`` included
    (rating fantasies, whose answers move with ``X_actual``), equals central differences."""
    model = make_model("cpu", generator)
    nf = 3
    acqf = qKnowledgeGradient(model, num_fantasies=nf, sampler=SobolQMCNormalSampler(torch.Size([nf]), seed=3))
    X0 = torch.rand(2, 2 + nf, 2, generator=generator, dtype=torch.float64)
    X = X0.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(acqf(X).sum(), X)
    with torch.no_grad():
        fd = _central_difference(lambda Z: acqf(Z).sum(), X0)
    assert grad[:, :2].abs().max() > 1e-3  # X_actual has a gradient
    torch.testing.assert_close(grad, fd, rtol=MODE_TOL_RTOL, atol=1e-6)


def test_posterior_gradient_in_the_training_items(generator):
    """With training items that require gradients, the posterior is differentiable in them
    through the Laplace mode; without autograd, nothing is traced."""
    g = generator
    X0 = torch.rand(8, 2, generator=g, dtype=torch.float64)
    C = random_comparisons(8, 6, g)
    Xt = torch.rand(4, 2, generator=g, dtype=torch.float64)

    def value(X):
        post = PreferenceGP(
            X,
            C,
            ratings=torch.tensor([0.3, 0.8]),
            rating_index=[0, 7],
            covar_module=kernel("cpu"),
            comparison_noise=0.5,
        ).posterior(Xt)
        return post.mean.sum() + post.variance.sum()

    X = X0.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(value(X), X)
    with torch.no_grad():
        fd = _central_difference(value, X0)
        assert not value(X).requires_grad
    assert grad.abs().max() > 1e-3
    torch.testing.assert_close(grad, fd, rtol=MODE_TOL_RTOL, atol=1e-6)
