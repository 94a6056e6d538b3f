r"""Hostile-start fits: ``fit_gpytorch_mll`` from hyperparameters at the edges of what the optimiser
can reach, on the fuzz's hostile problems (``fuzz_problems.make_problem``).

A start (:func:`hostile_model`, from a seed): the problem of that seed (at most ``max_n`` items),
a model with every likelihood parameter learned, and log-uniform starting values: lengthscales
``1e-4 .. 1e4`` (per dimension), outputscale ``1e-5 .. 1e5``, ``sigma_R`` and ``sigma_B``
``1e-4 .. 1e3``, ``nu`` anywhere in its constraint ``1e-2 .. 1e6``. :func:`fit_outcome` fits it
and says how it ended: ``"fit"`` (a usable model: finite hyperparameters, a converged mode, a
finite posterior), a named error (``ModelFittingError`` after BoTorch's retries, or a
:class:`~torchpref.inference.numerics.NotPSDError`), or anything else (a defect).

``python benchmarks/hostile_fits.py [--fits 100] [--max-n 15]`` runs many and writes
``benchmarks/results/hostile_fits.json`` (a progress bar on stderr); ``tests/test_hostile_fits.py``
runs a few in the default test run.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

import fuzz_problems as fp

F64 = torch.float64
#: Errors a hostile start may end in: documented and named (docs/robustness.md).
NAMED = ("ModelFittingError", "NotPSDError", "LaplaceNumericalError")


def _log_uniform(lo: float, hi: float, g: torch.Generator, shape=()) -> torch.Tensor:
    u = torch.rand(shape, generator=g, dtype=F64)
    return torch.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * u)


def hostile_model(seed: int, max_n: int = 15):
    """The hostile problem of ``seed`` and a model started from hostile hyperparameters."""
    from gpytorch.kernels import RBFKernel, ScaleKernel

    from torchpref import PreferenceGP

    p = fp.make_problem(seed, max_n=max_n, pairwise_likelihood=False)
    g = torch.Generator().manual_seed(10_000 + seed)
    d = p.X.shape[-1]
    kernel = ScaleKernel(RBFKernel(ard_num_dims=d)).to(F64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = PreferenceGP(
            p.X,
            p.comparisons if len(p.comparisons) else None,
            p.ratings if len(p.ratings) else None,
            p.rating_index if len(p.ratings) else None,
            covar_module=kernel,
            learn_likelihood=True,
        )
        kernel.base_kernel.lengthscale = _log_uniform(1e-4, 1e4, g, (1, d))
        kernel.outputscale = _log_uniform(1e-5, 1e5, g)
        model.comparison_likelihood.comparison_noise = _log_uniform(1e-4, 1e3, g)
        model.rating_likelihood.rating_scale = _log_uniform(1e-4, 1e3, g)
        model.rating_likelihood.rating_precision = _log_uniform(1.01e-2, 0.99e6, g)
    return p, model


def usable(model) -> str | None:
    """Why ``model`` is not usable after a fit (``None``: it is)."""
    if not all(bool(torch.isfinite(v).all()) for v in model.parameters()):
        return "non-finite hyperparameters"
    if not bool(torch.as_tensor(model.mode.converged).all()):
        return "mode not converged"
    Xq = torch.rand(4, model.train_X.shape[-1], generator=torch.Generator().manual_seed(1), dtype=F64)
    with torch.no_grad():
        post = model.posterior(Xq)
        if not (bool(torch.isfinite(post.mean).all()) and bool(torch.isfinite(post.variance).all())):
            return "non-finite posterior"
        if bool((post.variance < 0).any()):
            return "negative posterior variance"
    return None


def fit_outcome(seed: int, max_n: int = 15) -> dict:
    """Fit the hostile start of ``seed``; its outcome (``"fit"``, ``"unusable: ..."``, or the name
    of the exception raised), the exception's text and the time taken."""
    from botorch.fit import fit_gpytorch_mll

    from torchpref import LaplaceMarginalLogLikelihood

    p, model = hostile_model(seed, max_n)
    t0 = time.perf_counter()
    out = {"seed": seed, "n": p.n, "kind": p.kind}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fit_gpytorch_mll(LaplaceMarginalLogLikelihood(model))
            why = usable(model)
        out["outcome"] = "fit" if why is None else f"unusable: {why}"
    except Exception as err:  # recorded: the point of the benchmark
        out["outcome"] = type(err).__name__
        out["error"] = str(err).splitlines()[0][:200] if str(err) else ""
    out["seconds"] = round(time.perf_counter() - t0, 3)
    return out


def main(argv=None) -> None:
    from tqdm import tqdm

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fits", type=int, default=100)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--max-n", type=int, default=15)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results" / "hostile_fits.json")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    seeds = range(args.first_seed, args.first_seed + args.fits)
    rows = [fit_outcome(s, args.max_n) for s in tqdm(seeds, desc="hostile fits")]
    counts: dict[str, int] = {}
    for r in rows:
        counts[r["outcome"]] = counts.get(r["outcome"], 0) + 1
    other = [r for r in rows if r["outcome"] != "fit" and r["outcome"] not in NAMED]
    summary = {"fits": len(rows), "counts": counts, "other": len(other), "rows": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}))


if __name__ == "__main__":
    main()
