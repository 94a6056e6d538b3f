"""Model, acquisition and batch paths on every available device (``conftest.DEVICES``: CPU
always, CUDA where present), each against the same computation on the CPU. Tensors follow the
device of ``train_X``; nothing may come back on another device."""

import pytest
import torch
from botorch.acquisition import qLogExpectedImprovement, qUpperConfidenceBound
from botorch.fit import fit_gpytorch_mll
from botorch.sampling.normal import SobolQMCNormalSampler
from gpytorch.kernels import RBFKernel, ScaleKernel

from torchpref import BatchedPreferenceGP, PreferenceGP
from torchpref.acquisition.functions import QueryInformation, QueryUCB, latent_ucb
from torchpref.models.preference_gp import LaplaceMarginalLogLikelihood
from torchpref.selection.strategies import UCBC, InformationPerEffort
from torchpref.selection.top_profile import ProfileVariancePerEffort
from torchpref.testing import random_comparisons


def build(device, seed=0, n=9):
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, 2, generator=g, dtype=torch.float64)
    C = random_comparisons(n, 8, g)
    k = ScaleKernel(RBFKernel(ard_num_dims=2))
    model = PreferenceGP(
        X.to(device),
        C.to(device),
        ratings=torch.tensor([0.2, 0.7, 0.9]).to(device),
        rating_index=torch.tensor([0, 3, 5]).to(device),
        covar_module=k,
    )
    return model


def close(a: torch.Tensor, b: torch.Tensor, atol=1e-7):
    torch.testing.assert_close(a.detach().cpu(), b.detach().cpu(), rtol=1e-6, atol=atol)


def test_model_fit_and_posterior_on_device(device):
    model, ref = build(device), build("cpu")
    assert model.mode.f.device.type == device.type
    for m in (model, ref):
        fit_gpytorch_mll(LaplaceMarginalLogLikelihood(m))
    close(model.covar_module.outputscale, ref.covar_module.outputscale, atol=1e-5)
    Xq = torch.rand(4, 3, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    post, post_ref = model.posterior(Xq.to(device)), ref.posterior(Xq)
    assert post.mean.device.type == device.type
    close(post.mean, post_ref.mean, atol=1e-5)
    close(model.log_marginal_likelihood(), ref.log_marginal_likelihood(), atol=1e-6)


def test_acquisition_on_device(device):
    model, ref = build(device), build("cpu")
    X = torch.rand(5, 2, 2, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    for make in (
        lambda m: latent_ucb(m),
        lambda m: QueryUCB(m),
        lambda m: qUpperConfidenceBound(m, beta=4.0, sampler=SobolQMCNormalSampler(torch.Size([64]), seed=0)),
        lambda m: qLogExpectedImprovement(m, best_f=0.3, sampler=SobolQMCNormalSampler(torch.Size([64]), seed=0)),
    ):
        Xi = X[:, :1] if make(ref).__class__.__name__ == "UpperConfidenceBound" else X
        value = make(model)(Xi.to(device))
        assert value.device.type == device.type
        close(value, make(ref)(Xi))
    info = QueryInformation(model, num_samples=256, generator=torch.Generator().manual_seed(3))(X[:, :1].to(device))
    info_ref = QueryInformation(ref, num_samples=256, generator=torch.Generator().manual_seed(3))(X[:, :1])
    close(info, info_ref, atol=1e-6)


@pytest.mark.parametrize(
    "selector", [UCBC(m=3), InformationPerEffort(m=3, num_samples=32), ProfileVariancePerEffort(m=3, num_samples=32)]
)
def test_batch_and_selector_on_device(device, selector):
    models = [build(device, seed) for seed in range(3)]
    refs = [build("cpu", seed) for seed in range(3)]
    batch, batch_ref = BatchedPreferenceGP.from_models(models), BatchedPreferenceGP.from_models(refs)
    new = torch.tensor([[0.5, 0.5], [0.2, 0.9]], dtype=torch.float64)
    batch.add_observations(1, new.to(device), comparisons=[[0, 1]])
    batch_ref.add_observations(1, new, comparisons=[[0, 1]])
    X = torch.rand(3, 7, 2, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    mean, var = batch.marginals(X.to(device))
    assert mean.device.type == device.type
    close(mean, batch_ref.marginals(X)[0])
    gens = [torch.Generator().manual_seed(5 + t) for t in range(3)]
    gens_ref = [torch.Generator().manual_seed(5 + t) for t in range(3)]
    queries = selector.select_batch(batch, X.to(device), [None] * 3, 0, 5, gens)
    queries_ref = selector.select_batch(batch_ref, X, [None] * 3, 0, 5, gens_ref)
    for q, r in zip(queries, queries_ref):
        assert type(q) is type(r)
        close(q.items, r.items, atol=0)
