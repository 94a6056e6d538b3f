r"""What an experiment reports: curves over trials, paired tests, files and figures.

Results of a run are a list with one entry per trial, ``{strategy: record}``, a record holding
one list per metric (a value before the first query and after each), ``"cost"`` (the cumulative
effort, same length) and ``"kinds"`` (the kind of each query). :func:`curves` turns them into mean
± standard-error curves per query count or per unit of effort (:func:`at_budgets`);
:func:`paired_tests` compares two strategies trial by trial (Wilcoxon signed-rank and paired t,
SciPy); :func:`write_experiment_files` writes the JSON, CSV and PNG files of a run.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import torch


def mean_sem(values: Sequence[Sequence[float]]) -> tuple[list[float], list[float]]:
    r"""Mean and standard error (``std / sqrt(n)``, ``ddof = 1``) over trials.

    NaN entries are missing values (e.g. a metric a trial could not take): each point's mean and
    standard error use its trials with a value (a point with none has mean 0).

    Args:
        values: ``trials x points`` (e.g. one metric curve per trial).

    Returns:
        ``(mean, sem)``, each a list with one value per point (``sem`` 0 with fewer than two
        values).
    """
    t = torch.as_tensor(values, dtype=torch.float64)
    if t.dim() != 2 or t.shape[0] == 0:
        raise ValueError(f"values must be trials x points with at least one trial, got shape {tuple(t.shape)}.")
    ok = ~torch.isnan(t)
    if ok.all():
        n = t.shape[0]
        sem = t.std(dim=0, correction=1) / math.sqrt(n) if n > 1 else torch.zeros(t.shape[1], dtype=t.dtype)
        return t.mean(dim=0).tolist(), sem.tolist()
    counts = ok.sum(0).clamp_min(1)
    m = torch.where(ok, t, 0).sum(0) / counts
    var = torch.where(ok, (t - m).pow(2), 0).sum(0) / (counts - 1).clamp_min(1)
    sem = torch.where(counts > 1, var.sqrt() / counts.sqrt(), torch.zeros_like(m))
    return m.tolist(), sem.tolist()


def fraction_ratings(results: Sequence[dict[str, Any]], strategies: Sequence[str]) -> dict[str, float]:
    """Per strategy, the share of its queries (``result[strategy]["kinds"]``) that were ratings."""
    return {
        s: sum(k == "rating" for r in results for k in r[s]["kinds"]) / max(1, sum(len(r[s]["kinds"]) for r in results))
        for s in strategies
    }


def paired_tests(a: Sequence[float], b: Sequence[float]) -> dict[str, float]:
    r"""Paired comparison of two strategies' per-trial values (same trials, same order).

    Returns:
        ``mean_diff`` (``a - b``), its standard error ``sem_diff``, the paired t-test's
        ``t`` and two-sided ``p_ttest``, the Wilcoxon signed-rank ``p_wilcoxon`` (two-sided,
        zero differences dropped; NaN when all differences are zero), and ``wins`` / ``losses``
        / ``ties``: trials where ``a`` is larger / smaller / equal.
    """
    from scipy import stats

    x = torch.as_tensor(a, dtype=torch.float64)
    y = torch.as_tensor(b, dtype=torch.float64)
    if x.shape != y.shape or x.dim() != 1 or x.numel() < 2:
        raise ValueError(
            f"a and b must be paired 1-D samples of equal length >= 2, got shapes "
            f"{tuple(x.shape)} and {tuple(y.shape)}."
        )
    d = (x - y).numpy()
    out = {
        "n": int(d.size),
        "mean_diff": float(d.mean()),
        "sem_diff": float(d.std(ddof=1) / math.sqrt(d.size)),
        "wins": int((d > 0).sum()),
        "losses": int((d < 0).sum()),
        "ties": int((d == 0).sum()),
    }
    if (d == 0).all():
        out.update(t=float("nan"), p_ttest=float("nan"), p_wilcoxon=float("nan"))
        return out
    tt = stats.ttest_rel(x.numpy(), y.numpy())
    out["t"], out["p_ttest"] = float(tt.statistic), float(tt.pvalue)
    # exact for small samples without ties or zeros, else the normal approximation with the tie
    # correction (SciPy's default would fall back on a permutation test: seconds per call)
    nz = d[d != 0]
    exact = nz.size <= 50 and len(set(abs(nz).tolist())) == nz.size
    out["p_wilcoxon"] = float(stats.wilcoxon(d, zero_method="wilcox", method="exact" if exact else "approx").pvalue)
    return out


def at_budgets(values: Sequence[float], cost: Sequence[float], budgets: Sequence[float]) -> list[float]:
    """A trial's metric after the last query whose cumulative ``cost`` (``values``' length, 0
    first) is within each budget."""
    out, j = [], 0
    for b in budgets:
        while j + 1 < len(cost) and cost[j + 1] <= b + 1e-9:
            j += 1
        out.append(values[j])
    return out


def effort_budgets(results: Sequence[dict[str, Any]], strategies: Sequence[str]) -> list[float]:
    """The whole-number budgets ``0, 1, ...`` up to the least effort any trial of any strategy spent."""
    max_budget = min(r[s]["cost"][-1] for r in results for s in strategies)
    return [float(b) for b in range(int(math.floor(max_budget)) + 1)]


def curves(
    results: Sequence[dict[str, Any]],
    strategies: Sequence[str],
    metrics: Sequence[str],
    budgets: Sequence[float] | None = None,
) -> dict[str, dict[str, list[float]]]:
    r"""Mean ± standard error of each metric over trials, per query count or per effort budget.

    Args:
        results: one ``{strategy: record}`` per trial.
        strategies: the strategies to summarise.
        metrics: the record keys to summarise.
        budgets: ``None``: per query count (the records' own points); else the value after the
            last query within each budget (:func:`at_budgets`).

    Returns:
        ``{strategy: {"<metric>_mean": [...], "<metric>_sem": [...]}}``.
    """
    out = {}
    for s in strategies:
        entry = {}
        for k in metrics:
            rows = [r[s][k] if budgets is None else at_budgets(r[s][k], r[s]["cost"], budgets) for r in results]
            entry[f"{k}_mean"], entry[f"{k}_sem"] = mean_sem(rows)
        out[s] = entry
    return out


def final_values(
    per_point: dict[str, dict[str, list[float]]], metrics: Sequence[str]
) -> dict[str, dict[str, list[float]]]:
    """``{strategy: {metric: [mean, sem]}}`` at the last point of :func:`curves`' output."""
    return {s: {k: [v[f"{k}_mean"][-1], v[f"{k}_sem"][-1]] for k in metrics} for s, v in per_point.items()}


# ---------------------------------------------------------------------------------- files
def write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write ``obj`` as indented JSON (creating the folder); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=2) + "\n")
    return path


def write_summary_csv(
    path: str | os.PathLike, summary: dict[str, dict[str, list[float]]], x_name: str = "queries"
) -> Path:
    r"""Long-format CSV, one row per (strategy, point): ``strategy, x_name, <column>...``.

    Args:
        summary: ``{strategy: {column: [value per point]}}``, all columns of equal length.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    columns = sorted({c for cols in summary.values() for c in cols})
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["strategy", x_name, *columns])
        for name, cols in summary.items():
            n = len(next(iter(cols.values())))
            for i in range(n):
                w.writerow([name, i, *(repr(float(cols[c][i])) if c in cols else "" for c in columns)])
    return path


def plot_mean_sem(
    path: str | os.PathLike,
    panels: Iterable[tuple[str, dict[str, tuple[Sequence[float], Sequence[float], Sequence[float]]]]],
    xlabel: str = "number of queries",
    title: str | None = None,
) -> Path:
    r"""One row of panels of mean curves with ± standard-error bands.

    Args:
        path: the image file (format from its suffix).
        panels: ``(ylabel, {strategy: (x, mean, sem)})`` per panel.
        xlabel: the shared x-axis label.
        title: an optional figure title.
    """
    from torchpref.extras import require

    matplotlib = require("matplotlib", "drawing an experiment's curves")
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    panels = list(panels)
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 4.0), squeeze=False)
    for ax, (ylabel, curves) in zip(axes[0], panels):
        for name, (x, mean, sem) in curves.items():
            x_t, m_t, s_t = (torch.as_tensor(v, dtype=torch.float64) for v in (x, mean, sem))
            (line,) = ax.plot(x_t.numpy(), m_t.numpy(), label=name, lw=1.6)
            ax.fill_between(x_t.numpy(), (m_t - s_t).numpy(), (m_t + s_t).numpy(), color=line.get_color(), alpha=0.2)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def write_experiment_files(
    out: str | os.PathLike,
    name: str,
    result: dict[str, Any],
    summary: dict[str, Any],
    figures: dict[str, dict[str, Any]],
    effort: dict[str, Any] | None = None,
) -> None:
    r"""Write a run's files into ``out``: ``<name>.json`` (``result``), ``<name>.csv`` (its
    per-query curves, ``result["strategies"]``, long format), ``<name>_summary.json``
    (``summary``), ``<name>_effort.csv`` (the per-effort curves ``effort``, if given) and one
    PNG per entry of ``figures`` (``{file name: keyword arguments of plot_mean_sem}``)."""
    out = Path(out)
    write_json(out / f"{name}.json", result)
    write_summary_csv(out / f"{name}.csv", result["strategies"], x_name="queries")
    if effort is not None:
        write_summary_csv(out / f"{name}_effort.csv", effort, x_name="effort")
    write_json(out / f"{name}_summary.json", summary)
    for file_name, kwargs in figures.items():
        plot_mean_sem(out / file_name, **kwargs)


def metric_panels(
    per_point: dict[str, dict[str, list[float]]], x: Sequence[float], labels: dict[str, str]
) -> list[tuple[str, dict[str, tuple]]]:
    """``plot_mean_sem``'s panels: one per metric of ``labels`` (``{metric: y label}``), one
    curve per strategy of :func:`curves`' output against ``x``."""
    return [
        (label, {s: (x, v[f"{k}_mean"], v[f"{k}_sem"]) for s, v in per_point.items()}) for k, label in labels.items()
    ]
