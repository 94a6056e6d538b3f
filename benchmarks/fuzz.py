r"""Hostile-problem fuzz: float32 against float64 and against BoTorch's ``PairwiseGP``.

Runs :func:`fuzz_problems.check` on ``--num`` problems (seeds ``--start`` on) and writes

* ``fuzz.csv``: one row per problem (outcomes, iterations, jitter, float32-float64 gaps);
* ``fuzz.json``: the summary (counts of exceptions, NaNs and unconverged solves per dtype, float32
  against ``PairwiseGP`` on the same comparisons-only problems, the share of problems whose float32
  posterior is within ``1e-3`` of float64's, with autograd off and on, and the worst);
* ``fuzz.png``: the gaps against ``n`` and against the float32 jitter.

Usage::

    nice -n 10 .venv/bin/python benchmarks/fuzz.py --num 1000 --out benchmarks/results
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from pathlib import Path

import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))

import fuzz_problems as fp  # noqa: E402

TARGET = 1e-3  # relative float32-float64 agreement asked for


def summarise(rows: list[dict]) -> dict:
    """Counts and shares over the problems (see the module docstring)."""
    out: dict = {"problems": len(rows), "by_kind": {k: sum(r["kind"] == k for r in rows) for k in fp.KINDS},
                 "n_max": max(r["n"] for r in rows), "target": TARGET}
    for dt in ("f64", "f32"):
        ran = [r for r in rows if r[f"{dt}_error"] is None]
        out[dt] = {"exceptions": len(rows) - len(ran), "nan": sum(bool(r[f"{dt}_nan"]) for r in rows),
                   "unconverged": sum(r[f"{dt}_converged"] is False for r in ran),
                   "errors": sorted({r[f"{dt}_error"].split(":")[0] for r in rows if r[f"{dt}_error"]})}
    comp = [r for r in rows if r["kind"] == "comparisons"]
    out["comparisons_only"] = {"problems": len(comp), "f32_exceptions": sum(r["f32_error"] is not None for r in comp),
                               "pairwisegp_f32_exceptions": sum(r["pairwisegp_error"] is not None for r in comp),
                               "pairwisegp_nan": sum(bool(r["pairwisegp_nan"]) for r in comp)}
    both = [r for r in rows if r["gap_mean_nograd"] is not None]
    for tag in ("nograd", "grad"):
        gaps = [max(r[f"gap_mean_{tag}"], r[f"gap_cov_{tag}"]) for r in both]
        worst = sorted(both, key=lambda r: -max(r[f"gap_mean_{tag}"], r[f"gap_cov_{tag}"]))[:5]
        out[f"agreement_{tag}"] = {
            "problems": len(gaps), "within_target": sum(g <= TARGET for g in gaps),
            "share_within_target": sum(g <= TARGET for g in gaps) / max(len(gaps), 1),
            "median": sorted(gaps)[len(gaps) // 2] if gaps else None, "max": max(gaps) if gaps else None,
            "worst": [{k: r[k] for k in ("seed", "kind", "n", "lengthscale", "outputscale", "f32_jitter")}
                      | {"gap": max(r[f"gap_mean_{tag}"], r[f"gap_cov_{tag}"])} for r in worst]}
    beyond = [r for r in both if max(r["gap_mean_nograd"], r["gap_cov_nograd"]) > TARGET]
    out["beyond_target_with_jitter_at_least_1e-5"] = sum((r["f32_jitter"] or 0) >= 1e-5 for r in beyond)
    return out


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    both = [r for r in rows if r["gap_mean_nograd"] is not None]
    colour = {"comparisons": "tab:blue", "ratings": "tab:orange", "mixed": "tab:green"}
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for ax, tag in zip(axes[:2], ("nograd", "grad")):
        for kind in fp.KINDS:
            sel = [r for r in both if r["kind"] == kind]
            ax.scatter([r["n"] for r in sel], [max(r[f"gap_mean_{tag}"], r[f"gap_cov_{tag}"], 1e-12) for r in sel],
                       s=8, alpha=0.6, c=colour[kind], label=kind)
        ax.axhline(TARGET, color="k", lw=1, ls="--", label="1e-3")
        ax.set(xscale="log", yscale="log", xlabel="n items", ylabel="float32 vs float64 posterior gap (relative)",
               title=f"autograd {'on' if tag == 'grad' else 'off'}")
        ax.legend(fontsize=8)
    jit = [max(r["f32_jitter"] or 0, 1e-12) for r in both]
    axes[2].scatter(jit, [max(r["gap_mean_nograd"], r["gap_cov_nograd"], 1e-12) for r in both], s=8, alpha=0.6,
                    c=[colour[r["kind"]] for r in both])
    axes[2].axhline(TARGET, color="k", lw=1, ls="--")
    axes[2].set(xscale="log", yscale="log", xlabel="float32 jitter / outputscale (1e-12: none)",
                ylabel="gap (autograd off)", title="the gap follows the jitter float32 needs")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write(rows: list[dict], args: argparse.Namespace, seconds: float) -> dict:
    """``fuzz.csv`` and ``fuzz.json`` for the problems done so far; returns the summary."""
    with open(args.out / "fuzz.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    summary = summarise(rows) | {"seeds": [args.start, args.start + len(rows) - 1], "max_n": args.max_n,
                                 "seconds": round(seconds, 1), "torch": torch.__version__}
    (args.out / "fuzz.json").write_text(json.dumps(summary, indent=1, default=lambda x: None if math.isnan(x) else x))
    return summary


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--num", type=int, default=1000, help="problems (default 1000)")
    ap.add_argument("--start", type=int, default=0, help="first seed")
    ap.add_argument("--max-n", type=int, default=1500, help="largest number of items")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
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
    print(json.dumps({k: summary[k] for k in ("problems", "f64", "f32", "comparisons_only")}, indent=1))
    return summary


if __name__ == "__main__":
    main()
