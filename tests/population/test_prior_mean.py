"""``PreferenceGP(mean_module=...)``: a prior mean entering the Laplace solve as an offset."""

import pathlib

import pytest
import torch
from gpytorch.means import ConstantMean, LinearMean, ZeroMean

import torchpref
from torchpref.models.checkpoint import CheckpointError
from torchpref.testing import assert_evidence_gradient


def _problem(n=8, d=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, d, generator=g, dtype=torch.float64)
    C = torch.tensor([[0, 1], [2, 3], [4, 5], [6, 7], [1, 2], [3, 4]])
    ratings = torch.tensor([0.8, 0.3, 0.6], dtype=torch.float64)
    return X, C, ratings, torch.tensor([0, 5, 7])


def _pair(X, mean=None, ratings=True, **kw):
    Xd, C, r, ri = _problem()
    args = dict(ratings=r, rating_index=ri) if ratings else {}
    return torchpref.PreferenceGP(X, C, **args, mean_module=mean, **kw)


def test_zero_mean_is_todays_model_bit_for_bit():
    X, *_ = _problem()
    plain, zero = _pair(X), _pair(X, ZeroMean())
    Xt = torch.rand(5, 2, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    p0, p1 = plain.posterior(Xt), zero.posterior(Xt)
    assert torch.equal(p0.mean, p1.mean)
    assert torch.equal(p0.variance, p1.variance)
    assert torch.equal(plain.log_marginal_likelihood(), zero.log_marginal_likelihood())


def test_constant_mean_shifts_a_comparison_model():
    """Comparisons see differences: a constant mean c shifts the posterior mean by c and changes
    nothing else (covariance, evidence, preference probabilities)."""
    X, *_ = _problem()
    c = 0.7
    mean = ConstantMean().double()
    mean.constant.data.fill_(c)
    plain, shifted = _pair(X, ratings=False), _pair(X, mean, ratings=False)
    Xt = torch.rand(6, 2, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    p0, p1 = plain.posterior(Xt), shifted.posterior(Xt)
    torch.testing.assert_close(p1.mean, p0.mean + c, rtol=0, atol=1e-9)
    torch.testing.assert_close(p1.variance, p0.variance, rtol=0, atol=1e-9)
    with torch.no_grad():
        torch.testing.assert_close(
            shifted.preference_probability(Xt[:3], Xt[3:]), plain.preference_probability(Xt[:3], Xt[3:])
        )
    torch.testing.assert_close(shifted.log_marginal_likelihood(), plain.log_marginal_likelihood())
    torch.testing.assert_close(shifted.utility, plain.utility + c, rtol=0, atol=1e-9)


def test_mode_is_the_brute_force_map_of_the_deviation():
    """With ratings the mean matters: the model's mode of ``g`` maximises
    ``log p(Y | m + g) - g^T K^-1 g / 2``, found here by an independent optimiser (L-BFGS)."""
    X, C, r, ri = _problem()
    mean = LinearMean(2).double()
    with torch.no_grad():
        mean.weights.copy_(torch.tensor([[0.9], [-0.4]]))
        mean.bias.fill_(0.2)
    model = _pair(X, mean)
    K = model.covar_module(X).to_dense().detach() + 1e-10 * torch.eye(8, dtype=torch.float64)
    m = mean(X).detach()
    lik = model.likelihood
    g = torch.zeros(8, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS(
        [g], max_iter=500, tolerance_grad=1e-12, tolerance_change=1e-14, line_search_fn="strong_wolfe"
    )

    def closure():
        opt.zero_grad()
        f = m + g
        lp = lik.comparison.derivatives(f[C[:, 0]] - f[C[:, 1]])[0].sum()
        lp = lp + lik.rating.derivatives(f[ri], r)[0].sum()
        loss = -(lp - 0.5 * g @ torch.linalg.solve(K, g))
        loss.backward()
        return loss

    opt.step(closure)
    torch.testing.assert_close(model.mode.f, g.detach(), rtol=0, atol=1e-5)
    torch.testing.assert_close(model.utility, (m + g).detach(), rtol=0, atol=1e-5)


def test_evidence_gradient_in_the_mean_parameters():
    X, *_ = _problem()
    mean = LinearMean(2).double()
    with torch.no_grad():
        mean.weights.copy_(torch.tensor([[0.5], [0.3]]))
    model = _pair(X, mean)
    params = dict(mean.named_parameters())
    params["lengthscale"] = model.covar_module.base_kernel.raw_lengthscale
    assert_evidence_gradient(model, params, h=1e-5, rtol=1e-4)


def test_fit_learns_a_constant_from_high_ratings():
    g = torch.Generator().manual_seed(1)
    X = torch.rand(10, 2, generator=g, dtype=torch.float64)
    r = torch.full((10,), 0.9, dtype=torch.float64)
    model = torchpref.PreferenceGP(X, ratings=r, rating_index=torch.arange(10), mean_module=ConstantMean().double())
    from botorch.fit import fit_gpytorch_mll

    fit_gpytorch_mll(torchpref.LaplaceMarginalLogLikelihood(model))
    assert float(model.mean_module.constant.detach()) > 0.5
    with torch.no_grad():
        assert float(model.expected_rating(X).min()) > 0.75


def test_add_observations_keeps_the_mean():
    X, C, r, ri = _problem()
    mean = ConstantMean().double()
    mean.constant.data.fill_(0.4)
    model = _pair(X, mean)
    x_new = torch.tensor([[0.5, 0.5]], dtype=torch.float64)
    model.add_observations(x_new, ratings=[0.7], rating_index=[0])
    fresh = torchpref.PreferenceGP(
        model.train_X, model.comparisons, model.ratings, model.rating_index, mean_module=mean
    )
    torch.testing.assert_close(model.posterior(X).mean, fresh.posterior(X).mean, rtol=0, atol=1e-5)


def test_bad_mean_module_is_named():
    X, *_ = _problem()
    with pytest.raises(ValueError, match="mean_module must be a gpytorch Mean"):
        _pair(X, mean=lambda x: x.sum(-1))


def test_checkpoint_with_a_mean(tmp_path: pathlib.Path):
    X, *_ = _problem()
    mean = ConstantMean().double()
    mean.constant.data.fill_(0.3)
    model = _pair(X, mean)
    torchpref.save_model(model, tmp_path / "m.pt")
    with pytest.raises(CheckpointError, match="mean_module.raw_constant"):
        torchpref.load_model(tmp_path / "m.pt")
    back = torchpref.load_model(tmp_path / "m.pt", mean_module=ConstantMean().double())
    assert float(back.mean_module.constant.detach()) == pytest.approx(0.3)
    torch.testing.assert_close(back.posterior(X).mean, model.posterior(X).mean, rtol=0, atol=1e-6)
