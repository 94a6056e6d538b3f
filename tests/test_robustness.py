"""Hundreds of small random problems, extreme hyperparameters included: the mode converges and
nothing is NaN (mode, posterior mean / variance, evidence and its gradient)."""

import sys
import warnings
from pathlib import Path

import pytest
import torch
from gpytorch.kernels import RBFKernel, ScaleKernel

from torchpref.models import PreferenceGP

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import fuzz_problems as fp  # noqa: E402

F64 = torch.float64


def random_config(seed):
    """The hostile problem of ``seed`` from the fuzz (``benchmarks/fuzz_problems.py``), at most 15
    items, with hostile likelihood parameters for every kind."""
    p = fp.make_problem(seed, max_n=15, pairwise_likelihood=False)
    cfg = dict(seed=seed, n=p.n, d=p.X.shape[-1], kind=p.kind, lengthscale=p.lengthscale,
               outputscale=p.outputscale, **p.likelihood)
    return cfg, p.X, p.comparisons, p.ratings, p.rating_index


def check(seed):
    cfg, X, C, u, ri = random_config(seed)
    k = ScaleKernel(RBFKernel(ard_num_dims=cfg["d"])).to(F64)
    k.base_kernel.lengthscale = cfg["lengthscale"]
    k.outputscale = cfg["outputscale"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # jitter / boundary warnings are expected here
        model = PreferenceGP(X, C if len(C) else None, u if len(u) else None, ri if len(u) else None,
                             covar_module=k, comparison_noise=cfg["comparison_noise"],
                             rating_scale=cfg["rating_scale"], rating_precision=cfg["rating_precision"],
                             learn_likelihood=True)
        mode = model.mode
        problems = []
        if not mode.converged:
            problems.append(f"not converged after {mode.iterations} iterations")
        if not torch.isfinite(mode.f).all():
            problems.append("non-finite mode")
        Xs = torch.rand(4, cfg["d"], generator=torch.Generator().manual_seed(seed + 1), dtype=F64)
        post = model.posterior(torch.cat([Xs, X[:2]]))
        if not (torch.isfinite(post.mean).all() and torch.isfinite(post.variance).all()):
            problems.append("non-finite posterior")
        if (post.variance < -1e-9 * cfg["outputscale"]).any():
            problems.append(f"negative variance {float(post.variance.min()):.3g}")
        ev = model.log_marginal_likelihood()
        params = [p for p in model.parameters() if p.requires_grad]
        grads = torch.autograd.grad(ev, params, allow_unused=True)
        if not torch.isfinite(ev):
            problems.append("non-finite evidence")
        if not all(g is None or torch.isfinite(g).all() for g in grads):
            problems.append("non-finite evidence gradient")
    return cfg, problems


CHUNKS = 6
PER_CHUNK = 50


@pytest.mark.parametrize("chunk", range(CHUNKS))
def test_random_problems(chunk):
    failures = []
    for seed in range(chunk * PER_CHUNK, (chunk + 1) * PER_CHUNK):
        try:
            cfg, problems = check(seed)
        except Exception as e:  # noqa: BLE001 - report every failing configuration at once
            cfg, problems = random_config(seed)[0], [f"{type(e).__name__}: {e}"]
        if problems:
            failures.append(f"{cfg}: {'; '.join(problems)}")
    assert not failures, f"{len(failures)} of {PER_CHUNK} configurations failed:\n" + "\n".join(failures)
