r"""Speed of ``torchpref.PreferenceGP`` against BoTorch's ``PairwiseGP``, both in one run.

Same comparisons-only data, same kernel, priors and initial hyperparameters (see
``bench_common.py``). Each measurement is repeated, the two libraries alternating so that load
from other processes falls on both alike, and the median is kept. Tasks:

* ``mode``: construction + Laplace mode (``PairwiseGP``'s constructor solves its MAP; ours:
  construct + ``model.mode``);
* ``fit``: ``fit_gpytorch_mll`` with each model's Laplace MLL, from the same initial values;
* ``posterior``: ``posterior(X).mean`` and ``.variance`` on a ``1000 x 1 x d`` batch, model fitted
  and caches warm;
* ``mixed_mode``: torchpref only, 2,000 items with comparisons and ratings, construct + mode.

``--clock cpu`` times each task by this process's CPU time instead of wall time: on a machine
loaded by other processes the wall time mostly measures the waiting; with one thread the two
agree on a quiet machine.

Peak memory: a fresh subprocess per (task, library, size) loads everything, resets its peak RSS
(``/proc/self/clear_refs``), runs the task once and reads ``VmHWM`` (Linux only). Reported: that
peak and the RSS just before the task. ``tracemalloc`` does not see torch's allocations, and
``getrusage``'s max RSS is inherited from the parent across fork + exec, so neither is used.
The posterior's peak includes filling each model's prediction cache (first call).

Writes ``results/speed_pairwise.{csv,json,png}``.

Usage::

    .venv/bin/python benchmarks/speed_pairwise.py [--repeats 3] [--no-memory] [--threads 1] [--clock cpu]
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

RESULTS = HERE / "results"
#: minimum ratio pairwisegp / torchpref per size: at n = 500 (issue 10 item 6) and at n = 100
TARGETS = {500: {"mode": 4.0, "fit": 5.0, "posterior": 100.0}, 100: {"mode": 4.0, "fit": 4.0}}
MIXED_TARGET_S = 5.0


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


#: the clock timings read: ``time.perf_counter`` (wall) or ``time.process_time`` (this process's
#: CPU time: on a machine loaded by other processes, the work done rather than the waiting)
CLOCK = {"wall": time.perf_counter, "cpu": time.process_time}
clock = CLOCK["wall"]


def _timed(fn, setup=None) -> float:
    arg = setup() if setup is not None else None
    t0 = clock()
    fn(arg) if setup is not None else fn()
    return clock() - t0


def _fresh_mode_model(lib, X, C):
    """A model with its mode solved at the initial hyperparameters, ready to fit."""
    if lib == "torchpref":
        return bc.mode_torchpref(X, C)
    return bc.build_pairwisegp(X, C)


def task_fns(task: str, lib: str, X, C, fitted=None):
    """``(fn, setup)`` for one measurement; ``setup``'s result is ``fn``'s argument (untimed)."""
    if task == "mode":
        return (lambda: bc.mode_torchpref(X, C)) if lib == "torchpref" else (lambda: bc.build_pairwisegp(X, C)), None
    if task == "fit":
        fit = bc.fit_torchpref if lib == "torchpref" else bc.fit_pairwisegp
        return fit, (lambda: _fresh_mode_model(lib, X, C))
    if task == "posterior":
        Xq = bc.query_points()
        return (lambda: bc.posterior_moments(fitted, Xq)), None
    raise ValueError(task)


def measure_pair(task: str, n: int, p: int, repeats: int, fitted: dict | None = None) -> dict[str, float]:
    X, C = bc.make_comparisons(n, p)
    fns = {lib: task_fns(task, lib, X, C, fitted[lib] if fitted else None) for lib in ("torchpref", "pairwisegp")}
    for fn, setup in fns.values():  # warm-up (first-call overheads, caches)
        _timed(fn, setup)
    times = {lib: [] for lib in fns}
    for r in range(repeats):
        for lib, (fn, setup) in fns.items():
            times[lib].append(_timed(fn, setup))
        log(
            f"  {task} n={n} p={p} repeat {r + 1}/{repeats}: "
            + ", ".join(f"{lib} {t[-1]:.4f}s" for lib, t in times.items())
        )
    return {lib: statistics.median(t) for lib, t in times.items()}


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
        log(f"  mixed_mode n={bc.MIXED_N} repeat {r + 1}/{repeats}: {ts[-1]:.3f}s")
    return statistics.median(ts)


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
        if task == "posterior":
            fitted = _fresh_mode_model(lib, X, C)
            (bc.fit_torchpref if lib == "torchpref" else bc.fit_pairwisegp)(fitted)
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
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-memory", action="store_true")
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
    ap.add_argument("--child", nargs=4, metavar=("TASK", "LIB", "N", "P"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    global clock
    clock = CLOCK[args.clock]
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.child:
        task, lib, n, p = args.child
        _child(task, lib, int(n), int(p))
        return

    RESULTS.mkdir(exist_ok=True)
    warnings.simplefilter("ignore", category=RuntimeWarning)  # BoTorch's fitting chatter, benchmark output only
    log(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {args.clock} clock, load {os.getloadavg()}")
    load_start = os.getloadavg()
    rows, quality = [], []
    for n, p in bc.SIZES:
        med = measure_pair("mode", n, p, max(args.repeats, 5))
        rows.append(
            {"task": "mode", "n": n, "p": p, "torchpref_s": med["torchpref"], "pairwisegp_s": med["pairwisegp"]}
        )
        med = measure_pair("fit", n, p, args.repeats)
        rows.append({"task": "fit", "n": n, "p": p, "torchpref_s": med["torchpref"], "pairwisegp_s": med["pairwisegp"]})
        # fitted models for the posterior timing and the fit-quality comparison
        X, C = bc.make_comparisons(n, p)
        fitted = {"torchpref": bc.mode_torchpref(X, C), "pairwisegp": bc.build_pairwisegp(X, C)}
        bc.fit_torchpref(fitted["torchpref"])
        bc.fit_pairwisegp(fitted["pairwisegp"])
        f_tp, f_pg = fitted["torchpref"].mode.f, fitted["pairwisegp"].utility.detach()
        quality.append(
            {
                "n": n,
                "p": p,
                "torchpref": {
                    **bc.hyperparameters(fitted["torchpref"]),
                    "evidence": bc.evidence_torchpref(fitted["torchpref"]),
                },
                "pairwisegp": {
                    **bc.hyperparameters(fitted["pairwisegp"]),
                    "evidence": bc.evidence_pairwisegp(fitted["pairwisegp"]),
                },
                "max_abs_mode_difference": float((f_tp - f_pg).abs().max()),
            }
        )
        log(f"  fit quality n={n}: {quality[-1]}")
        med = measure_pair("posterior", n, p, args.repeats, fitted)
        rows.append(
            {"task": "posterior", "n": n, "p": p, "torchpref_s": med["torchpref"], "pairwisegp_s": med["pairwisegp"]}
        )
    mixed_p = bc.MIXED_N
    rows.append(
        {
            "task": "mixed_mode",
            "n": bc.MIXED_N,
            "p": mixed_p,
            "torchpref_s": measure_mixed(args.repeats),
            "pairwisegp_s": None,
        }
    )

    for row in rows:
        tp, pg = row["torchpref_s"], row["pairwisegp_s"]
        row["ratio"] = pg / tp if pg is not None else None
        if row["task"] == "mixed_mode":
            row["target"], row["met"] = f"< {MIXED_TARGET_S:g} s", tp < MIXED_TARGET_S
        elif row["task"] in TARGETS.get(row["n"], {}):
            row["target"] = f">= {TARGETS[row['n']][row['task']]:g}x"
            row["met"] = row["ratio"] >= TARGETS[row["n"]][row["task"]]
        else:
            row["target"], row["met"] = "", None

    if not args.no_memory:
        log("peak memory: one subprocess per measurement")
        for row in rows:
            libs = ["torchpref"] if row["task"] == "mixed_mode" else ["torchpref", "pairwisegp"]
            for lib in ("torchpref", "pairwisegp"):
                res = peak_mib(row["task"], lib, row["n"], row["p"]) if lib in libs else None
                row[f"{lib}_peak_rss_mib"] = res[0] if res else None
                row[f"{lib}_baseline_rss_mib"] = res[1] if res else None
            log(
                f"  {row['task']} n={row['n']}: "
                + ", ".join(
                    f"{lib} peak {row[f'{lib}_peak_rss_mib']:.0f} (before task {row[f'{lib}_baseline_rss_mib']:.0f})"
                    for lib in libs
                    if row[f"{lib}_peak_rss_mib"] is not None
                )
                + " MiB"
            )

    fields = ["task", "n", "p", "torchpref_s", "pairwisegp_s", "ratio", "target", "met"]
    if not args.no_memory:
        fields += ["torchpref_peak_rss_mib", "pairwisegp_peak_rss_mib"]
    with open(RESULTS / "speed_pairwise.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        for row in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    meta = {
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "load_average_at_start": load_start,
        "load_average_at_end": os.getloadavg(),
        "clock": args.clock,
        "repeats": args.repeats,
        "statistic": "median",
        "dtype": "float64",
        "dim": bc.DIM,
        "memory": None
        if args.no_memory
        else (
            "VmHWM (MiB) of a fresh subprocess running the task once after resetting its peak via "
            "/proc/self/clear_refs (peak), and its RSS just before the task (baseline: imports + data)"
        ),
    }
    with open(RESULTS / "speed_pairwise.json", "w") as fh:
        json.dump({"meta": meta, "rows": rows, "fit_quality": quality}, fh, indent=2)
    plot(rows, RESULTS / "speed_pairwise.png")

    print()
    print(f"{'task':<11}{'n':>6}{'p':>6}{'torchpref_s':>13}{'pairwisegp_s':>14}{'ratio':>9}  target")
    for r in rows:
        pg = f"{r['pairwisegp_s']:.4f}" if r["pairwisegp_s"] is not None else "-"
        ratio = f"{r['ratio']:.1f}" if r["ratio"] is not None else "-"
        met = "" if r["met"] is None else ("met" if r["met"] else "MISSED")
        print(f"{r['task']:<11}{r['n']:>6}{r['p']:>6}{r['torchpref_s']:>13.4f}{pg:>14}{ratio:>9}  {r['target']} {met}")
    log(f"wrote {RESULTS / 'speed_pairwise.csv'}, .json, .png")


def plot(rows, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [f"{r['task']}\nn={r['n']}, p={r['p']}" for r in rows]
    x = range(len(rows))
    fig, ax = plt.subplots(figsize=(10, 4.5))
    w = 0.38
    tp = [r["torchpref_s"] for r in rows]
    pg = [r["pairwisegp_s"] if r["pairwisegp_s"] is not None else float("nan") for r in rows]
    ax.bar([i - w / 2 for i in x], tp, w, label="torchpref PreferenceGP")
    ax.bar([i + w / 2 for i in x], pg, w, label="BoTorch PairwiseGP")
    for i, r in enumerate(rows):
        if r["ratio"] is not None:
            ax.text(
                i,
                max(tp[i], pg[i]) * 1.3,
                f"{r['ratio']:.0f}x" if r["ratio"] >= 10 else f"{r['ratio']:.1f}x",
                ha="center",
                fontsize=8,
            )
    ax.set_yscale("log")
    ax.set_ylabel("seconds (median, log scale)")
    ax.set_xticks(list(x), labels, fontsize=8)
    ax.set_title("torchpref vs BoTorch PairwiseGP, same data and hyperparameters (d = 2, float64, CPU)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
