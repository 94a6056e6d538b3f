"""float32 as a first-class dtype and errors by name: each test here failed before its fix."""

import warnings

import pytest
import torch
from botorch.exceptions.warnings import InputDataWarning
from gpytorch.kernels import RBFKernel, ScaleKernel

from torchpref.inference import numerics
from torchpref.models.preference_gp import PreferenceGP
from torchpref.testing import rand, random_comparisons

F32, F64 = torch.float32, torch.float64


def kernel(d, lengthscale, outputscale=1.0, dtype=F64):
    k = ScaleKernel(RBFKernel(ard_num_dims=d)).to(dtype)
    k.base_kernel.lengthscale = lengthscale
    k.outputscale = outputscale
    return k


def comparisons_model(generator, n, d, lengthscale, outputscale=1.0, dtype=F64, **kwargs):
    X = rand(n, d, generator=generator)
    C = random_comparisons(n, 2 * n, generator)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputDataWarning)
        return PreferenceGP(X.to(dtype), C, covar_module=kernel(d, lengthscale, outputscale, dtype), **kwargs)


# ------------------------------------------------------------------ float32


def test_jitter_is_relative_to_the_diagonal_and_the_dtype():
    # a singular matrix of scale 1e12: an absolute jitter cap of 1e-6 is 1e-18 of its diagonal
    v = torch.arange(1.0, 4.0, dtype=F64)
    A = 1e12 * torch.outer(v, v) / 4
    L, j = numerics.cholesky_jittered(A)
    assert 0 < j <= 1e-6 * float(A.diagonal().mean())
    torch.testing.assert_close(L @ L.T, A + j * torch.eye(3, dtype=F64))
    # the schedule escalates tenfold, as psd_safe_cholesky does, from a dtype-dependent start
    assert numerics.jitter_schedule(F64) == [0.0, 1e-10, 1e-9, 1e-8, 1e-7, 1e-6]
    assert numerics.jitter_schedule(F32, scale=2.0) == [0.0, 2e-6, 2e-5, 2e-4, 2e-3]
    with pytest.raises(numerics.NotPSDError, match="float32, n = 3"):
        numerics.cholesky_jittered(-torch.eye(3, dtype=F32))


@pytest.mark.parametrize("laplace_dtype", [None, F32])  # mixed precision (the default) and native
def test_float32_issue_example_factorises(generator, laplace_dtype):
    # issue 11: X = torch.rand(200, 2) in float32, RBF lengthscale 0.2, outputscale 1 -> NotPSDError
    model = comparisons_model(generator, 200, 2, 0.2, dtype=F32, laplace_dtype=laplace_dtype)
    assert model.mode.converged
    assert torch.isfinite(model.posterior(model.train_X[:5]).mean).all()


def test_float32_newton_converges_at_its_own_tolerance(generator):  # native float32
    # the float64 tolerance 1e-11 is below float32's round-off: 100 iterations, then a warning
    assert numerics.default_tolerance(F64) == 1e-11 and 1e-7 < numerics.default_tolerance(F32) < 1e-5
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no convergence warning
        warnings.simplefilter("ignore", InputDataWarning)
        model = comparisons_model(generator, 300, 2, 0.3, outputscale=100.0, dtype=F32, laplace_dtype=F32)
        mode = model.mode
    assert mode.converged and mode.iterations <= 10


@pytest.mark.parametrize("laplace_dtype", [None, F32])
def test_kernel_is_exact_at_coincident_points_under_autograd(generator, laplace_dtype):
    # GPyTorch zeroes a point's distance to itself only without gradients: k(x, x) came back
    # off by ~3e-4 of the outputscale in float32 at lengthscale 0.01 with autograd on
    X = rand(60, 3, generator=generator).to(F32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputDataWarning)
        model = PreferenceGP(X, covar_module=kernel(3, 0.01, dtype=F32), laplace_dtype=laplace_dtype)  # the prior
    s = model.covar_module.outputscale.detach()
    Xq = torch.cat([X[:7], X[:3]]).unsqueeze(0).requires_grad_(True)  # training items, and repeats
    post = model.posterior(Xq)
    torch.testing.assert_close(post.variance.detach().reshape(-1), s.expand(10), rtol=0, atol=0)
    cov = post.distribution.covariance_matrix.detach()[0]
    torch.testing.assert_close(cov[7:, :3], s * torch.eye(3, dtype=F32), rtol=0, atol=1e-30)
    post.mean.sum().backward()  # still differentiable
    assert torch.isfinite(Xq.grad).all()


def test_float32_inputs_warn_as_in_botorch(generator):
    X = rand(5, 2, generator=generator)
    with pytest.warns(InputDataWarning, match="float32"):
        PreferenceGP(X.to(F32))
    with warnings.catch_warnings():
        warnings.simplefilter("error", InputDataWarning)
        PreferenceGP(X)
        # the filter BoTorch's own tests (and code written for PairwiseGP) use for this warning
        from botorch.exceptions.warnings import _get_single_precision_warning

        warnings.filterwarnings(
            "ignore", category=InputDataWarning, message=_get_single_precision_warning(str(torch.float32))
        )
        PreferenceGP(X.to(F32))


# ----------------------------------------------------------- errors by name


def test_max_newton_iter_zero_is_a_value_error(generator):
    X = rand(5, 2, generator=generator)
    with pytest.raises(ValueError, match="max_newton_iter.*got 0"):
        PreferenceGP(X, random_comparisons(5, 3, generator), max_newton_iter=0)
    model = PreferenceGP(X, random_comparisons(5, 3, generator))
    with pytest.raises(ValueError, match="max_newton_iter"):
        model.max_newton_iter = 0
    assert model.max_newton_iter == 100


def test_posterior_inputs_of_another_dtype_or_non_finite_are_named(generator):
    model = comparisons_model(generator, 8, 2, 0.3, dtype=F32)
    with pytest.raises(ValueError, match="X is torch.float64 but the model is torch.float32"):
        model.posterior(rand(3, 2, generator=generator))
    X = rand(3, 2, generator=generator)
    X[1, 0] = float("nan")
    model64 = comparisons_model(generator, 8, 2, 0.3)
    with pytest.raises(ValueError, match=r"X must be finite.*\[nan\]"):
        model64.posterior(X)
    with pytest.raises(ValueError, match="X must be finite"):
        model64.marginals(X)


def test_bool_comparisons_are_rejected(generator):
    X = rand(4, 2, generator=generator)
    C = torch.tensor([[True, False]])  # was read as [1, 0]
    with pytest.raises(ValueError, match="comparisons must hold integer indices, got a bool tensor"):
        PreferenceGP(X, C)
    model = PreferenceGP(X, torch.tensor([[0, 1]]))
    with pytest.raises(ValueError, match="rating_index must hold integer indices"):
        model.add_observations(ratings=torch.tensor([0.5]), rating_index=torch.tensor([True]))


def test_interrupt_inside_add_observations_leaves_the_model_unchanged(generator, monkeypatch):
    X = rand(6, 2, generator=generator)
    model = PreferenceGP(X, random_comparisons(6, 4, generator), covar_module=kernel(2, 0.4))
    data, before = model.data, model.posterior(X).mean.detach()
    lik = model.likelihood.comparison
    real = lik.derivatives

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(lik, "derivatives", interrupted)  # Ctrl-C while the new mode is solved
    with pytest.raises(KeyboardInterrupt):
        model.add_observations(rand(2, 2, generator=generator), comparisons=torch.tensor([[0, 1]]))
    monkeypatch.setattr(lik, "derivatives", real)
    assert model.data is data and model.train_X.shape[0] == 6
    torch.testing.assert_close(model.posterior(X).mean.detach(), before, rtol=0, atol=0)


# ------------------------------------------------------------- save and load


def test_saved_model_gives_the_same_posterior_in_a_fresh_process(generator, tmp_path):
    from botorch.models.transforms import Normalize

    import torchpref

    X = rand(9, 2, generator=generator, low=-3.0, high=5.0)
    C = random_comparisons(9, 6, generator)
    u, ri = rand(3, generator=generator, low=0.1, high=0.9), torch.tensor([0, 4, 4])
    bounds = torch.tensor([[-3.0, -3.0], [5.0, 5.0]], dtype=F64)
    model = PreferenceGP(
        X,
        C,
        u,
        ri,
        covar_module=kernel(2, [0.3, 0.6], 1.7),
        input_transform=Normalize(2, bounds=bounds),
        comparison_noise=0.3,
        rating_scale=0.7,
        learn_likelihood=True,
        max_newton_iter=40,
    )
    Xs = rand(5, 2, generator=generator, low=-3.0, high=5.0)
    ref = model.posterior(Xs)
    path = tmp_path / "model.pt"
    torchpref.save_model(model, path)
    torch.save({"mean": ref.mean.detach(), "var": ref.variance.detach(), "Xs": Xs}, tmp_path / "ref.pt")
    script = f"""
import torch, torchpref
from botorch.models.transforms import Normalize
from gpytorch.kernels import RBFKernel, ScaleKernel
ref = torch.load({str(tmp_path / 'ref.pt')!r}, weights_only=True)
ck = torch.load({str(path)!r}, weights_only=True)  # the safe default: tensors and plain values only
k = ScaleKernel(RBFKernel(ard_num_dims=2)).to(torch.float64)
model = torchpref.load_model(ck, covar_module=k, input_transform=Normalize(2, bounds=torch.tensor([[-3.0, -3.0], [5.0, 5.0]], dtype=torch.float64)))
assert model.max_newton_iter == 40 and model.likelihood.comparison.raw_comparison_noise.requires_grad
assert model.comparisons.shape == (6, 2) and model.ratings.shape == (3,)
p = model.posterior(ref["Xs"])
torch.testing.assert_close(p.mean.detach(), ref["mean"], rtol=0, atol=1e-6)
torch.testing.assert_close(p.variance.detach(), ref["var"], rtol=0, atol=1e-6)
print("same posterior")
"""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "same posterior" in out.stdout


def test_load_model_names_a_wrong_file_or_kernel(generator, tmp_path):
    import torchpref

    model = PreferenceGP(rand(4, 2, generator=generator), random_comparisons(4, 3, generator))
    path = tmp_path / "model.pt"
    torchpref.save_model(model, path)
    torch.save({"a": torch.zeros(1)}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="is not a torchpref.PreferenceGP checkpoint"):
        torchpref.load_model(tmp_path / "other.pt")
    from gpytorch.kernels import MaternKernel

    with pytest.raises(ValueError, match="missing .*raw_lengthscale"):
        torchpref.load_model(path, covar_module=MaternKernel(ard_num_dims=2).to(F64))
    loaded = torchpref.load_model(path)
    torch.testing.assert_close(loaded.train_X, model.train_X, rtol=0, atol=0)


# ------------------------------------------------------------------ raw units


RAW_LOW = torch.tensor([100.0, 0.5, 2.0], dtype=F64)  # price, weight, battery hours
RAW_HIGH = torch.tensor([2000.0, 3.5, 20.0], dtype=F64)


def raw_units_use(seed, input_transform):
    """Issue 12's use: 50 items with 3 features in raw units, 15 best-of-3 answers, the model's
    best item; returns its true rank and the warnings raised."""
    from botorch.fit import fit_gpytorch_mll

    import torchpref

    g = torch.Generator().manual_seed(seed)
    Z = torch.rand(50, 3, generator=g, dtype=F64)
    X = RAW_LOW + (RAW_HIGH - RAW_LOW) * Z
    u = -1.5 * Z[:, 0] - 0.8 * Z[:, 1] + Z[:, 2].sqrt()  # cheap, light, long battery life
    shown = [torch.randperm(50, generator=g)[:3] for _ in range(15)]
    C = torch.cat([torchpref.best_of_m(int(s[u[s].argmax()]), s) for s in shown])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = PreferenceGP(
            X, C, input_transform=input_transform, comparison_noise=0.1
        )  # the value it was written for
        fit_gpytorch_mll(torchpref.LaplaceMarginalLogLikelihood(model))
    best = int(model.posterior(X).mean.detach().reshape(-1).argmax())
    return int((u > u[best]).sum()) + 1, [w for w in caught if issubclass(w.category, InputDataWarning)]


def test_raw_units_warn_and_normalize_finds_the_best_item():
    from botorch.models.transforms import Normalize

    rank, caught = raw_units_use(0, None)
    assert len(caught) == 1  # once per model, naming the columns and the remedy
    assert "column 0: [1" in str(caught[0].message) and "Normalize(d=3" in str(caught[0].message)
    ranks = []
    for seed in range(6):
        rank, caught = raw_units_use(seed, Normalize(3, bounds=torch.stack([RAW_LOW, RAW_HIGH])))
        assert not caught
        ranks.append(rank)
    # in raw units the model's best was truly ranked 8, 5, 4, 5, 2, 3 on these seeds
    assert max(ranks) <= 2 and ranks.count(1) >= 4, ranks
