r"""Does ``torch.compile`` pay for a fused Newton step at small ``n``? Compile time, warm-up and per-call time.

The step is one Newton iteration's arithmetic for comparisons-only data, written as one function
of tensors: the predictors ``eta = (D L) a``, the probit's ``log Phi`` and ``phi / Phi`` (the
package's own :func:`~torchpref.inference.numerics.log_ndtr` and ``inv_mills``), the gradient
``(D L)^T l' - a``, ``B = I + (D L)^T diag(w) (D L)``, its Cholesky factor and the direction
``B^-1 grad`` (about twenty operations: the minimum an iteration needs, not our solver's).
It runs eager and through ``torch.compile(dynamic=True)`` (inductor, C++ code generated and
compiled with the system's compiler), for ``n = 20, 50, 100, 200`` and ``p = 2 n``, under
``torch.inference_mode`` (as the solver runs). Reported: the first call's wall and CPU time (this
process's, and the compiler processes' it waited for), the first call at each new size (dynamic
shapes: no recompilation expected), the per-call medians eager and compiled, and the largest
difference of the outputs (the compiled step must agree with the eager one to round-off). The
compilation uses a fresh inductor cache directory.

Writes ``results/speed_compile.json``.

Usage::

    .venv/bin/python benchmarks/speed/speed_compile.py [--repeats 7]
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import torch

from torchpref.experiments.results import write_json
from torchpref.inference.numerics import inv_mills, log_ndtr

RESULTS = Path(__file__).resolve().parents[1] / "results"
SIZES = [20, 50, 100, 200]


def step(R: torch.Tensor, a: torch.Tensor, s: float):
    """One Newton step for a probit term with rows ``R = D L`` (``B x p x n``) at ``a`` (``B x n``)."""
    eta = (R @ a.unsqueeze(-1)).squeeze(-1)
    z = eta / s
    log_cdf = log_ndtr(z)
    r = inv_mills(z, log_cdf)
    grad = (R.mT @ (r / s).unsqueeze(-1)).squeeze(-1) - a
    psi = log_cdf.sum(-1) - 0.5 * (a * a).sum(-1)
    H = R.mT @ ((r * (z + r) / (s * s)).unsqueeze(-1) * R)  # (D L)^T diag(w) (D L)
    H.diagonal(dim1=-2, dim2=-1).add_(1.0)
    M, info = torch.linalg.cholesky_ex(H)
    direction = torch.cholesky_solve(grad.unsqueeze(-1), M).squeeze(-1)
    return psi, grad, direction, (grad * direction).sum(-1), info


def _cpu() -> tuple[float, float]:
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime, kids.ru_utime + kids.ru_stime


def _per_call(fn, args, repeats: int, inner: int) -> float:
    ts = []
    for _ in range(repeats):
        t0 = time.process_time()
        for _ in range(inner):
            fn(*args)
        ts.append((time.process_time() - t0) / inner)
    return statistics.median(ts)


def _problem(n: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    R = torch.randn(1, 2 * n, n, generator=g, dtype=torch.float64) / n**0.5
    return R, torch.randn(1, n, generator=g, dtype=torch.float64)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    warnings.simplefilter("ignore")
    load_start = os.getloadavg()
    # a fresh inductor cache: the first call pays the whole compilation, as in a new environment
    # (later processes on the same machine reuse the cache and pay less)
    os.environ["TORCHINDUCTOR_CACHE_DIR"] = tempfile.mkdtemp(prefix="torchpref_inductor_")
    s = 2.0**0.5
    compiled = torch.compile(step, dynamic=True)
    R, a = _problem(SIZES[0])
    (c_own, c_kids), t0 = _cpu(), time.perf_counter()
    with torch.inference_mode():
        compiled(R, a, s)
    own, kids = _cpu()
    first = {"wall_s": time.perf_counter() - t0, "cpu_s": own - c_own, "compiler_processes_cpu_s": kids - c_kids}
    print(f"first call (compilation): {first}", flush=True)
    rows = []
    for n in SIZES:
        R, a = _problem(n)
        with torch.inference_mode():
            t0 = time.perf_counter()
            compiled(R, a, s)
            first_at_size = time.perf_counter() - t0
            inner = max(20, 4000 // n)
            eager_t = _per_call(step, (R, a, s), args.repeats, inner)
            compiled_t = _per_call(compiled, (R, a, s), args.repeats, inner)
            ref, out = step(R, a, s), compiled(R, a, s)
            diff = max(float((x - y).abs().max()) for x, y in zip(ref[:4], out[:4], strict=True))
        rows.append(
            {
                "n": n,
                "p": 2 * n,
                "eager_s": eager_t,
                "compiled_s": compiled_t,
                "speedup": eager_t / compiled_t,
                "first_call_at_size_s": first_at_size,
                "max_abs_difference": diff,
            }
        )
        print(
            f"n={n}: eager {eager_t * 1e6:.0f} us, compiled {compiled_t * 1e6:.0f} us "
            f"({eager_t / compiled_t:.2f}x), first call at this size {first_at_size:.2f} s, max diff {diff:.1e}",
            flush=True,
        )
    meta = {
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "clock": "process_time (CPU) per call; wall and CPU for the first call",
        "repeats": args.repeats,
        "load_average_at_start": load_start,
        "load_average_at_end": os.getloadavg(),
        "cpus": os.cpu_count(),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "speed_compile.json", {"meta": meta, "compilation": first, "rows": rows}, measured="user")
    print(f"wrote {args.out / 'speed_compile.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
