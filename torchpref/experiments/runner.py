r"""A generic trial runner and the statistics, files and figures of an experiment.

:func:`run_trials` maps a picklable, module-level ``trial_fn`` over a list of argument tuples
with any :class:`concurrent.futures.Executor`: by default a ``ProcessPoolExecutor``; for a
large sweep, a cluster's executor works unchanged, e.g.

.. code-block:: python

    from dask.distributed import Client           # optional, not a torchpref requirement
    executor = Client("scheduler:8786").get_executor()
    run_wave_experiment(trials=10_000, executor=executor)

    from ray.util.multiprocessing import Pool      # Ray: its Pool, or any Executor adapter
    ...

A trial function should call :func:`single_threaded` first: tiny linear algebra runs fastest
on one thread per process, and the setting belongs to the worker, not to an import.

The summaries are per query count (``mean`` and standard error over trials), paired tests
(Wilcoxon signed-rank and paired t, SciPy) compare two strategies trial by trial.
"""

from __future__ import annotations

import csv
import json
import math
import os
from concurrent.futures import Executor, ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import torch
from gpytorch.kernels import Kernel
from torch import Tensor


def single_threaded() -> None:
    """Make the calling process use one intra-op thread (call inside a trial function)."""
    if torch.get_num_threads() != 1:
        torch.set_num_threads(1)


def default_workers() -> int:
    """Worker processes to use by default: the CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def run_trials(
    trial_fn: Callable[..., Any],
    trial_args_list: Sequence[tuple],
    executor: Executor | None = None,
    progress: bool = True,
    *,
    workers: int | None = None,
    description: str = "trials",
    sizes: Sequence[int] | None = None,
) -> list[Any]:
    r"""Run ``trial_fn(*args)`` for every ``args`` in ``trial_args_list``; results in input order.

    Args:
        trial_fn: a module-level (picklable) function.
        trial_args_list: one tuple of arguments per trial.
        executor: any ``concurrent.futures.Executor`` (a process pool, a Dask client's
            ``get_executor()``, ...). ``None``: a ``ProcessPoolExecutor`` with ``workers``
            processes, shut down afterwards; with ``workers=1`` the trials run in this process.
        progress: show a ``tqdm`` bar over completed trials.
        workers: processes of the default pool (default :func:`default_workers`).
        description: the progress bar's label.
        sizes: how many trials each call runs (for the progress bar; default 1 each).

    Returns:
        ``[trial_fn(*args) for args in trial_args_list]``.
    """
    args_list = [tuple(a) for a in trial_args_list]
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers}.")
    sizes = [1] * len(args_list) if sizes is None else list(sizes)
    if len(sizes) != len(args_list):
        raise ValueError(f"sizes must have one entry per call ({len(args_list)}), got {len(sizes)}.")
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=sum(sizes), desc=description, unit="trial")
    results: list[Any] = [None] * len(args_list)
    try:
        if executor is None and (workers or default_workers()) == 1:
            for i, a in enumerate(args_list):
                results[i] = trial_fn(*a)
                if bar is not None:
                    bar.update(sizes[i])
            return results
        own = executor is None
        ex = ProcessPoolExecutor(max_workers=workers or default_workers()) if own else executor
        try:
            futures = {ex.submit(trial_fn, *a): i for i, a in enumerate(args_list)}
            for fut in as_completed(futures):
                i = futures[fut]
                results[i] = fut.result()
                if bar is not None:
                    bar.update(sizes[i])
        finally:
            if own:
                ex.shutdown(cancel_futures=True)
        return results
    finally:
        if bar is not None:
            bar.close()


# ------------------------------------------------------------------------------ statistics
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
    n = ok.sum(0).clamp_min(1)
    m = torch.where(ok, t, 0).sum(0) / n
    var = torch.where(ok, (t - m).pow(2), 0).sum(0) / (n - 1).clamp_min(1)
    sem = torch.where(n > 1, var.sqrt() / n.sqrt(), torch.zeros_like(m))
    return m.tolist(), sem.tolist()


def fraction_ratings(results: Sequence[dict[str, Any]], strategies: Sequence[str]) -> dict[str, float]:
    """Per strategy, the share of its queries (``result[strategy]["kinds"]``) that were ratings."""
    return {s: sum(k == "rating" for r in results for k in r[s]["kinds"])
            / max(1, sum(len(r[s]["kinds"]) for r in results)) for s in strategies}


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
        raise ValueError(f"a and b must be paired 1-D samples of equal length >= 2, got shapes "
                         f"{tuple(x.shape)} and {tuple(y.shape)}.")
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
    out["p_wilcoxon"] = float(stats.wilcoxon(d, zero_method="wilcox").pvalue)
    return out


# ---------------------------------------------------------------------------------- files
def write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write ``obj`` as indented JSON (creating the folder); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=2) + "\n")
    return path


def write_summary_csv(path: str | os.PathLike, summary: dict[str, dict[str, list[float]]],
                      x_name: str = "queries") -> Path:
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
    import matplotlib

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


def trial_seeds(seed: int, trials: int) -> list[int]:
    """``trials`` per-trial seeds derived from a run's ``seed``."""
    if trials < 1:
        raise ValueError(f"trials must be a positive integer, got {trials}.")
    g = torch.Generator().manual_seed(int(seed))
    return torch.randint(0, 2**62, (trials,), generator=g).tolist()


class FixedRBFKernel(Kernel):
    r"""``outputscale * exp(-|x - x'|^2 / (2 lengthscale^2))`` with fixed (buffer) hyperparameters.

    The values of ``ScaleKernel(RBFKernel())`` with the same lengthscale and outputscale, computed
    by the same operations (GPyTorch's centred quadratic expansion, so the results are the same to
    the last bit), without the constraint transforms, autograd function and sub-modules that cost
    most of a small kernel evaluation's time. For experiments that never fit the hyperparameters;
    ``outputscale`` and ``base_kernel.lengthscale`` read and set the values as on a ``ScaleKernel``.

    Args:
        lengthscale: the (scalar) lengthscale.
        outputscale: the kernel variance ``sigma_f^2``.
    """

    def __init__(self, lengthscale: float | Tensor, outputscale: float | Tensor):
        super().__init__()
        ls, os_ = (torch.as_tensor(v) for v in (lengthscale, outputscale))
        dtype = ls.dtype if ls.is_floating_point() else torch.get_default_dtype()
        self.register_buffer("lengthscale_value", ls.to(dtype).reshape(1, 1))
        self.register_buffer("outputscale_value", os_.to(dtype).reshape(()))

    # ``ScaleKernel(RBFKernel())``'s attribute names, so code written for that kernel can read and
    # set the values: ``k.outputscale``, ``k.base_kernel.lengthscale`` (the kernel itself).
    @property
    def base_kernel(self) -> "FixedRBFKernel":
        """The kernel itself, so ``kernel.base_kernel.lengthscale`` reads as for ``ScaleKernel(RBFKernel())``."""
        return self

    @property
    def lengthscale(self) -> Tensor:
        """The fixed lengthscale (``1 x 1``)."""
        return self.lengthscale_value

    @lengthscale.setter
    def lengthscale(self, value: float | Tensor) -> None:
        self.lengthscale_value = torch.as_tensor(value).to(self.lengthscale_value).reshape(1, 1)

    @property
    def outputscale(self) -> Tensor:
        """The fixed kernel variance ``sigma_f^2`` (a scalar)."""
        return self.outputscale_value

    @outputscale.setter
    def outputscale(self, value: float | Tensor) -> None:
        self.outputscale_value = torch.as_tensor(value).to(self.outputscale_value).reshape(())

    def forward(self, x1: Tensor, x2: Tensor, diag: bool = False, last_dim_is_batch: bool = False, **params) -> Tensor:
        if last_dim_is_batch:
            raise NotImplementedError("FixedRBFKernel does not support last_dim_is_batch.")
        x1 = x1.div(self.lengthscale_value)
        x2 = x2.div(self.lengthscale_value)
        if diag:
            if torch.equal(x1, x2):
                return self.outputscale_value.expand(*x1.shape[:-1]).clone()
            return torch.linalg.norm(x1 - x2, dim=-1).pow(2).div_(-2.0).exp_().mul_(self.outputscale_value)
        same = torch.equal(x1, x2) and not (x1.requires_grad or x2.requires_grad)
        adjustment = x1.mean(-2, keepdim=True)  # gpytorch.kernels.kernel.sq_dist, step by step
        x1 = x1 - adjustment
        x1_norm = x1.pow(2).sum(dim=-1, keepdim=True)
        x1_pad = torch.ones_like(x1_norm)
        if same:
            x2, x2_norm, x2_pad = x1, x1_norm, x1_pad
        else:
            x2 = x2 - adjustment
            x2_norm = x2.pow(2).sum(dim=-1, keepdim=True)
            x2_pad = torch.ones_like(x2_norm)
        res = torch.cat([-2.0 * x1, x1_norm, x1_pad], dim=-1).matmul(torch.cat([x2, x2_pad, x2_norm], dim=-1).mT)
        if same:
            res.diagonal(dim1=-2, dim2=-1).fill_(0)
        return res.clamp_min_(0).div_(-2.0).exp_().mul(self.outputscale_value)


def fixed_model(X: torch.Tensor, comparisons: torch.Tensor, settings: dict[str, float]):
    """A :class:`~torchpref.PreferenceGP` with fixed hyperparameters: ``settings`` holds
    ``lengthscale``, ``outputscale``, ``comparison_noise``, ``rating_scale``, ``rating_precision``.
    The kernel is a :class:`FixedRBFKernel` holding the values a ``ScaleKernel(RBFKernel())`` set to
    the same settings stores (its constraint round trip included)."""
    from gpytorch.kernels import RBFKernel, ScaleKernel

    from torchpref.models import PreferenceGP

    ref = ScaleKernel(RBFKernel())
    ref.base_kernel.lengthscale = settings["lengthscale"]
    ref.outputscale = settings["outputscale"]
    ref = ref.to(X)  # set, then cast: the values (float32 round trip included) the runs have always used
    with torch.no_grad():
        kernel = FixedRBFKernel(ref.base_kernel.lengthscale.detach().clone(), ref.outputscale.detach().clone()).to(X)
    return PreferenceGP(X, comparisons=comparisons, covar_module=kernel,
                        comparison_noise=settings["comparison_noise"], rating_scale=settings["rating_scale"],
                        rating_precision=settings["rating_precision"])
