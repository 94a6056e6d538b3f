r"""Speed of ``torchpref.PreferenceGP`` against BoTorch's ``PairwiseGP`` and botorch-rust's, all in one run.

Same comparisons-only data (``n`` items, ``p = 2 n`` comparisons), same kernel, priors and
initial hyperparameters (see ``bench_common.py``; botorch-rust gets the same kernel built from its
own classes). Peers: BoTorch's ``PairwiseGP``, and botorch-rust's ``PairwiseGP`` (PyPI
``botorch-rust``, import ``botorch_rs``: BoTorch's API reimplemented in Rust) where it is
installed (skipped with a note where it is not). Each measurement is repeated, the libraries
alternating so that load from other processes falls on all alike, and the median is kept. Tasks:

* ``mode``: construction + Laplace mode (``PairwiseGP``'s constructors solve their MAP; ours:
  construct + ``model.mode``), the kernel module built inside the timing for each;
* ``fit``: each library's ``fit_gpytorch_mll`` with its Laplace MLL, from the same initial values;
* ``posterior``: ``posterior(X).mean`` and ``.variance`` on a ``1000 x 1 x d`` batch, model fitted
  and caches warm;
* ``eubo``: ``optimize_acqf`` of ``AnalyticExpectedUtilityOfBestOption`` (``q = 2``, 3 restarts,
  512 raw samples, seeded; botorch-rust's own EUBO and ``optimize_acqf`` for its model) on the fitted model;
* ``mixed_mode``: torchpref only, 2,000 items with comparisons and ratings, construct + mode.

The agreement of the libraries is reported per size (``fit_quality`` in the JSON): the largest
difference of the modes at the initial hyperparameters (the same MAP problem for all three), and
each fit's hyperparameters and evidence (each library's own evidence + log priors).

``--clock cpu`` ranks and compares by this process's CPU time instead of wall time: on a machine
loaded by other processes the wall time mostly measures the waiting; with one thread the two
agree on a quiet machine. Both clocks are recorded for every measurement (``{lib}_cpu_s`` and
``{lib}_wall_s``: a CPU time above the wall time means more than one thread worked), and the JSON
says which threads were limited: torch's (``--threads``), and the BLAS libraries' counts inside the
compiled path's calls (``meta.blas``: the libraries' own counts, and what the compiled calls set). From ``--slow-n`` items on, each task is timed once per library after
no warm-up (PairwiseGP's fit at n = 2,000 takes minutes).

Peak memory: a fresh subprocess per (task, library, size) loads everything, resets its peak RSS
(``/proc/self/clear_refs``), runs the task once and reads ``VmHWM`` (Linux only). Reported: that
peak and the RSS just before the task. ``tracemalloc`` does not see torch's allocations, and
``getrusage``'s max RSS is inherited from the parent across fork + exec, so neither is used.
The posterior's peak includes filling each model's prediction cache (first call).

``--paths both`` adds the column ``torchpref_torch``: torchpref with the compiled path off
(``torchpref.fast_path("off")``), beside ``torchpref`` under the setting of the run (``auto`` unless
``TORCHPREF_FAST_PATH`` says otherwise; ``--paths torch`` runs ``torchpref`` itself with it off).
``--quick``: n = 20, 50, 100, 200, 500, 3 repeats (5 for the mode), the mode, fit and EUBO only (no
posterior: botorch-rust's takes 51 s a call at n = 500; n = 500 timed once per library), no mixed
model, no memory probe: about 5 minutes.

Writes ``results/speed_pairwise.{csv,json,png}``.

Usage::

    .venv/bin/python benchmarks/speed/speed_pairwise.py [--repeats 3] [--sizes 20 50 100 200 500] [--no-memory]
        [--threads 1] [--clock cpu] [--no-botorch-rust]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import statistics
import subprocess
import sys
import time
import warnings
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import bench_common as bc  # noqa: E402

from torchpref.experiments.stamp import stamped  # noqa: E402
from torchpref.inference.fast_path import fast_path, set_fast_path, setting, warm_up  # noqa: E402

RESULTS = HERE.parent / "results"
SIZES = [20, 50, 100, 200, 500]
PEERS = ("pairwisegp", "botorch_rust", "torchpref_torch")
LIB_NAMES = {
    "torchpref": "torchpref PreferenceGP",
    "torchpref_torch": "torchpref, compiled path off",
    "pairwisegp": "BoTorch PairwiseGP",
    "botorch_rust": "botorch-rust PairwiseGP",
}
#: minimum ratio peer time / torchpref time, per peer, task and size (issue 27: at n = 20 ... 500 the
#: mode and the fit at least as fast as botorch-rust's and 4x PairwiseGP's; issue 10 at n = 500;
#: the posterior and EUBO keep their lead over both)
TARGETS = {
    n: {
        "mode": {"pairwisegp": 4.0, "botorch_rust": 1.0},
        "fit": {"pairwisegp": 5.0 if n == 500 else 4.0, "botorch_rust": 1.0},
        "posterior": {"pairwisegp": 100.0 if n == 500 else 1.0, "botorch_rust": 1.0},
        "eubo": {"pairwisegp": 1.0, "botorch_rust": 1.0},
    }
    for n in (20, 50, 100, 200, 500)
}
MIXED_TARGET_S = 5.0


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


#: the clock timings read: ``time.perf_counter`` (wall) or ``time.process_time`` (this process's
#: CPU time: on a machine loaded by other processes, the work done rather than the waiting)
CLOCK = {"wall": time.perf_counter, "cpu": time.process_time}
clock = CLOCK["wall"]


def _timed(fn, setup=None) -> dict[str, float]:
    """``{"cpu": seconds, "wall": seconds}`` of one call (``setup``, untimed, gives its argument)."""
    arg = setup() if setup is not None else None
    c0, w0 = time.process_time(), time.perf_counter()
    fn(arg) if setup is not None else fn()
    return {"cpu": time.process_time() - c0, "wall": time.perf_counter() - w0}


def _medians(times: list[dict[str, float]]) -> dict[str, float]:
    """The median of each clock over the repeats, and ``"s"``: the run's clock's."""
    out = {k: statistics.median(t[k] for t in times) for k in ("cpu", "wall")}
    return {**out, "s": out["cpu" if clock is CLOCK["cpu"] else "wall"]}


def blas_threads() -> dict:
    """The BLAS libraries' own thread counts (threadpoolctl, where installed) and what the compiled
    path's calls set them to (:data:`torchpref.inference.fast_path.BLAS_THREADS`)."""
    from torchpref.inference.fast_path import BLAS_THREADS

    try:
        from threadpoolctl import threadpool_info
    except ImportError:
        return {"libraries": None, "inside_compiled_calls": BLAS_THREADS.limited}
    libs = [f"{i['internal_api']} {os.path.basename(i['filepath'])}: {i['num_threads']}" for i in threadpool_info()]
    return {"libraries": libs, "inside_compiled_calls": BLAS_THREADS.limited}


def _torch_path(fn):
    """``fn`` with torchpref's compiled path off (``torchpref.fast_path("off")``)."""

    def run(*args):
        with fast_path("off"):
            return fn(*args)

    return run


BUILD = {"torchpref": bc.mode_torchpref, "pairwisegp": bc.build_pairwisegp, "botorch_rust": bc.build_botorch_rust}
FIT = {"torchpref": bc.fit_torchpref, "pairwisegp": bc.fit_pairwisegp, "botorch_rust": bc.fit_botorch_rust}
BUILD["torchpref_torch"], FIT["torchpref_torch"] = _torch_path(bc.mode_torchpref), _torch_path(bc.fit_torchpref)
EVIDENCE = {
    "torchpref_torch": _torch_path(bc.evidence_torchpref),
    "torchpref": bc.evidence_torchpref,
    "pairwisegp": bc.evidence_pairwisegp,
    "botorch_rust": bc.evidence_botorch_rust,
}


def utilities(model, lib: str) -> torch.Tensor:
    """The model's mode at its training items."""
    return model.mode.f if lib.startswith("torchpref") else torch.as_tensor(model.utility).detach()


def task_fns(task: str, lib: str, X, C, fitted=None):
    """``(fn, setup)`` for one measurement; ``setup``'s result is ``fn``'s argument (untimed)."""
    if task == "mode":
        return (lambda: BUILD[lib](X, C)), None
    if task == "fit":
        return FIT[lib], (lambda: BUILD[lib](X, C))
    if task == "kernel":  # the GPyTorch kernel alone (its modules and priors), which "mode" builds first
        make = bc.make_kernel_rs if lib == "botorch_rust" else bc.make_kernel
        return (lambda: make(X.shape[-1])), None
    wrap = _torch_path if lib == "torchpref_torch" else (lambda fn: fn)
    if task == "posterior":
        Xq = bc.query_points()
        return wrap(lambda: bc.posterior_moments(fitted, Xq)), None
    if task == "eubo":
        return wrap(lambda: bc.eubo_optimize(fitted, "torchpref" if lib == "torchpref_torch" else lib)), None
    raise ValueError(task)


def measure(task: str, n: int, p: int, libs, repeats: int, fitted: dict | None = None, warm_up: bool = True):
    X, C = bc.make_comparisons(n, p)
    fns = {lib: task_fns(task, lib, X, C, fitted[lib] if fitted else None) for lib in libs}
    if warm_up:
        for fn, setup in fns.values():  # first-call overheads, caches
            _timed(fn, setup)
    times: dict[str, list] = {lib: [] for lib in fns}
    for r in range(repeats):
        for lib, (fn, setup) in fns.items():
            times[lib].append(_timed(fn, setup))
        log(
            f"  {task} n={n} p={p} repeat {r + 1}/{repeats}: "
            + ", ".join(f"{lib} {t[-1]['cpu']:.4f}s cpu {t[-1]['wall']:.4f}s wall" for lib, t in times.items())
        )
    return {lib: _medians(t) for lib, t in times.items()}


def _cells(med: dict) -> dict:
    """A row's time columns from :func:`measure`'s medians."""
    out = {}
    for lib, m in med.items():
        out.update({f"{lib}_s": m["s"], f"{lib}_cpu_s": m["cpu"], f"{lib}_wall_s": m["wall"]})
    return out


def fit_quality(n: int, p: int, libs) -> tuple[dict, dict]:
    """Fitted models of each library, and their agreement: modes at the initial hyperparameters
    against torchpref's, fitted hyperparameters and evidence."""
    X, C = bc.make_comparisons(n, p)
    models = {lib: BUILD[lib](X, C) for lib in libs}
    f0 = {lib: utilities(m, lib) for lib, m in models.items()}
    for lib, m in models.items():
        FIT[lib](m)
    quality = {"n": n, "p": p}
    for lib, m in models.items():
        quality[lib] = {**bc.hyperparameters(m), "evidence": EVIDENCE[lib](m)}
        if lib != "torchpref":
            quality[lib]["max_abs_initial_mode_difference"] = float((f0[lib] - f0["torchpref"]).abs().max())
            quality[lib]["max_abs_fitted_mode_difference"] = float(
                (utilities(m, lib) - utilities(models["torchpref"], "torchpref")).abs().max()
            )
    return models, quality


def measure_mixed(repeats: int) -> float:
    X, C, u, ri = bc.make_mixed()

    def run():
        m = bc.PreferenceGP(
            X, comparisons=C, ratings=u, rating_index=ri, covar_module=bc.make_kernel(), comparison_noise=0.1
        )
        return m.mode

    run()
    ts = []
    for r in range(repeats):
        ts.append(_timed(run))
        log(
            f"  mixed_mode n={bc.MIXED_N} repeat {r + 1}/{repeats}: {ts[-1]['cpu']:.3f}s cpu {ts[-1]['wall']:.3f}s wall"
        )
    return _medians(ts)


# ------------------------------------------------------------------ memory (one subprocess each)
def _proc_status_kib(key: str) -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    raise KeyError(key)


def _reset_peak() -> int:
    """Reset this process's peak RSS (``VmHWM``) to its current RSS; return that RSS in KiB.

    ``getrusage``'s ``ru_maxrss`` cannot be used: Linux carries it across ``fork`` + ``exec``, so
    a child of this (large) benchmark process reports the parent's peak.
    """
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")
    return _proc_status_kib("VmRSS")


def _child(task: str, lib: str, n: int, p: int) -> None:
    """Run one task once in this fresh process; print its RSS before and its peak RSS (KiB) as JSON."""
    if task == "mixed_mode":
        X, C, u, ri = bc.make_mixed(n, p)
        before = _reset_peak()
        _ = bc.PreferenceGP(
            X, comparisons=C, ratings=u, rating_index=ri, covar_module=bc.make_kernel(), comparison_noise=0.1
        ).mode
    else:
        X, C = bc.make_comparisons(n, p)
        fitted = None
        if task in ("posterior", "eubo"):
            fitted = BUILD[lib](X, C)
            FIT[lib](fitted)
        fn, setup = task_fns(task, lib, X, C, fitted)
        arg = setup() if setup is not None else None
        before = _reset_peak()
        fn(arg) if setup is not None else fn()
    after = _proc_status_kib("VmHWM")
    print(json.dumps({"before_kib": before, "after_kib": after}))


def peak_mib(task: str, lib: str, n: int, p: int) -> tuple[float, float] | None:
    """``(peak, baseline)`` max RSS in MiB of a fresh process running the task once; the baseline
    is its max RSS just before the task (torch, BoTorch and the data already loaded)."""
    cmd = [
        sys.executable,
        str(Path(__file__).resolve()),
        "--threads",
        str(torch.get_num_threads()),
        "--child",
        task,
        lib,
        str(n),
        str(p),
    ]
    out = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "PYTHONWARNINGS": "ignore"})
    if out.returncode != 0:
        log(f"  memory child failed for {task}/{lib}: {out.stderr.strip().splitlines()[-1:]}")
        return None
    r = json.loads(out.stdout.strip().splitlines()[-1])
    return r["after_kib"] / 1024.0, r["before_kib"] / 1024.0


# ------------------------------------------------------------------------------------ main
def _arguments():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--sizes", type=int, nargs="+", default=SIZES, help="numbers of items n (p = 2 n comparisons)")
    ap.add_argument("--tasks", nargs="+", default=["mode", "fit", "posterior", "eubo"])
    ap.add_argument("--slow-n", type=int, default=1000, help="from this n on: one timing per library, no warm-up")
    ap.add_argument("--no-mixed", action="store_true", help="skip the 2,000-item mixed model")
    ap.add_argument("--no-memory", action="store_true")
    ap.add_argument(
        "--memory-sizes",
        type=int,
        nargs="*",
        default=[500],
        help="sizes whose peak memory is measured (each a subprocess)",
    )
    ap.add_argument("--no-botorch-rust", action="store_true", help="leave botorch-rust out even if installed")
    ap.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch.set_num_threads (default 1: on a shared machine, OpenMP threads that spin while "
        "other processes hold the cores make 2-thread timings erratic, up to 10x slower; 0: torch's default)",
    )
    ap.add_argument(
        "--clock",
        choices=sorted(CLOCK),
        default="wall",
        help="wall time, or this process's CPU time (robust to load from other processes; with one "
        "thread the two agree on a quiet machine)",
    )
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--name", default="speed_pairwise", help="stem of the files written (e.g. speed_pairwise_large)")
    ap.add_argument(
        "--paths",
        choices=("auto", "torch", "both"),
        default="both",
        help="torchpref's solver: the setting of the run (auto), the torch solver only, or both as two columns",
    )
    ap.add_argument("--quick", action="store_true", help="n = 20 ... 500, 3 repeats, no mixed model or memory probe")
    ap.add_argument("--child", nargs=4, metavar=("TASK", "LIB", "N", "P"), help=argparse.SUPPRESS)
    return ap.parse_args()


def _judge(row: dict, libs) -> None:
    """The row's ratios (peer time / torchpref time) and whether its targets are met."""
    tp = row["torchpref_s"]
    met, text = [], []
    for lib in PEERS:
        t = row.get(f"{lib}_s")
        row[f"ratio_{lib}"] = t / tp if t is not None else None
        target = TARGETS.get(row["n"], {}).get(row["task"], {}).get(lib)
        if target is not None and t is not None:
            text.append(f"{lib} >= {target:g}x")
            met.append(row[f"ratio_{lib}"] >= target)
    if row["task"] == "mixed_mode":
        row["target"], row["met"] = f"< {MIXED_TARGET_S:g} s", tp < MIXED_TARGET_S
    else:
        row["target"], row["met"] = "; ".join(text), (all(met) if met else None)


def main() -> None:
    args = _arguments()
    global clock
    clock = CLOCK[args.clock]
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.child:
        task, lib, n, p = args.child
        _child(task, lib, int(n), int(p))
        return

    if args.quick:
        args.sizes, args.repeats, args.no_mixed, args.no_memory = [20, 50, 100, 200, 500], 3, True, True
        args.tasks = ["mode", "fit", "eubo"]  # the posterior: botorch-rust's takes 51 s a call at n = 500
        args.slow_n = 500  # n = 500: one timing per library (botorch-rust's EUBO takes 30-50 s a call)
    if args.paths == "torch":
        set_fast_path("off")
    else:
        warm_up()  # load (or compile) the compiled path before any timing
    args.out.mkdir(parents=True, exist_ok=True)
    warnings.simplefilter("ignore", category=RuntimeWarning)  # BoTorch's fitting chatter, benchmark output only
    libs = ["torchpref", "pairwisegp"] + (["torchpref_torch"] if args.paths == "both" else [])
    rust_note = None
    if args.no_botorch_rust:
        rust_note = "left out (--no-botorch-rust)"
    elif bc.botorch_rust_available():
        import botorch_rs

        libs.append("botorch_rust")
        rust_note = f"botorch-rust {getattr(botorch_rs, '__version__', '?')}"
    else:
        rust_note = 'not installed (pip install -e ".[speed-peers]", PyPI botorch-rust): skipped'
    log(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {args.clock} clock, load {os.getloadavg()}")
    log(f"peers: {', '.join(libs[1:])}; botorch-rust: {rust_note}")
    load_start = os.getloadavg()
    rows, quality = [], []
    for n in args.sizes:
        p = 2 * n
        slow = n >= args.slow_n
        reps = 1 if slow else args.repeats
        if n == args.sizes[0] and "mode" in args.tasks:  # what building the kernel costs, of "mode"'s time
            rows.append({"task": "kernel", "n": n, "p": p, **_cells(measure("kernel", n, p, libs, max(reps, 5)))})
        for task in ("mode", "fit"):
            if task in args.tasks:
                med = measure(
                    task, n, p, libs, 1 if slow else max(reps, 5 if task == "mode" else reps), warm_up=not slow
                )
                rows.append({"task": task, "n": n, "p": p, **_cells(med)})
        fitted, q = fit_quality(n, p, libs)
        quality.append(q)
        log(f"  agreement n={n}: {q}")
        for task in ("posterior", "eubo"):
            if task in args.tasks:
                med = measure(task, n, p, libs, reps, fitted, warm_up=not slow)
                rows.append({"task": task, "n": n, "p": p, **_cells(med)})
    if not args.no_mixed:
        rows.append(
            {
                "task": "mixed_mode",
                "n": bc.MIXED_N,
                "p": bc.MIXED_N,
                **_cells({"torchpref": measure_mixed(args.repeats)}),
            }
        )
    for row in rows:
        _judge(row, libs)

    if not args.no_memory:
        log("peak memory: one subprocess per measurement")
        for row in rows:
            if row["task"] != "mixed_mode" and row["n"] not in args.memory_sizes:
                continue
            row_libs = ["torchpref"] if row["task"] == "mixed_mode" else libs
            for lib in row_libs:
                res = peak_mib(row["task"], lib, row["n"], row["p"])
                row[f"{lib}_peak_rss_mib"] = res[0] if res else None
                row[f"{lib}_baseline_rss_mib"] = res[1] if res else None
            log(
                f"  {row['task']} n={row['n']}: "
                + ", ".join(
                    f"{lib} peak {row[f'{lib}_peak_rss_mib']:.0f}" for lib in row_libs if row[f"{lib}_peak_rss_mib"]
                )
                + " MiB"
            )

    fields = ["task", "n", "p"] + [f"{lib}_s" for lib in ("torchpref", *PEERS)]
    fields += [f"ratio_{lib}" for lib in PEERS] + ["target", "met"]
    fields += [f"{lib}_{c}_s" for c in ("cpu", "wall") for lib in ("torchpref", *PEERS)]
    if not args.no_memory:
        fields += [f"{lib}_peak_rss_mib" for lib in ("torchpref", *PEERS)]
    with open(args.out / f"{args.name}.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        for row in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    meta = {
        "torch": torch.__version__,
        "botorch_rust": rust_note,
        "threads": torch.get_num_threads(),
        "threads_limited": "torch.set_num_threads(threads); BLAS inside the compiled path's calls: see blas",
        "blas": blas_threads(),
        "clocks_recorded": ["cpu", "wall"],
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "load_average_at_start": load_start,
        "load_average_at_end": os.getloadavg(),
        "clock": args.clock,
        "fast_path": {"torchpref": setting(), "torchpref_torch": "off" if args.paths == "both" else None},
        "repeats": args.repeats,
        "slow_n": args.slow_n,
        "statistic": "median",
        "dtype": "float64",
        "dim": bc.DIM,
        "eubo": bc.EUBO_SETTINGS,
        "memory": None
        if args.no_memory
        else (
            "VmHWM (MiB) of a fresh subprocess running the task once after resetting its peak via "
            "/proc/self/clear_refs (peak), and its RSS just before the task (baseline: imports + data)"
        ),
    }
    with open(args.out / f"{args.name}.json", "w") as fh:
        json.dump(stamped({"meta": meta, "rows": rows, "fit_quality": quality}), fh, indent=2)
    plot(rows, libs, args.out / f"{args.name}.png")

    print()
    print(f"{'task':<11}{'n':>6}{'p':>6}" + "".join(f"{lib + '_s':>15}" for lib in libs) + "  ratios / target")
    for r in rows:
        cells = "".join(f"{r[f'{lib}_s']:>15.4f}" if r.get(f"{lib}_s") is not None else f"{'-':>15}" for lib in libs)
        ratios = ", ".join(f"{r[f'ratio_{lib}']:.2f}x" for lib in PEERS if r.get(f"ratio_{lib}") is not None)
        met = "" if r["met"] is None else ("met" if r["met"] else "MISSED")
        print(f"{r['task']:<11}{r['n']:>6}{r['p']:>6}{cells}  {ratios}  {r['target']} {met}")
    log(f"wrote {args.out / args.name}.csv, .json, .png")


def plot(rows, libs, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in rows if r["task"] != "mixed_mode"]
    labels = [f"{r['task']}\nn={r['n']}" for r in rows]
    x = range(len(rows))
    fig, ax = plt.subplots(figsize=(max(10, 0.6 * len(rows)), 4.5))
    w = 0.8 / len(libs)
    for k, lib in enumerate(libs):
        t = [r.get(f"{lib}_s") if r.get(f"{lib}_s") is not None else float("nan") for r in rows]
        ax.bar([i + (k - (len(libs) - 1) / 2) * w for i in x], t, w, label=LIB_NAMES[lib])
    ax.set_yscale("log")
    ax.set_ylabel("seconds (median, log scale)")
    ax.set_xticks(list(x), labels, fontsize=7)
    ax.set_title("torchpref vs PairwiseGP (BoTorch, botorch-rust), same data and hyperparameters (d = 2, float64, CPU)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    from torchpref.experiments.stamp import recording_subprocesses

    with recording_subprocesses():  # the stamp hashes the code of every process it starts too
        main()
