r"""The compiled fit's line search across problems: how often a fit leaves the compiled path.

Issue 52: with ``torch.set_default_dtype(torch.float64)`` (BoTorch's tutorials) the compiled fit of
``bench_common.make_comparisons(200, 400)`` ended with ``LINE_SEARCH_FAILED`` after 7 iterations and
BoTorch's routine refitted from scratch (8x the time). The loss near its minimum is noisy at about
the Laplace mode's tolerance; the line search (:func:`torchpref.inference._compiled_fit.wolfe_search`)
now brackets and zooms with safeguarded cubic steps, and the fit stops as converged where the
decrease a direction predicts is below L-BFGS-B's ``ftol``.

This sweeps ``n`` items (default 20-400), ``seeds`` data sets each, three comparison densities
(``p = n, 2n, 4n`` comparisons of ``bench_common.make_comparisons``) and both default dtypes
(``torch.set_default_dtype`` float32 and float64 before the data and the model are built), fitting
each with ``fit_gpytorch_mll`` under ``fast_path("on")`` and reading the model's ``last_fit``
(:class:`~torchpref.models.fast_fit.FitReport`): a *fallback* is a fit BoTorch's routine answered
(``solver == "torch"``), the target is 0. Writes
``benchmarks/results/line_search/speed_line_search.json`` (stamped): every fit's solver, status,
iterations, loss evaluations and CPU time, and the counts.

Usage::

    .venv/bin/python benchmarks/speed/speed_line_search.py [--sizes 20 50 100 200 300 400] [--seeds 12]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from collections import Counter
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import bench_common as bc  # noqa: E402

from torchpref.experiments.results import write_json  # noqa: E402
from torchpref.inference import fast_path  # noqa: E402

RESULTS = HERE.parent / "results" / "line_search"
DENSITIES = (1, 2, 4)  # comparisons per item
DTYPES = {"float32": torch.float32, "float64": torch.float64}


def fit_one(n: int, density: int, seed: int, dtype: torch.dtype) -> dict:
    """One fit of ``n`` items and ``density * n`` comparisons under default dtype ``dtype``."""
    before = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        X, C = bc.make_comparisons(n, density * n, seed=seed)
        model = bc.mode_torchpref(X, C)
        start = time.process_time()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            bc.fit_torchpref(model)
        cpu = time.process_time() - start
    finally:
        torch.set_default_dtype(before)
    report = model.last_fit
    return {
        "n": n,
        "p": density * n,
        "seed": seed,
        "default_dtype": str(dtype).removeprefix("torch."),
        "solver": report.solver,
        "status": report.status,
        "iterations": report.iterations,
        "evaluations": report.evaluations,
        "cpu_s": cpu,
        "evidence": bc.evidence_torchpref(model),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[20, 50, 100, 200, 300, 400])
    ap.add_argument("--seeds", type=int, default=12)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    load_start = os.getloadavg()
    with fast_path.fast_path("on"):
        if fast_path.warm_up() is None:
            print("the compiled path is not available here: run `torchpref fast-path build`", file=sys.stderr)
            return 1
        fits = []
        for name, dtype in DTYPES.items():
            for n in args.sizes:
                for density in DENSITIES:
                    for seed in range(args.seeds):
                        fits.append(fit_one(n, density, seed, dtype))
                    row = [f for f in fits if f["n"] == n and f["p"] == density * n and f["default_dtype"] == name]
                    fell = sum(f["solver"] != "compiled" for f in row)
                    print(f"{name} n={n} p={density * n}: {fell} fallbacks of {len(row)}", flush=True)
    fallbacks = [f for f in fits if f["solver"] != "compiled"]
    summary = {
        "fits": len(fits),
        "fallbacks": len(fallbacks),
        "statuses": dict(Counter(f["status"] for f in fits)),
        "max_evaluations": max(f["evaluations"] or 0 for f in fits),
        "load_avg_start": list(load_start),
        "load_avg_end": list(os.getloadavg()),
        "sizes": args.sizes,
        "seeds": args.seeds,
        "densities": list(DENSITIES),
    }
    path = write_json(args.out / "speed_line_search.json", {"summary": summary, "fits": fits})
    print(f"{len(fallbacks)} fallbacks in {len(fits)} fits; statuses {summary['statuses']}; wrote {path}")
    return 0 if not fallbacks else 1


if __name__ == "__main__":
    sys.exit(main())
