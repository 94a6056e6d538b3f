"""The posterior cache knows what it depends on: swapping or editing any module, setting or dtype
gives the posterior of a model built afresh with the same modules (issue #26, item 1)."""

import copy
import warnings

import pytest
import torch
from botorch.models.transforms.input import Normalize
from gpytorch.kernels import MaternKernel, RBFKernel, ScaleKernel

from torchpref.models.preference_gp import PreferenceGP

F64 = torch.float64


def _data(n=8):
    g = torch.Generator().manual_seed(3)
    X = torch.rand(n, 2, generator=g, dtype=F64)
    C = torch.tensor([[0, 1], [2, 3], [4, 5], [1, 6], [6, 2]])
    return X, C, torch.tensor([0.2, 0.9], dtype=F64), torch.tensor([6, 7]), torch.rand(5, 2, generator=g, dtype=F64)


def _fresh_like(model, **kw):
    """A model built afresh from ``model``'s data, modules (copied) and settings."""
    X, C, u, ri, _ = _data()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        levels = model.rating_levels
        fresh = PreferenceGP(
            X,
            C,
            torch.tensor([2.0, 4.0], dtype=F64) if levels else u,
            ri,
            covar_module=copy.deepcopy(model.covar_module),
            input_transform=copy.deepcopy(getattr(model, "input_transform", None)),
            ties_offered=model.ties_offered,
            rating_levels=levels,
            **kw,
        )
    fresh.likelihood = copy.deepcopy(model.likelihood)
    return fresh


def _kernel_class_swap(model):
    model.covar_module = ScaleKernel(RBFKernel(ard_num_dims=2)).to(F64)
    model.posterior(_data()[-1])
    k = ScaleKernel(MaternKernel(nu=2.5, ard_num_dims=2)).to(F64)
    k.load_state_dict(model.covar_module.state_dict())  # equal raw values, another class
    model.covar_module = k


def _nu(model):
    model.covar_module = ScaleKernel(MaternKernel(nu=2.5)).to(F64)
    model.posterior(_data()[-1])
    model.covar_module.base_kernel.nu = 0.5


def _ties_offered(model):
    model.ties_offered = True


def _active_dims(model):
    model.covar_module = ScaleKernel(RBFKernel(active_dims=[0])).to(F64)
    model.posterior(_data()[-1])
    model.covar_module.base_kernel.active_dims = torch.tensor([1])


def _input_transform(model):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.input_transform = Normalize(2, bounds=torch.tensor([[0.0, 0.0], [2.0, 2.0]], dtype=F64))


def _input_transform_bounds(model):
    _input_transform(model)
    model.posterior(_data()[-1])
    model.input_transform._coefficient.mul_(torch.tensor([0.75, 1.5], dtype=F64))  # other bounds


def _constraint_transform(model):
    # the kernel's own constraint (the likelihoods' default constraints are shared by all models)
    model.covar_module.base_kernel.raw_lengthscale_constraint._transform = torch.nn.Softplus(beta=3.0)


def _kernel_dtype(model):
    model.covar_module.to(torch.float32)  # round-off only: the key sees the dtype itself


EDITS = [
    _kernel_class_swap,
    _nu,
    _ties_offered,
    _active_dims,
    _input_transform,
    _input_transform_bounds,
    _constraint_transform,
    _kernel_dtype,
]


@pytest.mark.parametrize("edit", EDITS, ids=lambda f: f.__name__.strip("_"))
def test_an_edited_model_predicts_as_a_fresh_one(edit):
    X, C, u, ri, Xt = _data()
    model = PreferenceGP(X, C, u, ri)
    model.posterior(Xt)  # the cache is filled
    state = model._state()
    edit(model)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        got = model.posterior(Xt)
        want = _fresh_like(model).posterior(Xt)
    assert model._state() is not state
    torch.testing.assert_close(got.mean, want.mean, atol=1e-6, rtol=0)
    torch.testing.assert_close(got.variance, want.variance, atol=1e-6, rtol=0)


def test_cut_points_and_a_likelihood_swap_are_seen():
    X, C, _, ri, Xt = _data()
    model = PreferenceGP(X, C, torch.tensor([2.0, 4.0], dtype=F64), ri, rating_levels=5)
    before = model.posterior(Xt).mean
    model.rating_likelihood.cut_points = torch.tensor([-1.5, -0.2, 0.1, 2.0], dtype=F64)
    after = model.posterior(Xt).mean
    torch.testing.assert_close(after, _fresh_like(model).posterior(Xt).mean, atol=1e-6, rtol=0)
    assert (after - before).abs().max() > 1e-3
    # a likelihood module of another class (strict comparisons) in place of the forced-choice one
    model.likelihood.comparison = copy.deepcopy(model.likelihood.strict)
    torch.testing.assert_close(model.posterior(Xt).mean, _fresh_like(model).posterior(Xt).mean, atol=1e-6, rtol=0)


def test_train_eval_transitions_reset_the_cache_as_gpytorch_does():
    X, C, u, ri, Xt = _data()
    model = PreferenceGP(X, C, u, ri)
    state = model._state()
    assert model._state() is state  # unchanged: reused
    model.train()
    in_train = model._state()
    assert in_train is not state
    model.eval()
    in_eval = model._state()
    assert in_eval is not in_train
    model.eval()  # no transition: kept
    model.posterior(Xt)
    assert model._state() is in_eval
    torch.testing.assert_close(in_eval.mode.f, state.mode.f, atol=1e-9, rtol=0)  # same data, same mode


def test_unchanged_models_reuse_their_cache():
    X, C, u, ri, Xt = _data()
    model = PreferenceGP(X, C, u, ri, covar_module=ScaleKernel(MaternKernel(nu=1.5)).to(F64))
    model.posterior(Xt)
    state = model._state()
    for _ in range(3):
        model.posterior(Xt)
        model.preference_probability(Xt[:1], Xt[1:2])
    assert model._state() is state
