r"""The suite's summary: curves, paired verdicts ("best or tied?"), files and figures.

For every family and condition, each metric's mean ± standard error per query count and per
unit of effort (:func:`~torchpref.experiments.results.curves`); at each checkpoint (queries 10
and 20, effort 10 and 20) the best strategy by mean and, for every strategy, whether it is the
best or statistically tied with it (two-sided Wilcoxon signed-rank p > 0.05 on the paired
trials, :func:`~torchpref.experiments.results.paired_tests`).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from torchpref.experiments.results import at_budgets, curves, paired_tests, write_json

#: metrics where smaller is better (the others: larger)
SMALLER_IS_BETTER = ("wrms", "regret")
ALPHA = 0.05


def _values(trials: list[dict[str, Any]], strategy: str, metric: str, axis: str, x: float) -> list[float]:
    if axis == "queries":
        return [r[strategy][metric][int(x)] for r in trials]
    return [at_budgets(r[strategy][metric], r[strategy]["cost"], [x])[0] for r in trials]


def verdicts(
    trials: list[dict[str, Any]], strategies: Sequence[str], metric: str, axis: str, x: float
) -> dict[str, Any]:
    r"""At one checkpoint: each strategy's mean, the best one, and per strategy ``"best"``,
    ``"tied"`` (Wilcoxon p > :data:`ALPHA` against the best) or ``"worse"``, with the paired test."""
    vals = {s: _values(trials, s, metric, axis, x) for s in strategies}
    means = {s: sum(v) / len(v) for s, v in vals.items()}
    sign = -1.0 if metric in SMALLER_IS_BETTER else 1.0
    best = max(strategies, key=lambda s: sign * means[s])
    out: dict[str, Any] = {"best": best, "mean": means, "status": {}, "tests": {}}
    for s in strategies:
        if s == best:
            out["status"][s] = "best"
            continue
        t = paired_tests(vals[s], vals[best]) if len(trials) >= 2 else {"p_wilcoxon": math.nan}
        p = t["p_wilcoxon"]
        out["status"][s] = "tied" if (math.isnan(p) or p > ALPHA) else "worse"
        out["tests"][s] = t
    return out


def summarise(
    results: dict[tuple[str, str], list[dict[str, Any]]],
    strategies: Sequence[str],
    metrics: Sequence[str],
    budgets: Sequence[float],
    checkpoints: Sequence[int],
) -> dict[str, Any]:
    r"""Curves and verdicts of every (family, condition) of ``results`` (``{(family, condition):
    [one {strategy: record} per trial]}``)."""
    out: dict[str, Any] = {"curves": {}, "verdicts": {}, "fraction_ratings": {}}
    for (f, c), trials in results.items():
        key = f"{f}/{c}"
        max_budget = min(r[s]["cost"][-1] for r in trials for s in strategies)
        grid = [float(b) for b in range(int(math.floor(max_budget)) + 1)]
        out["curves"][key] = {
            "queries": curves(trials, strategies, metrics),
            "effort": curves(trials, strategies, metrics, grid),
            "budgets": grid,
        }
        queries = len(trials[0][strategies[0]]["wrms"]) - 1
        points = [("queries", float(q)) for q in checkpoints if q <= queries]
        points += [("effort", b) for b in budgets if b <= max_budget + 1e-9]  # as at_budgets: sums of seconds round
        out["verdicts"][key] = {
            f"{axis} {x:g}": {m: verdicts(trials, strategies, m, axis, x) for m in metrics} for axis, x in points
        }
        out["fraction_ratings"][key] = {
            s: sum(k == "rating" for r in trials for k in r[s]["kinds"])
            / max(1, sum(len(r[s]["kinds"]) for r in trials))
            for s in strategies
        }
    out["best_or_tied"] = {s: _count(out["verdicts"], s) for s in strategies}
    out["verdict_lines"] = [
        f"{s:18s} best or tied in {n} of {t} (family, condition, checkpoint, metric) cells"
        for s, (n, t) in out["best_or_tied"].items()
    ]
    return out


def _count(all_verdicts: dict[str, Any], strategy: str) -> tuple[int, int]:
    cells = [
        v["status"][strategy]
        for per_point in all_verdicts.values()
        for per_metric in per_point.values()
        for v in per_metric.values()
    ]
    return sum(c != "worse" for c in cells), len(cells)


def _write_csv(path: Path, summary: dict[str, Any], metrics: Sequence[str]) -> None:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(
            ["family", "condition", "axis", "x", "strategy", *[f"{m}_{k}" for m in metrics for k in ("mean", "sem")]]
        )
        for key, cv in summary["curves"].items():
            f, c = key.split("/")
            for axis in ("queries", "effort"):
                for s, cols in cv[axis].items():
                    xs = range(len(cols[f"{metrics[0]}_mean"])) if axis == "queries" else cv["budgets"]
                    for i, x in enumerate(xs):
                        w.writerow(
                            [
                                f,
                                c,
                                axis,
                                x,
                                s,
                                *[repr(float(cols[f"{m}_{k}"][i])) for m in metrics for k in ("mean", "sem")],
                            ]
                        )


def _figure(
    path: Path,
    summary: dict[str, Any],
    families: Sequence[str],
    condition: str,
    strategies: Sequence[str],
    metrics: Sequence[str],
) -> None:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(
        len(families), len(metrics), figsize=(4.2 * len(metrics), 2.6 * len(families)), squeeze=False
    )
    for row, f in zip(axes, families):
        cv = summary["curves"][f"{f}/{condition}"]
        for ax, m in zip(row, metrics):
            for s in strategies:
                mean, sem = cv["effort"][s][f"{m}_mean"], cv["effort"][s][f"{m}_sem"]
                (line,) = ax.plot(cv["budgets"], mean, label=s, lw=1.4)
                ax.fill_between(
                    cv["budgets"],
                    [a - b for a, b in zip(mean, sem)],
                    [a + b for a, b in zip(mean, sem)],
                    color=line.get_color(),
                    alpha=0.2,
                )
            ax.set_title(f"{f}: {m}", fontsize=9)
            ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("effort")
    axes[0][0].legend(fontsize=7)
    fig.suptitle(f"User-family suite, {condition} hyperparameters (mean ± s.e. against effort)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write_suite_files(
    out: Path,
    summary: dict[str, Any],
    families: Sequence[str],
    conditions: Sequence[str],
    strategies: Sequence[str],
    metrics: Sequence[str],
) -> None:
    """``suite.json`` (the curves), ``suite.csv`` (long format), ``suite_summary.json`` (the
    verdicts and settings) and ``suite_<condition>.png`` per condition, in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "suite.json", summary["curves"], stamp=False)  # keyed by family: suite_summary.json is stamped
    _write_csv(out / "suite.csv", summary, metrics)
    write_json(out / "suite_summary.json", {k: v for k, v in summary.items() if k != "curves"})
    for c in conditions:
        _figure(out / f"suite_{c}.png", summary, families, c, strategies, metrics)
