r"""Where a large fit's time goes: one L-BFGS evaluation of a mixed model, part by part.

``n`` items, ``n`` comparisons and ``n / 2`` ratings (``bench_common.make_mixed``; the data's own
``comparison_noise = 1``), mode solved at the initial hyperparameters. Then, for a small change of
the lengthscales (as one L-BFGS step makes), the parts of one evaluation of the fit's loss, each
timed (CPU, one thread) and the factorisations of the re-solve counted:

* ``kernel``: the kernel matrix with autograd (``model._prior``);
* ``resolve``: the warm-started re-solve of the mode (``PosteriorState.solve``: Cholesky of ``K``,
  the predicted start, Newton);
* ``evidence``: the Laplace evidence and the surrogate carrying its gradient (``laplace_evidence``);
* ``backward``: the backward pass to the raw hyperparameters.

The ``n^3`` operations inside (each Cholesky factor, ``B``'s products, the evidence gradient's
triangular solve and product) dominate from ``n`` of a few hundred on; times at a larger ``n``
follow from these by ``(n' / n)^3`` (the script prints that extrapolation for ``--to``, labelled
as such). Writes ``results/speed_large_fit.json``.

Usage::

    .venv/bin/python benchmarks/speed/speed_large_fit.py [--n 2000] [--to 5000]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import bench_common as bc  # noqa: E402

from torchpref.experiments.results import write_json  # noqa: E402
from torchpref.inference import newton  # noqa: E402
from torchpref.inference.laplace import laplace_evidence  # noqa: E402
from torchpref.inference.solver import PosteriorState, SolveKey  # noqa: E402
from torchpref.models.posterior_state import cache_key  # noqa: E402

RESULTS = HERE.parent / "results"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=2000)
    ap.add_argument("--to", type=int, default=5000)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    warnings.simplefilter("ignore", RuntimeWarning)
    load_start = os.getloadavg()
    X, C, u, ri = bc.make_mixed(args.n)
    model = bc.PreferenceGP(X, comparisons=C, ratings=u, rating_index=ri, covar_module=bc.make_kernel())
    t0 = time.process_time()
    _ = model.mode
    cold = time.process_time() - t0
    model.train()
    raw = model.covar_module.base_kernel.raw_lengthscale
    with torch.no_grad():
        raw.mul_(1.02)  # one L-BFGS-sized change of the hyperparameters
    calls = {"factorise": 0, "factorise_float32": 0}
    originals = {name: getattr(newton.Problem, name) for name in calls}

    def counting(name):
        def wrapped(prob, *a, **kw):
            calls[name] += 1
            return originals[name](prob, *a, **kw)

        return wrapped

    for name in calls:
        setattr(newton.Problem, name, counting(name))
    try:
        parts = {}
        t0 = time.process_time()
        padded, K = model._prior()
        parts["kernel"] = time.process_time() - t0
        t0 = time.process_time()
        fp, structure = cache_key(model)
        key = SolveKey(model.data, fp, structure, model.likelihood)
        state = PosteriorState.solve(
            key, padded, K, model._observations, previous=model._cache, max_iter=model.max_newton_iter
        )
        parts["resolve"] = time.process_time() - t0
        model._cache = state
        t0 = time.process_time()
        N = padded.num_items
        value = laplace_evidence(K.reshape(-1, N, N), state.obs, state.mode, L=state.pred.L, jitter=state.jitter)
        parts["evidence"] = time.process_time() - t0
        t0 = time.process_time()
        (-value.sum()).backward()
        parts["backward"] = time.process_time() - t0
    finally:
        for name, orig in originals.items():
            setattr(newton.Problem, name, orig)
    total = sum(parts.values())
    scale = (args.to / args.n) ** 3
    result = {
        "n": args.n,
        "comparisons": args.n,
        "ratings": args.n // 2,
        "cold_mode_cpu_s": cold,
        "evaluation_parts_cpu_s": parts,
        "evaluation_cpu_s": total,
        "resolve_factorisations": calls,
        "extrapolated_to": args.to,
        "extrapolated_evaluation_cpu_s": total * scale,
        "extrapolation": f"(n' / n)^3 = {scale:.3g}: the n^3 parts dominate; an estimate, not a measurement",
        "load_average_at_start": load_start,
        "load_average_at_end": os.getloadavg(),
        "threads": torch.get_num_threads(),
    }
    print(json.dumps(result, indent=2))
    args.out.mkdir(parents=True, exist_ok=True)
    write_json((args.out / "speed_large_fit.json"), result, measured="user")
    return 0


if __name__ == "__main__":
    sys.exit(main())
