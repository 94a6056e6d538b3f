r"""Why mixed data fits short lengthscales at scale: the data or the model?

``speed_pairwise.py``'s mixed model (``bench_common.make_mixed``: ``n`` items, ``n`` comparisons,
``n / 2`` Beta ratings) fits lengthscales near 0.01 where comparisons alone fit 0.2-0.3. The
data are drawn from ``bench_common.utility`` with comparisons answered under ``N(0, 1)`` noise on
each item (``sigma_R = 1``) and ratings from ``Beta(nu mu, nu (1 - mu))``, ``mu = Phi(u / sqrt 2)``,
``nu = 80`` (the model's defaults ``sigma_B = 1``, ``nu = 80``); the mixed benchmark's model
assumed ``comparison_noise = 0.1``. Arms, each fitted with ``fit_gpytorch_mll`` from the same
initial hyperparameters:

* mixed data, ``sigma_R = 0.1`` (the benchmark's model) and ``sigma_R = 1`` (the data's);
* the same comparisons alone, under both;
* the same ratings alone (``sigma_R`` does not enter).

If the ratings were noisier than ``nu`` says, the ratings-alone arm would fit short lengthscales
too; if the comparison noise is the cause, only the ``sigma_R = 0.1`` arms do. Reported per arm:
lengthscales, outputscale, evidence (with priors), L-BFGS evaluations and CPU time of the fit.
Writes ``results/mixed_lengthscale.json``.

Usage::

    .venv/bin/python benchmarks/speed/mixed_lengthscale.py [--n 1000]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

import torch

from torchpref.experiments.results import write_json

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import bench_common as bc  # noqa: E402

RESULTS = HERE.parent / "results"


def fit_arm(X, C, u, ri, comparison_noise: float) -> dict:
    model = bc.PreferenceGP(
        X,
        comparisons=C,
        ratings=u,
        rating_index=ri,
        covar_module=bc.make_kernel(),
        comparison_noise=comparison_noise,
    )
    _ = model.mode
    evals = [0]
    orig = model.log_marginal_likelihood

    def counted():
        evals[0] += 1
        return orig()

    model.log_marginal_likelihood = counted
    t0 = time.process_time()
    bc.fit_torchpref(model)
    cpu = time.process_time() - t0
    del model.log_marginal_likelihood
    return {
        **bc.hyperparameters(model),
        "evidence_with_priors": bc.evidence_torchpref(model),
        "lbfgs_evaluations": evals[0],
        "fit_cpu_s": cpu,
        "comparisons": int(C.shape[0]),
        "ratings": int(u.shape[0]),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=1000)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    warnings.simplefilter("ignore", RuntimeWarning)
    X, C, u, ri = bc.make_mixed(args.n)
    none_c = torch.zeros(0, 2, dtype=torch.long)
    none_u, none_i = torch.zeros(0, dtype=X.dtype), torch.zeros(0, dtype=torch.long)
    arms = {
        "mixed, sigma_R = 0.1": (C, u, ri, 0.1),
        "mixed, sigma_R = 1": (C, u, ri, 1.0),
        "comparisons only, sigma_R = 0.1": (C, none_u, none_i, 0.1),
        "comparisons only, sigma_R = 1": (C, none_u, none_i, 1.0),
        "ratings only": (none_c, u, ri, 1.0),
    }
    load_start = os.getloadavg()
    out = {}
    for name, (c, uu, ii, s) in arms.items():
        out[name] = fit_arm(X, c, uu, ii, s)
        print(f"{name}: {out[name]}", flush=True)
    result = {
        "n": args.n,
        "data": "bench_common.make_mixed: comparisons under N(0, 1) item noise (sigma_R = 1), Beta ratings with nu = 80",
        "load_average_at_start": load_start,
        "load_average_at_end": os.getloadavg(),
        "arms": out,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    write_json((args.out / "mixed_lengthscale.json"), result, measured="user")
    print(f"wrote {args.out / 'mixed_lengthscale.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
