r"""Hostile-problem fuzz: float32 against float64 and against BoTorch's ``PairwiseGP``.

Runs :func:`torchpref.testing.problems.check` on ``--num`` problems (seeds ``--start`` on) and writes

* ``fuzz.csv``: one row per problem (outcomes, iterations, jitter, float32-float64 gaps);
* ``fuzz.json``: the summary (counts of exceptions, NaNs and unconverged solves per model of
  ``torchpref.testing.problems.RUNS``: float64, float32 in mixed precision (the default) and native float32;
  each against ``PairwiseGP`` on the same comparisons-only problems; the share of problems whose
  float32 posterior is within ``1e-3`` of float64's, with autograd off and on, and the worst; the
  seconds each model took);
* ``fuzz.png``: the gaps against ``n``, the native float32 gap against its jitter, and the time
  per problem.

Usage::

    nice -n 10 .venv/bin/python benchmarks/robustness/fuzz.py --num 1000 --out benchmarks/results
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import time
from pathlib import Path

import torch
from tqdm import tqdm

from torchpref.experiments.stamp import stamped
from torchpref.testing import problems as fp

TARGET = 1e-3  # relative float32-float64 agreement asked for


RUN_LABEL = {"f64": "float64", "f32": "float32 (mixed precision, default)", "f32n": "float32 (native)"}


def _gap(r: dict, run: str, tag: str) -> float:
    return max(r[f"{run}_gap_mean_{tag}"], r[f"{run}_gap_cov_{tag}"])


def _agreement(rows: list[dict], run: str, tag: str) -> dict:
    both = [r for r in rows if r[f"{run}_gap_mean_nograd"] is not None]
    gaps = [_gap(r, run, tag) for r in both]
    worst = sorted(both, key=lambda r: -_gap(r, run, tag))[:5]
    return {
        "problems": len(gaps),
        "within_target": sum(g <= TARGET for g in gaps),
        "share_within_target": sum(g <= TARGET for g in gaps) / max(len(gaps), 1),
        "median": sorted(gaps)[len(gaps) // 2] if gaps else None,
        "max": max(gaps) if gaps else None,
        "worst": [
            {k: r[k] for k in ("seed", "kind", "n", "lengthscale", "outputscale", f"{run}_jitter")}
            | {"gap": _gap(r, run, tag)}
            for r in worst
        ],
    }


def _seconds(rows: list[dict]) -> dict:
    """Total seconds per run over the problems all runs solved, overall and by ``n``."""
    ok = [r for r in rows if all(r[f"{run}_error"] is None for run in fp.RUNS)]
    out = {}
    for label, lo, hi in (
        ("all", 0, math.inf),
        ("n < 100", 0, 100),
        ("100 <= n < 500", 100, 500),
        ("n >= 500", 500, math.inf),
    ):
        sel = [r for r in ok if lo <= r["n"] < hi]
        tot = {run: round(sum(r[f"{run}_seconds"] for r in sel), 2) for run in fp.RUNS}
        out[label] = (
            {"problems": len(sel)}
            | tot
            | {
                "f32_over_f32n": round(tot["f32"] / tot["f32n"], 3) if tot["f32n"] else None,
                "f32_over_f64": round(tot["f32"] / tot["f64"], 3) if tot["f64"] else None,
            }
        )
    return out


def summarise(rows: list[dict]) -> dict:
    """Counts and shares over the problems (see the module docstring)."""
    out: dict = {
        "problems": len(rows),
        "by_kind": {k: sum(r["kind"] == k for r in rows) for k in fp.KINDS},
        "n_max": max(r["n"] for r in rows),
        "target": TARGET,
        "runs": RUN_LABEL,
    }
    for run in fp.RUNS:
        ran = [r for r in rows if r[f"{run}_error"] is None]
        out[run] = {
            "exceptions": len(rows) - len(ran),
            "nan": sum(bool(r[f"{run}_nan"]) for r in rows),
            "unconverged": sum(r[f"{run}_converged"] is False for r in ran),
            "errors": sorted({r[f"{run}_error"].split(":")[0] for r in rows if r[f"{run}_error"]}),
        }
    comp = [r for r in rows if r["kind"] == "comparisons"]
    out["comparisons_only"] = (
        {"problems": len(comp)}
        | {f"{run}_exceptions": sum(r[f"{run}_error"] is not None for r in comp) for run in fp.RUNS}
        | {
            "pairwisegp_f32_exceptions": sum(r["pairwisegp_error"] is not None for r in comp),
            "pairwisegp_nan": sum(bool(r["pairwisegp_nan"]) for r in comp),
        }
    )
    for run in fp.FLOAT32_RUNS:
        for tag in ("nograd", "grad"):
            out[f"agreement_{run}_{tag}"] = _agreement(rows, run, tag)
        beyond = [r for r in rows if r[f"{run}_gap_mean_nograd"] is not None and _gap(r, run, "nograd") > TARGET]
        out[f"{run}_beyond_target_with_jitter_at_least_1e-5"] = sum((r[f"{run}_jitter"] or 0) >= 1e-5 for r in beyond)
    out["seconds_per_run"] = _seconds(rows)
    return out


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colour = {"comparisons": "tab:blue", "ratings": "tab:orange", "mixed": "tab:green"}
    fig, axes = plt.subplots(1, 4, figsize=(20, 4.2))
    for ax, run in zip(axes[:2], fp.FLOAT32_RUNS):
        both = [r for r in rows if r[f"{run}_gap_mean_nograd"] is not None]
        for kind in fp.KINDS:
            sel = [r for r in both if r["kind"] == kind]
            for tag, marker in (("nograd", "o"), ("grad", "x")):
                ax.scatter(
                    [r["n"] for r in sel],
                    [max(_gap(r, run, tag), 1e-12) for r in sel],
                    s=8,
                    alpha=0.5,
                    c=colour[kind],
                    marker=marker,
                    label=f"{kind}, autograd {'on' if tag == 'grad' else 'off'}",
                )
        ax.axhline(TARGET, color="k", lw=1, ls="--", label="1e-3")
        ax.set(xscale="log", yscale="log", xlabel="n items", ylabel="gap to float64 (relative)", title=RUN_LABEL[run])
        ax.legend(fontsize=7)
    both = [r for r in rows if r["f32n_gap_mean_nograd"] is not None]
    axes[2].scatter(
        [max(r["f32n_jitter"] or 0, 1e-12) for r in both],
        [max(_gap(r, "f32n", "nograd"), 1e-12) for r in both],
        s=8,
        alpha=0.6,
        c=[colour[r["kind"]] for r in both],
    )
    axes[2].axhline(TARGET, color="k", lw=1, ls="--")
    axes[2].set(
        xscale="log",
        yscale="log",
        xlabel="native float32 jitter / outputscale (1e-12: none)",
        ylabel="gap (autograd off)",
        title="native float32: the gap follows its jitter",
    )
    ok = [r for r in rows if all(r[f"{run}_error"] is None for run in fp.RUNS)]
    for run, c in (("f64", "k"), ("f32", "tab:red"), ("f32n", "tab:purple")):
        axes[3].scatter(
            [r["n"] for r in ok], [r[f"{run}_seconds"] for r in ok], s=6, alpha=0.4, c=c, label=RUN_LABEL[run]
        )
    axes[3].set(
        xscale="log",
        yscale="log",
        xlabel="n items",
        ylabel="seconds (build, mode, 2 posteriors)",
        title="time per problem",
    )
    axes[3].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write(rows: list[dict], args: argparse.Namespace, seconds: float) -> dict:
    """``fuzz.csv`` and ``fuzz.json`` for the problems done so far; returns the summary."""
    with open(args.out / "fuzz.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    summary = summarise(rows) | {
        "seeds": [args.start, args.start + len(rows) - 1],
        "max_n": args.max_n,
        "seconds": round(seconds, 1),
        "torch": torch.__version__,
    }
    summary = stamped(summary)  # commit, source hashes, versions, load, times (make results-status)
    (args.out / "fuzz.json").write_text(json.dumps(summary, indent=1, default=lambda x: None if math.isnan(x) else x))
    return summary


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--num", type=int, default=1000, help="problems (default 1000)")
    ap.add_argument("--start", type=int, default=0, help="first seed")
    ap.add_argument("--max-n", type=int, default=1500, help="largest number of items")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "results")
    ap.add_argument("--no-pairwisegp", action="store_true", help="skip BoTorch's PairwiseGP")
    args = ap.parse_args(argv)
    if args.num < 1 or args.max_n < 1:
        ap.error("--num and --max-n must be at least 1")
    args.out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(1)
    rows, t0 = [], time.perf_counter()
    for seed in tqdm(range(args.start, args.start + args.num), desc="fuzz problems"):
        t = time.perf_counter()
        rows.append(fp.check(fp.make_problem(seed, args.max_n), pairwisegp=not args.no_pairwisegp))
        rows[-1]["seconds"] = time.perf_counter() - t
        if len(rows) % 100 == 0 and len(rows) < args.num:  # a stopped run keeps what it has done
            write(rows, args, time.perf_counter() - t0)
    summary = write(rows, args, time.perf_counter() - t0)
    plot(rows, args.out / "fuzz.png")
    print(json.dumps({k: summary[k] for k in ("problems", *fp.RUNS, "comparisons_only", "seconds_per_run")}, indent=1))
    return summary


if __name__ == "__main__":
    main()
