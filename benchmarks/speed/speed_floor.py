r"""The floor of a Laplace mode and of a fit: the arithmetic they need, timed alone, beside what we spend.

For comparisons-only data (``n`` items, ``p = 2 n`` comparisons, the data and kernel of
``bench_common.py``) at n = 20, 50, 100, 200:

1. *What the solver does*: the factorisations of ``B = I + L^T W L`` and the likelihood
   evaluations of a cold-start mode, and of a whole ``fit_gpytorch_mll`` (its L-BFGS
   evaluations, each a warm-started re-solve plus the evidence and its gradient), counted by
   wrapping :class:`torchpref.inference.newton.Problem`'s methods (counting only).
2. *The arithmetic that needs*, each piece timed alone in a tight loop on ready inputs, once with
   torch (the ops our code calls) and once with LAPACK / BLAS through SciPy on NumPy arrays:

   * the prior: the RBF kernel matrix (``exp`` of scaled squared distances) and its Cholesky factor;
   * a factorisation: ``B = I + (D L)^T diag(w) (D L)`` (the rows ``D L`` formed once per
     solve), its Cholesky factor and the Newton direction ``B^-1 grad`` (``syrk`` + ``potrf`` +
     ``potrs`` in LAPACK);
   * an evaluation: ``eta = (D L) a``, the probit's ``log Phi`` and ``phi / Phi``, and
     ``grad = (D L)^T l'`` (two ``gemv`` and the elementwise part);
   * per L-BFGS evaluation of a fit, beyond its re-solve: the kernel matrix and its Cholesky
     factor, ``V = M^-1 L^T`` (``trsm``) and ``(W V^T)(W V^T)^T`` (``syrk``), the ``n^3`` parts
     of the evidence's gradient.

   ``floor = prior + factorisations x factorisation + evaluations x evaluation`` (plus, for a fit,
   ``L-BFGS evaluations x (prior + evidence)``): no Python around it, no line-search logic, no
   model, no BoTorch.
3. *What we spend*: construction + mode (the kernel module built too, as in
   ``speed_pairwise.py``), the solve alone (``find_mode`` on a ready ``L``), and the fit, under
   the run's setting of the compiled path (``TORCHPREF_FAST_PATH``, ``auto`` by default: loaded
   before the timings) and, as ``*_torch``, with it off. The work in 1. is counted on the torch
   solver.

The ratio ``ours / floor`` is the number to track. Medians of interleaved repeats, CPU time, one
thread; the load average is recorded. Writes ``results/speed_floor.{csv,json}``.

Usage::

    .venv/bin/python benchmarks/speed/speed_floor.py [--repeats 7] [--sizes 20 50 100 200]
"""

from __future__ import annotations

import argparse
import collections
import csv
import os
import statistics
import sys
import time
import warnings
from pathlib import Path

# one thread for SciPy's BLAS too (set before NumPy loads it): a threaded BLAS on a loaded machine
# spins, and the floor is of one thread's arithmetic
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import bench_common as bc  # noqa: E402

from torchpref.experiments.results import write_json  # noqa: E402
from torchpref.inference import newton  # noqa: E402
from torchpref.inference.fast_path import fast_path, setting, warm_up  # noqa: E402
from torchpref.inference.laplace import find_mode  # noqa: E402

RESULTS = HERE.parent / "results"
SIZES = [20, 50, 100, 200]
clock = time.process_time


def _median_time(fn, repeats: int, inner: int) -> float:
    """Median over ``repeats`` of the CPU time of one call, each repeat ``inner`` calls."""
    fn()
    ts = []
    for _ in range(repeats):
        t0 = clock()
        for _ in range(inner):
            fn()
        ts.append((clock() - t0) / inner)
    return statistics.median(ts)


class Counts:
    """Calls of :class:`~torchpref.inference.newton.Problem`'s factorisations and evaluations."""

    def __init__(self):
        self.calls = collections.Counter()
        self._orig = {}

    def __enter__(self):
        for name in ("factorise", "factorise_float32", "evaluate"):
            orig = getattr(newton.Problem, name)
            self._orig[name] = orig

            def wrapped(prob, *a, _orig=orig, _name=name, **kw):
                self.calls[_name] += 1
                return _orig(prob, *a, **kw)

            setattr(newton.Problem, name, wrapped)
        return self

    def __exit__(self, *exc):
        for name, orig in self._orig.items():
            setattr(newton.Problem, name, orig)


def count_work(X, C) -> dict[str, int]:
    """Factorisations and evaluations of a cold mode and of a fit (and the fit's L-BFGS evaluations),
    counted on the torch solver (the compiled path takes the same steps below 128 items, unseen)."""
    with fast_path("off"):
        return _count_work(X, C)


def _count_work(X, C) -> dict[str, int]:
    with Counts() as cm:
        model = bc.mode_torchpref(X, C)
    mode = dict(cm.calls)
    evals = [0]
    orig = bc.PreferenceGP.log_marginal_likelihood

    def counted(self):
        evals[0] += 1
        return orig(self)

    bc.PreferenceGP.log_marginal_likelihood = counted
    try:
        with Counts() as cf:
            bc.fit_torchpref(model)
    finally:
        bc.PreferenceGP.log_marginal_likelihood = orig
    fit = dict(cf.calls)
    return {
        "mode_factorisations": mode.get("factorise", 0) + mode.get("factorise_float32", 0),
        "mode_evaluations": mode.get("evaluate", 0),
        "fit_lbfgs_evaluations": evals[0],
        "fit_factorisations": fit.get("factorise", 0) + fit.get("factorise_float32", 0),
        "fit_evaluations": fit.get("evaluate", 0),
    }


def _inputs(X, C, model):
    """The arrays the pieces act on, at the initial hyperparameters: ``K``, ``L``, the rows ``D L``,
    ``w``, a gradient and a mode."""
    state = model._state()
    mode = state.mode  # batched: one problem
    L = state.pred.L[0]
    R = L[C[:, 0]] - L[C[:, 1]]  # D L: p x n
    return L, R, mode.weights[0][0], mode.a[0], mode.M[0]


def _jitter(model) -> float:
    """The diagonal jitter the model's kernel matrix needed, at least ``1e-10`` of its diagonal
    (a factorisation with no jitter can fail where items nearly coincide, as at n = 200)."""
    return max(float(model._state().jitter), 1e-10 * bc.INIT_OUTPUTSCALE)


def torch_pieces(X, C, model, repeats: int, inner: int) -> dict[str, float]:
    """Each piece timed with torch ops, one call each where one op does it."""
    L, R, w, a, M = _inputs(X, C, model)
    jitter = _jitter(model)
    n = L.shape[-1]
    ls = torch.full((X.shape[-1],), bc.INIT_LENGTHSCALE, dtype=X.dtype)
    eye = torch.eye(n, dtype=X.dtype)
    g = torch.randn(n, dtype=X.dtype, generator=torch.Generator().manual_seed(0))
    K = L @ L.mT
    WVt = R.mT @ (w.unsqueeze(-1) * R)

    def prior():
        Z = X / ls
        K = torch.cdist(Z, Z).square_().mul_(-0.5).exp_().mul_(bc.INIT_OUTPUTSCALE)
        K.diagonal().add_(jitter)  # near-coincident items: the jitter the model needed (0 if none)
        torch.linalg.cholesky(K)

    def factorisation():
        B = torch.addmm(eye, R.mT, w.unsqueeze(-1) * R)
        Mb = torch.linalg.cholesky(B)
        torch.cholesky_solve(g.unsqueeze(-1), Mb)

    def evaluation():
        eta = torch.mv(R, a) / 1.4142135623730951
        lc = torch.special.log_ndtr(eta)
        r = torch.exp(-0.5 * eta * eta - 0.9189385332046727 - lc)
        lc.sum()
        torch.mv(R.mT, r)

    def evidence():
        V = torch.linalg.solve_triangular(M, L.mT, upper=False)
        V.mT @ V
        WVt @ WVt.mT
        torch.mv(K, a)

    return {name: _median_time(fn, repeats, inner) for name, fn in _named(prior, factorisation, evaluation, evidence)}


def lapack_pieces(X, C, model, repeats: int, inner: int) -> dict[str, float]:
    """Each piece with SciPy's LAPACK / BLAS wrappers on NumPy arrays (``syrk``, ``potrf``, ``potrs``,
    ``trsm``, ``gemv``) and SciPy's ``log_ndtr``."""
    from scipy.linalg import blas, lapack
    from scipy.special import log_ndtr

    L, R, w, a, M = _inputs(X, C, model)
    jitter = _jitter(model)
    L, R, w, a, M = L.numpy(), R.numpy(), w.numpy(), a.numpy(), np.asfortranarray(M.numpy())
    Xn = X.numpy() / bc.INIT_LENGTHSCALE
    n = L.shape[-1]
    g = np.random.default_rng(0).standard_normal(n)
    Rs = np.asfortranarray(np.sqrt(w)[:, None] * R)  # probit weights are positive: W = (sqrt w D L)^T (...)
    Lf = np.asfortranarray(L)
    K = np.asfortranarray(L @ L.T)
    WVt = np.asfortranarray(R.T @ (w[:, None] * R))

    def prior():
        sq = (Xn * Xn).sum(-1)
        D2 = sq[:, None] + sq[None, :] - 2.0 * (Xn @ Xn.T)
        Kp = np.exp(-0.5 * D2) * bc.INIT_OUTPUTSCALE
        Kp[np.diag_indices(n)] += jitter
        lapack.dpotrf(Kp, lower=1, overwrite_a=1)

    def factorisation():
        B = blas.dsyrk(1.0, Rs, beta=1.0, c=np.eye(n, order="F"), trans=1, lower=1, overwrite_c=1)
        Mb, _ = lapack.dpotrf(B, lower=1, overwrite_a=1, clean=0)
        lapack.dpotrs(Mb, g, lower=1)

    def evaluation():
        eta = blas.dgemv(1.0 / 1.4142135623730951, R, a)
        lc = log_ndtr(eta)
        r = np.exp(-0.5 * eta * eta - 0.9189385332046727 - lc)
        lc.sum()
        blas.dgemv(1.0, R, r, trans=1)

    def evidence():
        V = blas.dtrsm(1.0, M, Lf.T.copy(order="F"), lower=1)
        blas.dsyrk(1.0, V, trans=1)
        blas.dsyrk(1.0, WVt)
        blas.dgemv(1.0, K, a)

    return {name: _median_time(fn, repeats, inner) for name, fn in _named(prior, factorisation, evaluation, evidence)}


def _named(*fns):
    return [(fn.__name__, fn) for fn in fns]


def floors(pieces: dict[str, float], work: dict[str, int]) -> dict[str, float]:
    mode = (
        pieces["prior"]
        + work["mode_factorisations"] * pieces["factorisation"]
        + work["mode_evaluations"] * pieces["evaluation"]
    )
    fit = (
        work["fit_lbfgs_evaluations"] * (pieces["prior"] + pieces["evidence"])
        + work["fit_factorisations"] * pieces["factorisation"]
        + work["fit_evaluations"] * pieces["evaluation"]
    )
    return {"mode": mode, "fit": fit}


def _off(fn):
    def run(*args):
        with fast_path("off"):
            return fn(*args)

    return run


def ours(X, C, repeats: int) -> dict[str, float]:
    """Construction + mode, the solve alone, and the fit: medians of ``repeats``, interleaved; under
    the run's setting of the compiled path and (``*_torch``) with it off."""
    model = bc.mode_torchpref(X, C)
    state = model._state()
    L, obs = state.pred.L, state.obs
    fns = {
        "mode": (lambda _: bc.mode_torchpref(X, C), None),
        "solve": (lambda _: find_mode(L, obs), None),
        "fit": (bc.fit_torchpref, lambda: bc.mode_torchpref(X, C)),
    }
    fns.update({f"{k}_torch": (_off(fn), setup) for k, (fn, setup) in list(fns.items())})
    times = {k: [] for k in fns}
    for r in range(repeats + 1):
        for k, (fn, setup) in fns.items():
            inner = 1 if k.startswith("fit") else 5
            for _ in range(inner):
                arg = setup() if setup else None
                t0 = clock()
                fn(arg)
                if r:  # the first round is the warm-up
                    times[k].append(clock() - t0)
    return {k: statistics.median(v) for k, v in times.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--sizes", type=int, nargs="+", default=SIZES)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    warnings.simplefilter("ignore", RuntimeWarning)
    try:
        from tqdm.auto import tqdm
    except ImportError:  # pragma: no cover

        def tqdm(x, **_):
            return x

    warm_up()  # the compiled path loaded before any timing (built first under TORCHPREF_FAST_PATH=on)
    load_start = os.getloadavg()
    rows = []
    for n in tqdm(args.sizes, desc="sizes"):
        X, C = bc.make_comparisons(n, 2 * n)
        work = count_work(X, C)
        model = bc.mode_torchpref(X, C)
        inner = max(5, 4000 // n)
        pt = torch_pieces(X, C, model, args.repeats, inner)
        pl = lapack_pieces(X, C, model, args.repeats, inner)
        spent = ours(X, C, args.repeats)
        ft, fl = floors(pt, work), floors(pl, work)
        row = {"n": n, "p": 2 * n, **work}
        row.update({f"torch_{k}_s": v for k, v in pt.items()})
        row.update({f"lapack_{k}_s": v for k, v in pl.items()})
        row.update({f"ours_{k}_s": v for k, v in spent.items()})
        for task in ("mode", "fit"):
            row[f"floor_torch_{task}_s"], row[f"floor_lapack_{task}_s"] = ft[task], fl[task]
            row[f"{task}_over_torch_floor"] = spent[task] / ft[task]
            row[f"{task}_over_lapack_floor"] = spent[task] / fl[task]
            row[f"{task}_torch_path_over_torch_floor"] = spent[f"{task}_torch"] / ft[task]
        row["solve_over_torch_floor"] = spent["solve"] / (ft["mode"] - pt["prior"])
        rows.append(row)
        print(
            f"n={n}: mode {spent['mode'] * 1e3:.2f} ms (solve {spent['solve'] * 1e3:.2f}) vs floor "
            f"{ft['mode'] * 1e3:.3f} torch / {fl['mode'] * 1e3:.3f} LAPACK ms ({row['mode_over_torch_floor']:.1f}x, "
            f"{row['mode_over_lapack_floor']:.1f}x); fit {spent['fit'] * 1e3:.1f} ms vs {ft['fit'] * 1e3:.2f} / "
            f"{fl['fit'] * 1e3:.2f} ms ({row['fit_over_torch_floor']:.1f}x, {row['fit_over_lapack_floor']:.1f}x)",
            flush=True,
        )
    args.out.mkdir(parents=True, exist_ok=True)
    meta = {
        "torch": torch.__version__,
        "numpy": np.__version__,
        "threads": torch.get_num_threads(),
        "clock": "process_time (CPU)",
        "repeats": args.repeats,
        "statistic": "median",
        "load_average_at_start": load_start,
        "load_average_at_end": os.getloadavg(),
        "cpus": os.cpu_count(),
        "fast_path": setting(),
    }
    write_json(args.out / "speed_floor.json", {"meta": meta, "rows": rows}, measured="user")  # stamped
    with open(args.out / "speed_floor.csv", "w", newline="") as fh:
        wr = csv.DictWriter(fh, fieldnames=list(rows[0]))
        wr.writeheader()
        for row in rows:
            wr.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    print(f"wrote {args.out / 'speed_floor.csv'}, .json (load {load_start} -> {os.getloadavg()})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
