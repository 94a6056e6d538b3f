r"""The twins' summary (:mod:`~torchpref.experiments.twins`): areas and paired tests against
random, questions to reach random's concordance, verdicts at equal seconds, files and the figure.

* **area**: a curve's mean over questions ``1 .. Q`` (concordance, value: higher is better; log
  loss: lower), per twin; each strategy against the baseline by the paired two-sided Wilcoxon
  test over twins (:func:`~torchpref.experiments.results.paired_tests`);
* **questions to reach**: per twin, the first question count ``k`` at which the strategy's
  concordance is at least the baseline's after ``Q`` questions for the same twin (``Q + 1``,
  "not within ``Q``", if never); its median over twins. Also the mean curves' version: the first
  ``k`` whose mean concordance reaches the baseline's mean after ``Q``;
* **equal seconds**: each metric after the last answer within 10 and 20 ratings' worth of seconds
  of the effort model (34 and 68 s plain, 134 and 268 s trajectories), and per cell the best
  strategy by mean and whether each is best or tied with it (Wilcoxon p > 0.05 on the twins).
"""

from __future__ import annotations

import csv
import json
import math
import statistics
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from torchpref.experiments.results import at_budgets, mean_sem, paired_tests, write_json
from torchpref.experiments.runner import EFFORT_FREE
from torchpref.experiments.suite import EFFORTS as SUITE_EFFORTS
from torchpref.experiments.suite import M
from torchpref.simulation.raters import EffortModel

__all__ = ["EFFORTS", "append_rows", "read_rows", "report", "summarise"]

#: the effort models in seconds (docs/suite.md): ``plain`` and ``trajectories``
EFFORTS: dict[str, EffortModel] = {k: v for k, v in SUITE_EFFORTS.items() if v is not None}

METRICS = ("concordance", "value", "log_loss")
SMALLER = ("log_loss",)
BUDGET_RATINGS = (10, 20)
ALPHA = 0.05


def read_rows(path: Path) -> dict[tuple, list[dict]]:
    """The rows of a ``twins_rows.jsonl`` by (data set, fold, condition, strategy, effort)."""
    out: dict[tuple, list[dict]] = {}
    if path.is_file():
        for line in path.read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                out.setdefault((r["dataset"], r["fold"], r["condition"], r["strategy"], r["effort"]), []).append(r)
    return out


def append_rows(path: Path, rows: Sequence[dict]) -> None:
    """Append rows to a ``twins_rows.jsonl`` (one JSON object a line), flushed."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a") as fh:
        for r in rows:
            fh.write(json.dumps(r) + "\n")


def _cells(rows: Sequence[dict], effort: str) -> dict[tuple[str, str], dict[str, dict[tuple, dict]]]:
    """``{(data set, condition): {strategy: {(fold, twin): record with "cost"}}}`` under ``effort``:
    each strategy's run for that effort model, or its effort-free run, its costs in that model's
    seconds."""
    costs = EFFORTS[effort].costs(M)
    out: dict[tuple[str, str], dict[str, dict[tuple, dict]]] = {}
    for r in rows:
        if r["effort"] != effort and r["strategy"] not in EFFORT_FREE:
            continue
        rec = dict(r, cost=_cost(r["kinds"], costs))
        if "repeats" in r:
            rec["repeats"] = [dict(rp, cost=_cost(rp["kinds"], costs)) for rp in r["repeats"]]
        out.setdefault((r["dataset"], r["condition"]), {}).setdefault(r["strategy"], {})[r["fold"], r["twin"]] = rec
    return out


def _cost(kinds: Sequence[str], costs: dict[str, float]) -> list[float]:
    out = [0.0]
    for k in kinds:
        out.append(out[-1] + costs[k])
    return out


def at_seconds(rec: dict, metric: str, budgets: Sequence[float]) -> list[float]:
    """A record's ``metric`` after the last answer within each budget of seconds (a repeated
    baseline's: the mean over its repeats)."""
    reps = rec.get("repeats") or [rec]
    per = [at_budgets(r[metric], r["cost"], budgets) for r in reps]
    return [sum(v[i] for v in per) / len(per) for i in range(len(budgets))]


def _area(curve: Sequence[float]) -> float:
    return sum(curve[1:]) / max(1, len(curve) - 1)


def _reach(mine: Sequence[float], target: float) -> int:
    """The first question count whose value reaches ``target`` (``len(mine)`` if none)."""
    return next((k for k, v in enumerate(mine) if v >= target - 1e-12), len(mine))


def _against(per: dict[str, dict[tuple, dict]], strategy: str, baseline: str) -> dict[str, Any]:
    """Areas, paired tests against ``baseline`` and questions to reach its last concordance."""
    keys = sorted(set(per[strategy]) & set(per[baseline]))
    mine, base = [per[strategy][k] for k in keys], [per[baseline][k] for k in keys]
    out: dict[str, Any] = {"twins": len(keys)}
    for m in METRICS:
        a, b = [_area(r[m]) for r in mine], [_area(r[m]) for r in base]
        out[m] = {"area": statistics.fmean(a)}
        if strategy != baseline:
            out[m].update(paired_tests(a, b))
    Q = len(base[0]["concordance"]) - 1
    reach = [_reach(r["concordance"], b["concordance"][Q]) for r, b in zip(mine, base)]
    mean_mine = [statistics.fmean(r["concordance"][k] for r in mine) for k in range(Q + 1)]
    out["reach"] = {
        "target_questions": Q,
        "median": statistics.median(reach),
        "not_within": sum(k > Q for k in reach),
        "mean_curve": _reach(mean_mine, statistics.fmean(b["concordance"][Q] for b in base)),
        "baseline_final": statistics.fmean(b["concordance"][Q] for b in base),
    }
    out["fraction_ratings"] = statistics.fmean(k == "rating" for r in mine for k in r["kinds"])
    return out


def _verdicts(per: dict[str, dict[tuple, dict]], budget: float) -> dict[str, Any]:
    """At ``budget`` seconds: per metric the means, the best strategy and each one's status."""
    strategies = list(per)
    keys = sorted(set.intersection(*(set(v) for v in per.values())))
    out: dict[str, Any] = {}
    for m in METRICS:
        vals = {s: [at_seconds(per[s][k], m, [budget])[0] for k in keys] for s in strategies}
        means = {s: statistics.fmean(v) for s, v in vals.items()}
        sign = -1.0 if m in SMALLER else 1.0
        best = max(strategies, key=lambda s: sign * means[s])
        status = {}
        for s in strategies:
            p = math.nan if s == best else paired_tests(vals[s], vals[best])["p_wilcoxon"]
            status[s] = "best" if s == best else ("tied" if math.isnan(p) or p > ALPHA else "worse")
        out[m] = {"best": best, "mean": means, "status": status}
    return out


def summarise(rows: Sequence[dict], baseline: str) -> dict[str, Any]:
    """Per effort model, data set and condition: each strategy against ``baseline`` and the
    verdicts at equal seconds; per effort model and strategy the count of best-or-tied cells."""
    out: dict[str, Any] = {}
    for effort in EFFORTS:
        cells = _cells(rows, effort)
        if not cells:
            continue
        entry: dict[str, Any] = {"cells": {}, "best_or_tied": {}}
        for (ds, cond), per in sorted(cells.items()):
            if baseline not in per:
                continue
            budgets = [round(EFFORTS[effort].rating() * q, 9) for q in BUDGET_RATINGS]
            entry["cells"][f"{ds}/{cond}"] = {
                "strategies": {s: _against(per, s, baseline) for s in per},
                "equal_seconds": {f"{b:g} s": _verdicts(per, b) for b in budgets},
            }
        for cell in entry["cells"].values():
            for verdict in cell["equal_seconds"].values():
                for v in verdict.values():
                    for s, status in v["status"].items():
                        n, t = entry["best_or_tied"].get(s, (0, 0))
                        entry["best_or_tied"][s] = (n + (status != "worse"), t + 1)
        out[effort] = entry
    return out


def curves(rows: Sequence[dict], effort: str, step: float) -> list[dict]:
    """Mean and standard error of each metric per question count and per ``step`` seconds."""
    out = []
    for (ds, cond), per in sorted(_cells(rows, effort).items()):
        top = min(rp["cost"][-1] for recs in per.values() for r in recs.values() for rp in r.get("repeats") or [r])
        grid = [step * i for i in range(int(top // step) + 1)]
        for s, recs in per.items():
            rs = list(recs.values())
            for axis, xs in (("questions", list(range(len(rs[0]["concordance"])))), ("seconds", grid)):
                cols = {}
                for m in METRICS:
                    vals = [r[m] if axis == "questions" else at_seconds(r, m, grid) for r in rs]
                    cols[m] = mean_sem(vals)
                for i, x in enumerate(xs):
                    row = dict(dataset=ds, condition=cond, effort=effort, strategy=s, axis=axis, x=x, twins=len(rs))
                    for m in METRICS:
                        row[f"{m}_mean"], row[f"{m}_sem"] = cols[m][0][i], cols[m][1][i]
                    out.append(row)
    return out


def plot(table: Sequence[dict], path: Path, effort: str = "plain") -> None:
    """Concordance against questions and against seconds (``effort``), one line per strategy; one
    row of panels per data set and condition."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = sorted({(r["dataset"], r["condition"]) for r in table if r["effort"] == effort})
    fig, axes = plt.subplots(len(groups), 2, figsize=(11, 3.2 * len(groups)), squeeze=False)
    for i, (ds, cond) in enumerate(groups):
        for j, axis in enumerate(("questions", "seconds")):
            ax = axes[i][j]
            here = [
                r for r in table if (r["dataset"], r["condition"], r["effort"], r["axis"]) == (ds, cond, effort, axis)
            ]
            for s in dict.fromkeys(r["strategy"] for r in here):
                pts = [r for r in here if r["strategy"] == s]
                ax.plot([r["x"] for r in pts], [r["concordance_mean"] for r in pts], label=s, lw=1.4)
            ax.set_title(f"{ds}, {cond}: concordance", fontsize=9)
            ax.set_xlabel("questions" if axis == "questions" else f"seconds ({effort} effort model)")
            ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def report(rows: Sequence[dict], out: Path, meta: dict, baseline: str) -> list[str]:
    """Write ``twins.json`` (stamped: meta and summary), ``twins.csv`` (the curves) and
    ``twins.png``, ``twins_trajectories.png``; return the lines to print."""
    summary = summarise(rows, baseline)
    write_json(out / "twins.json", {"meta": meta, "baseline": baseline, "summary": summary})
    table = [r for e, step in (("plain", 2.0), ("trajectories", 10.0)) for r in curves(rows, e, step)]
    if table:
        with (out / "twins.csv").open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(table[0]))
            w.writeheader()
            w.writerows(table)
        plot(table, out / "twins.png", "plain")
        plot(table, out / "twins_trajectories.png", "trajectories")
    return summary_lines(summary, baseline)


def summary_lines(summary: dict[str, Any], baseline: str) -> list[str]:
    """Area under concordance against ``baseline`` (p) and questions to reach its final concordance."""
    lines = []
    for effort, entry in summary.items():
        lines.append(f"[{effort}] best or tied at equal seconds: " + ", ".join(f"{s} {n}/{t}" for s, (n, t) in entry["best_or_tied"].items()))  # fmt: skip
        for cell, e in entry["cells"].items():
            lines.append(f"  {cell}")
            for s, v in e["strategies"].items():
                c, r = v["concordance"], v["reach"]
                p = f"{c['mean_diff']:+.4f} p={c['p_wilcoxon']:.2g}" if "p_wilcoxon" in c else "(baseline)"
                lines.append(
                    f"    {s:26s} area {c['area']:.4f} {p}; reaches {baseline}'s {r['target_questions']}-question "
                    f"concordance in {r['median']:g} (median; {r['not_within']} not within), ratings {v['fraction_ratings']:.0%}"
                )
    return lines
