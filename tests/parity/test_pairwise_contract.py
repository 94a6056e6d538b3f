"""PairwiseGP's constructor contract on PreferenceGP, and the MLL built as GPyTorch's are.

What Ax, BoFire and AEPsych do with BoTorch's ``PairwiseGP`` (``datapoints=``, ``likelihood=``,
``jitter=``, a positional ``input_transform``, an empty ``load_state_dict``, a prior-only model
with an input transform, ``mll_class(likelihood=..., model=...)``) works on ``PreferenceGP``, each
checked against ``PairwiseGP`` or against the model built the usual way (docs/ax.md).
"""

from __future__ import annotations

import inspect

import pytest
import torch
from botorch.fit import fit_gpytorch_mll
from botorch.models.likelihoods.pairwise import PairwiseLogitLikelihood
from botorch.models.likelihoods.pairwise import PairwiseProbitLikelihood as BoTorchProbit
from botorch.models.pairwise_gp import PairwiseGP
from botorch.models.transforms.input import Normalize

import torchpref
from torchpref import LaplaceMarginalLogLikelihood, PreferenceGP, UnsupportedLikelihoodError


@pytest.fixture
def data():
    g = torch.Generator().manual_seed(3)
    X = torch.rand(6, 2, generator=g, dtype=torch.float64)
    u = X.sum(-1)
    pairs = torch.tensor([[0, 1], [2, 3], [4, 5], [1, 2], [3, 4]])
    better = u[pairs[:, 0]] > u[pairs[:, 1]]
    C = torch.where(better.unsqueeze(-1), pairs, pairs.flip(-1))
    return X, C


def _moments(model, X):
    with torch.no_grad():
        post = model.posterior(X)
        return post.mean, post.variance


def test_datapoints_is_train_x(data):
    X, C = data
    a = PreferenceGP(datapoints=X, comparisons=C)
    b = PreferenceGP(X, C)
    assert torch.equal(a.train_X, X) and torch.equal(a.comparisons, C)
    for x, y in zip(_moments(a, X), _moments(b, X), strict=True):
        torch.testing.assert_close(x, y, rtol=0, atol=0)
    with pytest.raises(ValueError, match="datapoints"):
        PreferenceGP(X, C, datapoints=X)


def test_argspec_as_ax_reads_it(data):
    """Ax checks ``inspect.getfullargspec(cls).args`` for the arguments it passes."""
    args = inspect.getfullargspec(PreferenceGP).args
    for name in ("train_X", "comparisons", "covar_module", "input_transform"):
        assert name in args
    X, C = data
    tf = Normalize(2)
    model = PreferenceGP(X, C, None, None, None, tf)  # input_transform in its position
    assert model.input_transform is tf


def test_pairwise_likelihoods(data):
    X, C = data
    botorch_probit = PreferenceGP(X, C, likelihood=BoTorchProbit())
    assert float(botorch_probit.likelihood.comparison.comparison_noise) == 1.0
    ours = PreferenceGP(X, C, likelihood=torchpref.PairwiseProbitLikelihood(comparison_noise=0.5))
    assert float(ours.likelihood.comparison.comparison_noise) == pytest.approx(0.5)
    reference = PreferenceGP(X, C, comparison_noise=0.5)
    for x, y in zip(_moments(ours, X), _moments(reference, X), strict=True):
        torch.testing.assert_close(x, y)
    with pytest.raises(UnsupportedLikelihoodError, match="PairwiseLogitLikelihood"):
        PreferenceGP(X, C, likelihood=PairwiseLogitLikelihood())
    with pytest.raises(ValueError, match="comparison_noise"):
        PreferenceGP(X, C, likelihood=BoTorchProbit(), comparison_noise=0.3)
    assert issubclass(UnsupportedLikelihoodError, ValueError)


def test_probit_likelihood_matches_pairwise_gp_mode(data):
    """With BoTorch's probit likelihood and PairwiseGP's kernel, the MAP utilities are PairwiseGP's."""
    X, C = data
    ref = PairwiseGP(X, C, likelihood=BoTorchProbit())
    model = PreferenceGP(datapoints=X, comparisons=C, likelihood=BoTorchProbit(), covar_module=ref.covar_module)
    torch.testing.assert_close(model.utility, ref.utility, rtol=1e-5, atol=1e-6)


def test_jitter_tolerated(data):
    X, C = data
    a = PreferenceGP(X, C, jitter=1e-4)
    for x, y in zip(_moments(a, X), _moments(PreferenceGP(X, C), X), strict=True):
        torch.testing.assert_close(x, y, rtol=0, atol=0)
    with pytest.raises(ValueError, match="jitter"):
        PreferenceGP(X, C, jitter=-1.0)


def test_load_state_dict_non_strict(data):
    X, C = data
    model = PreferenceGP(X, C)
    before = _moments(model, X)
    result = model.load_state_dict({})  # Ax's BOPE cross-validation does this
    assert "covar_module.raw_outputscale" in result.missing_keys and not result.unexpected_keys
    for x, y in zip(before, _moments(model, X), strict=True):
        torch.testing.assert_close(x, y, rtol=0, atol=0)
    result = model.load_state_dict({"no.such.key": torch.zeros(1)})
    assert result.unexpected_keys == ["no.such.key"]
    with pytest.raises(RuntimeError, match="Missing key"):
        model.load_state_dict({}, strict=True)
    # a fitted model's hyperparameters do arrive, and the posterior follows them
    other = PreferenceGP(X, C)
    other.covar_module.outputscale = 3.0
    model.load_state_dict(other.state_dict())
    assert float(model.covar_module.outputscale.detach()) == pytest.approx(3.0)
    for x, y in zip(_moments(other, X), _moments(model, X), strict=True):  # a warm-started mode: Newton's tolerance
        torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-5)


def test_prior_only_with_input_transform(data):
    X, C = data
    bounds = torch.tensor([[0.0, 0.0], [2.0, 2.0]], dtype=torch.float64)
    prior = PreferenceGP(None, None, input_transform=Normalize(2, bounds=bounds))
    plain = PreferenceGP(None, None)
    mean, var = _moments(prior, X)
    assert torch.equal(mean, torch.zeros_like(mean))
    torch.testing.assert_close(var, _moments(plain, X)[1])  # a stationary prior: the same variance
    cond = prior.condition_on_observations(X, C)
    direct = PreferenceGP(X, C, input_transform=Normalize(2, bounds=bounds))
    for x, y in zip(_moments(cond, X), _moments(direct, X), strict=True):
        torch.testing.assert_close(x, y)
    learned = PreferenceGP(None, None, input_transform=Normalize(2)).condition_on_observations(2 * X, C)
    torch.testing.assert_close(learned.input_transform.mins, (2 * X).min(0, keepdim=True).values)


def test_mll_built_as_gpytorch_mlls(data):
    X, C = data
    model = PreferenceGP(X, C)
    one = LaplaceMarginalLogLikelihood(model)
    two = LaplaceMarginalLogLikelihood(model.likelihood, model)
    kw = LaplaceMarginalLogLikelihood(likelihood=model.likelihood, model=model)
    torch.testing.assert_close(one(), two(), rtol=0, atol=0)
    torch.testing.assert_close(one(), kw(), rtol=0, atol=0)
    assert kw.model is model and kw.likelihood is model.likelihood
    with pytest.raises(ValueError, match="model.likelihood"):
        LaplaceMarginalLogLikelihood(PreferenceGP(X, C).likelihood, model)
    with pytest.raises(ValueError, match="PreferenceGP"):
        LaplaceMarginalLogLikelihood(model.likelihood, None)
    fit_gpytorch_mll(kw)
    assert float(kw()) > float(LaplaceMarginalLogLikelihood(PreferenceGP(X, C))())
