"""Hundreds of small random problems, extreme hyperparameters included: the mode converges and
nothing is NaN (mode, posterior mean / variance, evidence and its gradient)."""

import math
import warnings

import pytest
import torch
from gpytorch.kernels import RBFKernel, ScaleKernel

from torchpref.models import PreferenceGP

F64 = torch.float64


def random_config(seed):
    g = torch.Generator().manual_seed(seed)

    def logu(lo, hi):
        return math.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * float(torch.rand((), generator=g, dtype=F64)))

    n = int(torch.randint(2, 16, (), generator=g))
    d = int(torch.randint(1, 4, (), generator=g))
    kind = ["mixed", "comparisons", "ratings"][int(torch.randint(0, 3, (), generator=g))]
    cfg = dict(seed=seed, n=n, d=d, kind=kind, lengthscale=logu(1e-3, 1e3), outputscale=logu(1e-2, 1e2),
               comparison_noise=logu(1e-3, 10.0), rating_scale=logu(0.1, 3.0), rating_precision=logu(1.0, 1e3))
    X = torch.rand(n, d, generator=g, dtype=F64)
    if torch.rand((), generator=g) < 0.3:  # duplicated items (same coordinates, separate indices)
        X[n // 2:] = X[: n - n // 2].clone()
    p = int(torch.randint(1, 3 * n, (), generator=g)) if kind != "ratings" else 0
    q = int(torch.randint(1, 2 * n, (), generator=g)) if kind != "comparisons" else 0
    i = torch.randint(0, n, (p,), generator=g)
    j = (i + torch.randint(1, max(n, 2), (p,), generator=g)) % n
    C = torch.stack([i, j], -1)
    if p and torch.rand((), generator=g) < 0.4:  # contradictory comparisons: both orders
        C = torch.cat([C, C.flip(-1)])
    ri = torch.randint(0, n, (q,), generator=g)
    mode_u = int(torch.randint(0, 3, (), generator=g))
    if mode_u == 0:  # near 0 and 1
        u = torch.where(torch.rand(q, generator=g) < 0.5, torch.full((q,), 1e-6, dtype=F64),
                        torch.full((q,), 1 - 1e-6, dtype=F64))
    elif mode_u == 1:
        u = torch.rand(q, generator=g, dtype=F64).clamp(1e-4, 1 - 1e-4)
    else:  # the same item rated inconsistently
        u = torch.linspace(0.05, 0.95, q, dtype=F64)
        ri = torch.zeros(q, dtype=torch.long)
    return cfg, X, C, u, ri


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
