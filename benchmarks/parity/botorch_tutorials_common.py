"""Shared pieces of the BoTorch tutorial benchmarks (``botorch_tutorials_preference_bo.py``,
``botorch_tutorials_bope.py``): the two models' construction and MLL lines (the only lines that
differ between the two runs), a resumable per-seed record, the paired test and the summary."""

from __future__ import annotations

import hashlib
import json
import math
import time
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch
from botorch.fit import fit_gpytorch_mll
from botorch.models.pairwise_gp import PairwiseGP, PairwiseLaplaceMarginalLogLikelihood
from botorch.models.transforms.input import Normalize
from scipy import stats

from torchpref.models.preference_gp import LaplaceMarginalLogLikelihood, PreferenceGP

MODELS = ("PairwiseGP", "PreferenceGP")
RESULTS = Path(__file__).resolve().parents[1] / "results"


def fit_preference_model(name: str, X: torch.Tensor, comps: torch.Tensor, **model_kwargs):
    """The tutorials' ``init_and_fit_model`` / ``fit_pref_model``: the construction and MLL lines
    are the only ones that depend on ``name``."""
    with phase("preference_fit"):
        if name == "PairwiseGP":
            model = PairwiseGP(X, comps, input_transform=Normalize(d=X.shape[-1]))
            mll = PairwiseLaplaceMarginalLogLikelihood(model.likelihood, model)
        else:
            model = PreferenceGP(X, comps, input_transform=Normalize(d=X.shape[-1]), **model_kwargs)
            mll = LaplaceMarginalLogLikelihood(model)
        fit_gpytorch_mll(mll)
    return model


def seed_all(seed: int) -> None:
    """The tutorials seed torch's and NumPy's global generators."""
    torch.manual_seed(seed)
    np.random.seed(seed)


def code_fingerprint() -> str:
    """A digest of the code of every ``torchpref`` module and of these scripts (their syntax trees, as
    the stamps hash them): a record resumes only the rows this code measured, so the results file's
    stamp never covers rows that older code measured."""
    from torchpref.experiments.stamp import ROOT, code_digest

    here = Path(__file__).resolve().parent
    files = sorted([*(ROOT / "torchpref").rglob("*.py"), *here.glob("botorch_tutorials_*.py")])
    digest = hashlib.sha256()
    for f in files:
        digest.update(f"{f.relative_to(ROOT).as_posix()}:{code_digest(f)}\n".encode())
    return digest.hexdigest()


class Record:
    """One JSON line per finished ``(seed, model)`` run, so a long run can be resumed or extended: rows
    of the same settings measured on the same code (:func:`code_fingerprint`); others are left in the
    file and not read."""

    def __init__(self, path: Path, config: dict):
        self.path, self.config = path, {**config, "code": code_fingerprint()}
        self.rows = []
        if path.exists():
            for line in path.read_text().splitlines():
                row = json.loads(line)
                if row.get("config") == self.config:
                    self.rows.append(row)

    def done(self, seed: int, model: str) -> bool:
        return any(r["seed"] == seed and r["model"] == model for r in self.rows)

    def add(self, row: dict) -> None:
        row = {**row, "config": self.config}
        self.rows.append(row)
        with self.path.open("a") as f:
            f.write(json.dumps(row) + "\n")


#: wall and CPU seconds per named phase of the running trial (``phase``), reset by ``timed``
PHASES: dict[str, float] = {}
PHASES_CPU: dict[str, float] = {}


@contextmanager
def phase(name: str):
    """Add the wall and CPU time of the ``with`` block to ``PHASES[name]`` / ``PHASES_CPU[name]``
    (where a loop spends its time; the CPU time is robust to load from other processes)."""
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        yield
    finally:
        PHASES[name] = PHASES.get(name, 0.0) + time.perf_counter() - t0
        PHASES_CPU[name] = PHASES_CPU.get(name, 0.0) + time.process_time() - c0


def timed(fn: Callable[[], dict]) -> dict:
    """Run one trial; add its wall time, its CPU time (this process, one thread: the work done
    rather than the waiting on a loaded machine) and the wall and CPU time per ``phase``."""
    PHASES.clear()
    PHASES_CPU.clear()
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return {
        **out,
        "wall_s": time.perf_counter() - t0,
        "cpu_s": time.process_time() - c0,
        "phase_s": dict(PHASES),
        "phase_cpu_s": dict(PHASES_CPU),
    }


def paired_summary(rows: list[dict], key: str, higher_is_better: bool) -> dict:
    """Paired comparison over the seeds both models finished: PreferenceGP minus PairwiseGP.

    ``p_worse`` is the one-sided paired t-test p-value for "PreferenceGP is worse"; ``p_wilcoxon``
    the same hypothesis by the signed-rank test. "Not worse at p < 0.05" means ``p_worse >= 0.05``.
    """
    by = {m: {r["seed"]: r for r in rows if r["model"] == m} for m in MODELS}
    seeds = sorted(set(by["PairwiseGP"]) & set(by["PreferenceGP"]))
    a = np.array([by["PreferenceGP"][s][key] for s in seeds], dtype=float)
    b = np.array([by["PairwiseGP"][s][key] for s in seeds], dtype=float)
    tw = np.array([by["PairwiseGP"][s]["wall_s"] for s in seeds])
    ow = np.array([by["PreferenceGP"][s]["wall_s"] for s in seeds])
    diff = (a - b) if higher_is_better else (b - a)  # > 0: PreferenceGP better
    out = {
        "seeds": seeds,
        "n": len(seeds),
        "metric": key,
        "PreferenceGP_mean": _mean(a),
        "PairwiseGP_mean": _mean(b),
        "PreferenceGP_sem": _sem(a),
        "PairwiseGP_sem": _sem(b),
        "wall_s_PairwiseGP": float(tw.sum()),
        "wall_s_PreferenceGP": float(ow.sum()),
        "wall_time_ratio": float(tw.sum() / ow.sum()) if len(seeds) else math.nan,
    }
    if all("cpu_s" in by[m][s] for m in MODELS for s in seeds) and seeds:
        tc = sum(by["PairwiseGP"][s]["cpu_s"] for s in seeds)
        oc = sum(by["PreferenceGP"][s]["cpu_s"] for s in seeds)
        out.update({"cpu_s_PairwiseGP": tc, "cpu_s_PreferenceGP": oc, "cpu_time_ratio": tc / oc})
    if len(seeds) >= 2 and np.any(diff != 0):
        out["p_worse"] = float(stats.ttest_1samp(diff, 0.0, alternative="less").pvalue)
        out["p_wilcoxon"] = float(stats.wilcoxon(diff, alternative="less").pvalue)
    else:
        out["p_worse"] = out["p_wilcoxon"] = math.nan if len(seeds) < 2 else 1.0
    return out


def phase_summary(rows: list[dict]) -> dict:
    """Per model, the CPU seconds of each ``phase`` summed over the seeds, the whole loop's CPU
    seconds and each phase's share of it (rows without phase times are left out)."""
    out = {}
    for m in MODELS:
        rs = [r for r in rows if r["model"] == m and "phase_cpu_s" in r]
        total = sum(r["cpu_s"] for r in rs)
        phases = {k: sum(r["phase_cpu_s"].get(k, 0.0) for r in rs) for r in rs for k in r["phase_cpu_s"]}
        out[m] = {
            "seeds": len(rs),
            "cpu_s": total,
            "phase_cpu_s": phases,
            "share": {k: v / total for k, v in phases.items()} if total else {},
        }
    return out


def errorbar_curve(ax, x, ys: np.ndarray, **kwargs) -> None:
    """Mean of the ``seeds x points`` curves ``ys`` with a 95% confidence band of the mean."""
    sem = ys.std(0, ddof=1) / np.sqrt(len(ys)) if len(ys) > 1 else 0 * ys.mean(0)
    ax.errorbar(x, ys.mean(0), yerr=1.96 * sem, capsize=2, **kwargs)


def plot_curves(
    rows: list[dict],
    arms,
    key: str,
    x_of: Callable[[int], np.ndarray],
    path,
    *,
    xlabel: str,
    ylabel: str,
    title: str,
    optimum: float | None = None,
) -> None:
    """One curve per model (line style) and arm: the rows' ``key.format(arm)`` lists against
    ``x_of(length)``, mean with a 95% band over the seeds; the number of seeds ends ``title``."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name, style in zip(MODELS, ("-", "--")):
        for arm in arms:
            ys = np.array([r[key.format(arm)] for r in rows if r["model"] == name])
            if len(ys):
                errorbar_curve(ax, x_of(ys.shape[1]), ys, ls=style, label=f"{name} {arm}")
    if optimum is not None:
        ax.axhline(optimum, color="k", lw=1, label="optimum")
    ax.set(xlabel=xlabel, ylabel=ylabel, title=f"{title}, {len({r['seed'] for r in rows})} seeds (mean, 95% CI)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _mean(x):
    return float(np.mean(x)) if len(x) else math.nan


def _sem(x):
    return float(np.std(x, ddof=1) / np.sqrt(len(x))) if len(x) > 1 else math.nan
