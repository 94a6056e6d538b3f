r"""Hostile-start fits: ``fit_gpytorch_mll`` from hyperparameters at the edges of what the optimiser
can reach, on the fuzz's hostile problems (``torchpref.testing.problems.make_problem``).

A start (:func:`torchpref.testing.problems.hostile_model`, from a seed): the problem of that seed (at most ``max_n`` items),
a model with every likelihood parameter learned, and log-uniform starting values: lengthscales
``1e-4 .. 1e4`` (per dimension), outputscale ``1e-5 .. 1e5``, ``sigma_R`` and ``sigma_B``
``1e-4 .. 1e3``, ``nu`` anywhere in its constraint ``1e-2 .. 1e6``. :func:`~torchpref.testing.problems.fit_outcome` fits it
and says how it ended: ``"fit"`` (a usable model: finite hyperparameters, a converged mode, a
finite posterior), a named error (``ModelFittingError`` after BoTorch's retries, or a
:class:`~torchpref.inference.numerics.NotPSDError`), or anything else (a defect).

``python benchmarks/robustness/hostile_fits.py [--fits 100] [--max-n 15]`` runs many and writes
``benchmarks/results/hostile_fits.json`` (a progress bar on stderr); ``tests/inference/test_hostile_fits.py``
runs a few in the default test run.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from torchpref.experiments.results import write_json
from torchpref.testing.problems import NAMED, fit_outcome


def main(argv=None) -> None:
    from tqdm import tqdm

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fits", type=int, default=100)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--max-n", type=int, default=15)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "results" / "hostile_fits.json")
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
    write_json(args.out, summary, measured="user")
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}))


if __name__ == "__main__":
    main()
