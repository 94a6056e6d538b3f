r"""The experiment skeleton: the strategy registry, seeds, the trial runner and the command line.

Every experiment (:mod:`~torchpref.experiments.wave`, :mod:`~torchpref.experiments.lake`,
:mod:`~torchpref.experiments.suite`) is built from the same pieces:

* :func:`make_selector`: a strategy by name from one registry (:data:`STRATEGIES`), with the
  experiment's ``m`` (items per ranking) and ``gamma`` (eq. 12);
* :func:`make_model`: a :class:`~torchpref.PreferenceGP` with fixed hyperparameters from a
  settings dict (a :class:`~torchpref.models.kernels.FixedRBFKernel`);
* :func:`trial_seeds`: the per-trial seeds of a run;
* :func:`run_trials`: maps a picklable, module-level ``trial_fn`` over argument tuples with any
  :class:`concurrent.futures.Executor`; :func:`run_by_strategy` runs batches of trials of one
  strategy each (a batched model, :class:`~torchpref.BatchedPreferenceGP`) and gathers them per
  trial;
* :func:`check_run` validates a run's arguments, :func:`run_cli` is the ``torchpref reproduce
  NAME`` command of any experiment whose summary has ``final`` and ``wall_time_s``.

Statistics, files and figures are in :mod:`torchpref.experiments.results`. By default trials run
on a ``ProcessPoolExecutor``; for a large sweep, a cluster's executor works unchanged, e.g.

.. code-block:: python

    from dask.distributed import Client           # optional, not a torchpref requirement
    executor = Client("scheduler:8786").get_executor()
    run_wave_experiment(trials=10_000, executor=executor)

A trial function should call :func:`single_threaded` first: tiny linear algebra runs fastest
on one thread per process, and the setting belongs to the worker, not to an import.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor, as_completed
from typing import Any

import torch
from torch import Tensor

from torchpref.models.kernels import fixed_rbf_kernel
from torchpref.models.preference_gp import PreferenceGP
from torchpref.selection.combined import InformationAndProfile
from torchpref.selection.defaults import default_selector
from torchpref.selection.eubo import ExpectedBestOption
from torchpref.selection.per_second import ProfilePerSecond
from torchpref.selection.robust import EpsilonExplore
from torchpref.selection.strategies import (
    UCBC,
    InformationPerEffort,
    RandomMixed,
    RandomRankings,
    RandomRatings,
    Selector,
    UCBRatings,
)
from torchpref.selection.top_profile import ProfileVariancePerEffort
from torchpref.selection.variance_reduction import VariancePerEffort


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
    unit: str = "trial",
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
        unit: what the progress bar counts.

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

        bar = tqdm(total=sum(sizes), desc=description, unit=unit)
    results: list[Any] = [None] * len(args_list)

    def done(i: int, result: Any) -> None:
        results[i] = result
        if bar is not None:
            bar.update(sizes[i])

    try:
        if executor is None and (workers or default_workers()) == 1:
            for i, a in enumerate(args_list):
                done(i, trial_fn(*a))
        else:
            own = executor is None
            ex = executor if executor is not None else ProcessPoolExecutor(max_workers=workers or default_workers())
            _run_on(ex, trial_fn, args_list, done, own)
        return results
    finally:
        if bar is not None:
            bar.close()


def _run_on(
    ex: Executor, trial_fn: Callable[..., Any], args_list: list[tuple], done: Callable[[int, Any], None], own: bool
) -> None:
    """Submit every call to ``ex`` and hand each result to ``done(index, result)`` as it completes;
    an ``own`` executor is shut down afterwards, its pending calls cancelled on an error."""
    try:
        futures = {ex.submit(trial_fn, *a): i for i, a in enumerate(args_list)}
        for fut in as_completed(futures):
            done(futures[fut], fut.result())
    finally:
        if own:
            ex.shutdown(cancel_futures=True)


def trial_seeds(seed: int, trials: int) -> list[int]:
    """``trials`` per-trial seeds derived from a run's ``seed``."""
    if trials < 1:
        raise ValueError(f"trials must be a positive integer, got {trials}.")
    g = torch.Generator().manual_seed(int(seed))
    return torch.randint(0, 2**62, (trials,), generator=g).tolist()


# ------------------------------------------------------------------------- the registry
_FACTORIES: dict[str, Callable[..., Selector]] = {
    "UCBC": lambda m, gamma, **_: UCBC(gamma=gamma, m=m),
    "random ratings": lambda **_: RandomRatings(),
    "random rankings": lambda m, **_: RandomRankings(m=m),
    "random mixed": lambda m, **_: RandomMixed(m=m),
    "UCB ratings": lambda gamma, **_: UCBRatings(gamma=gamma),
    "info per effort": lambda m, gamma, rating_cost, ranking_cost: InformationPerEffort(
        m=m, rating_cost=rating_cost, ranking_cost=ranking_cost, gamma=gamma
    ),
    "top & level info": lambda m, gamma, rating_cost, ranking_cost: InformationPerEffort(
        m=m, rating_cost=rating_cost, ranking_cost=ranking_cost, gamma=gamma, target="top+levels"
    ),
    "utility info": lambda m, gamma, rating_cost, ranking_cost: InformationPerEffort(
        m=m, rating_cost=rating_cost, ranking_cost=ranking_cost, gamma=gamma, target="utility"
    ),
    "variance per effort": lambda m, rating_cost, ranking_cost, **_: VariancePerEffort(
        m=m, rating_cost=rating_cost, ranking_cost=ranking_cost
    ),
    "profile per effort": lambda m, rating_cost, ranking_cost, **_: ProfileVariancePerEffort(
        m=m, rating_cost=rating_cost, ranking_cost=ranking_cost
    ),
    "clipped profile": lambda m, rating_cost, ranking_cost, **_: ProfileVariancePerEffort(
        m=m, rating_cost=rating_cost, ranking_cost=ranking_cost, clipped=True
    ),
    "clipped profile + 0.5 random": lambda m, rating_cost, ranking_cost, **_: EpsilonExplore(
        ProfileVariancePerEffort(m=m, rating_cost=rating_cost, ranking_cost=ranking_cost, clipped=True), 0.5
    ),
    "profile per second": lambda m, rating_cost, ranking_cost, **_: ProfilePerSecond(
        m=m, rating_seconds=rating_cost, ranking_seconds=ranking_cost
    ),
    "combination": lambda m, gamma, rating_cost, ranking_cost: InformationAndProfile(
        m=m, rating_cost=rating_cost, ranking_cost=ranking_cost, gamma=gamma
    ),
    "combination (profile)": lambda m, gamma, rating_cost, ranking_cost: InformationAndProfile(
        m=m, rating_cost=rating_cost, ranking_cost=ranking_cost, gamma=gamma, decide="profile"
    ),
    "information + profile": lambda m, gamma, rating_cost, ranking_cost: InformationAndProfile(
        m=m, rating_cost=rating_cost, ranking_cost=ranking_cost, gamma=gamma, decide="sum"
    ),
    "qEUBO": lambda m, gamma, **_: ExpectedBestOption(m=m, gamma=gamma),
    # the sessions' default as shipped (its own costs, whatever a run's effort model): rankings of m
    "default": lambda m, **_: default_selector(m + 1),
}

#: the strategies whose choices do not depend on the costs they are given (the rest weigh effort)
EFFORT_FREE = ("UCBC", "random ratings", "random rankings", "random mixed", "UCB ratings", "qEUBO")

#: every strategy :func:`make_selector` knows, by name
STRATEGIES = tuple(_FACTORIES)


def make_selector(
    name: str, *, m: int = 5, gamma: float = 3.0, rating_cost: float = 1.0, ranking_cost: float | None = None
) -> Selector:
    r"""The selector called ``name`` (one of :data:`STRATEGIES`).

    Args:
        name: the strategy.
        m: items per ranking query.
        gamma: eq. 12's ``gamma`` (UCB-based strategies).
        rating_cost: effort of a rating, as the selector values it (information per effort).
        ranking_cost: effort of a best-of-``m`` ranking, as the selector values it (default
            ``1 + (m - 1) / 4``).

    Raises:
        ValueError: naming an unknown strategy.
    """
    if name not in _FACTORIES:
        raise ValueError(f"unknown strategy {name!r}; choose from {list(STRATEGIES)}.")
    return _FACTORIES[name](m=m, gamma=gamma, rating_cost=rating_cost, ranking_cost=ranking_cost)


def make_model(X: Tensor, comparisons: Tensor, settings: dict[str, float]) -> PreferenceGP:
    """A :class:`~torchpref.PreferenceGP` with fixed hyperparameters: ``settings`` holds
    ``lengthscale``, ``outputscale``, ``comparison_noise``, ``rating_scale``, ``rating_precision``;
    the kernel is :func:`~torchpref.models.kernels.fixed_rbf_kernel`'s."""
    kernel = fixed_rbf_kernel(settings["lengthscale"], settings["outputscale"], X)
    return PreferenceGP(
        X,
        comparisons=comparisons,
        covar_module=kernel,
        comparison_noise=settings["comparison_noise"],
        rating_scale=settings["rating_scale"],
        rating_precision=settings["rating_precision"],
    )


# ------------------------------------------------------------------------- the skeleton
def check_run(
    queries: int, strategies: Sequence[str] | None, default: Sequence[str], batch_size: int | None = None
) -> list[str]:
    """Validate a run's arguments; returns its strategies (``default`` if ``None``)."""
    if not isinstance(queries, int) or queries < 1:
        raise ValueError(f"queries must be a positive integer, got {queries!r}.")
    if batch_size is not None and batch_size < 1:
        raise ValueError(f"batch_size must be a positive integer or None, got {batch_size}.")
    strategies = list(default if strategies is None else strategies)
    for s in strategies:
        if s not in STRATEGIES:
            raise ValueError(f"unknown strategy {s!r}; choose from {list(STRATEGIES)}.")
    return strategies


def run_by_strategy(
    batch_fn: Callable[..., list[dict[str, Any]]],
    seeds: Sequence[int],
    strategies: Sequence[str],
    batch_size: int,
    args: tuple = (),
    *,
    first: Sequence[str] = (),
    **run_kw,
) -> list[dict[str, Any]]:
    r"""Run ``batch_fn(seeds_chunk, *args, strategy)`` for every strategy and chunk of at most
    ``batch_size`` trial seeds (one executor call each, :func:`run_trials`) and gather the
    results per trial.

    Args:
        batch_fn: a module-level function returning one ``{strategy: record}`` per seed.
        seeds: the trial seeds.
        strategies: the strategies.
        batch_size: trials per call.
        args: extra arguments between the seeds and the strategy.
        first: strategies to start first (the costliest: the last calls to finish are then
            short ones).
        **run_kw: :func:`run_trials`' keywords (``executor``, ``workers``, ``progress``,
            ``description``).

    Returns:
        One ``{strategy: record}`` per trial seed, in order.
    """
    order = sorted(strategies, key=lambda s: s not in first)
    starts = [(s, i) for s in order for i in range(0, len(seeds), batch_size)]
    tasks = [(tuple(seeds[i : i + batch_size]), *args, s) for s, i in starts]
    run_kw.setdefault("unit", "trial x strategy")  # each strategy runs every trial
    parts = run_trials(batch_fn, tasks, sizes=[len(t[0]) for t in tasks], **run_kw)
    results: list[dict[str, Any]] = [{} for _ in seeds]
    for (s, i), part in zip(starts, parts):
        place_records(results, i, s, part)
    return results


def place_records(results: list[dict[str, Any]], first: int, strategy: str, part: list[dict[str, Any]]) -> None:
    """Put a call's per-trial records of ``strategy`` (``part``, for trials ``first``, ``first + 1``,
    ...) into ``results``, one ``{strategy: record}`` per trial."""
    for k, r in enumerate(part):
        results[first + k][strategy] = r[strategy]


def run_cli(args: argparse.Namespace, experiment: Callable[..., dict[str, Any]], **kwargs) -> int:
    r"""``torchpref reproduce NAME``: run ``experiment(trials=, queries=, seed=, out=, workers=,
    **kwargs)`` and print where the files went and each strategy's final values."""
    res = experiment(
        trials=args.trials,
        queries=args.queries,
        seed=args.seed,
        out=args.out,
        workers=getattr(args, "workers", None),
        **kwargs,
    )
    s = res["summary"]
    print(f"{args.trials} trials x {args.queries} queries in {s['wall_time_s']:.1f} s; files in {args.out}")
    for name, values in s["final"].items():
        print(
            f"  {name:16s} "
            + "   ".join(f"{k} {m:.4g}" + (f" ± {e:.2g}" if args.trials > 1 else "") for k, (m, e) in values.items())
        )
    return 0
