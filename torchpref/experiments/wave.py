r"""The 1-D experiment of the paper's Fig. 6 (Sec. IV.A): random wave functions, 20 queries.

Each trial draws a wave function (eq. 13), starts every strategy from the same single random
comparison, and asks ``queries`` questions of a simulated user (``sigma_R = 0.05``,
``sigma_B = 0.8``, ``nu = 80``) with 100 fresh uniform candidates per query. The model has the
authors' fixed hyperparameters (lengthscale 0.02, ``sigma_R = 0.2``, ``sigma_B = 0.8``,
``nu = 60``, ``sigma_f = 0.6``, i.e. kernel variance 0.36; see :data:`MODEL_SETTINGS`).
Metrics on 101 evenly spaced points (the authors' grid): WRMS of eq. 14 between the true
rating ``Phi(f / (sigma_B sqrt 2))`` and ``model.expected_rating``, and how many of the true
top-15 points are in the estimated top-15.

Every strategy of a trial sees the same wave function, the same first comparison and the
same candidate draws' seed, so strategies compare trial by trial (paired tests).

The trials of a strategy run in batches (:func:`run_trial_batch`: one
:class:`~torchpref.models.batch.BatchedPreferenceGP` for the batch, one selector call per step for all
its trials), which gives the same questions, answers and metrics as one model at a time
(:func:`run_trial`, ``batch_size=None``) for less than half the CPU time.

Command line: ``torchpref reproduce wave [--trials N] [--queries Q] [--seed S] [--out DIR]``;
from Python: :func:`run_wave_experiment`.
"""

from __future__ import annotations

import argparse
import functools
import time
from concurrent.futures import Executor
from pathlib import Path
from typing import Any

import torch

from torchpref.data.queries import BoxCandidates
from torchpref.experiments import runner
from torchpref.experiments.results import (
    at_budgets,
    curves,
    effort_budgets,
    final_values,
    fraction_ratings,
    metric_panels,
    paired_tests,
    write_experiment_files,
)
from torchpref.models.batch import BatchedPreferenceGP
from torchpref.models.preference_gp import PreferenceGP
from torchpref.selection.active import run_active_learning, run_active_learning_batch
from torchpref.selection.strategies import Selector
from torchpref.simulation.metrics import rating_from_latent, true_positives, wrms
from torchpref.simulation.users import SimulatedUser
from torchpref.simulation.utility_functions import WaveFunction, evaluation_grid

#: the authors' model hyperparameters for this experiment (docs/decisions.md): their 1-D run's
#: ``log_hyp = log([0.02, 0.6, 0.2, 0.8, 60])`` is ``[lengthscale, sigma_f, sigma_R, sigma_B, nu]``,
#: so the kernel variance is ``sigma_f^2 = 0.36`` (not 1: the evidence is in docs/wave.md).
MODEL_SETTINGS = {
    "lengthscale": 0.02,
    "outputscale": 0.36,
    "comparison_noise": 0.2,
    "rating_scale": 0.8,
    "rating_precision": 60.0,
}
M = 5  # items per ranking query
GAMMA = 3.0  # eq. 12 (the paper's text; the authors' code used 2)
NUM_CANDIDATES = 100
GRID_POINTS = 101  # the authors' grid: 0, 0.01, ..., 1
TOP_K = 15
#: effort of a rating and of a best-of-m ranking (``1 + (m - 1) / 4``: 2 for m = 5), see docs/wave.md
RATING_COST = 1.0
RANKING_COST = 1.0 + (M - 1) / 4
SELECTOR_RANKING_COST = 1.0

STRATEGIES = ["UCBC", "random ratings", "random rankings", "UCB ratings", "info per effort"]
METRICS = ("wrms", "tp")


#: the selector as this experiment runs it (``runner.make_selector``'s keywords)
SELECTOR_OPTIONS: dict[str, Any] = {
    "m": M,
    "gamma": GAMMA,
    "rating_cost": RATING_COST,
    "ranking_cost": SELECTOR_RANKING_COST,
}


def make_selector(name: str) -> Selector:
    """The selector ``name`` as this experiment runs it (:data:`SELECTOR_OPTIONS`)."""
    return runner.make_selector(name, **SELECTOR_OPTIONS)


make_model = functools.partial(runner.make_model, settings=MODEL_SETTINGS)
trial_seeds = runner.trial_seeds


def _setup(trial_seed: int) -> tuple[WaveFunction, list[int], torch.Tensor, torch.Tensor]:
    """A trial's wave function, its seeds (user, selector), true ratings on the grid, first pair."""
    g = torch.Generator().manual_seed(trial_seed)
    truth = WaveFunction.random(generator=g)
    seeds = torch.randint(0, 2**62, (3,), generator=g).tolist()
    with torch.no_grad():
        u_true = rating_from_latent(truth(evaluation_grid(GRID_POINTS), noise=False), MODEL_SETTINGS["rating_scale"])
    x0 = torch.rand(2, 1, generator=g, dtype=torch.float64)
    return truth, seeds, u_true, x0


def _start(
    truth: WaveFunction, seeds: list[int], x0: torch.Tensor
) -> tuple[SimulatedUser, PreferenceGP, torch.Generator]:
    """A fresh user, the model of its answer to the first pair, and the selector's generator:
    every strategy of a trial starts from these."""
    user = SimulatedUser.paper_wave(lambda X: truth(X, noise=False), generator=torch.Generator().manual_seed(seeds[0]))
    first = user.choose(x0)
    return user, make_model(x0, torch.tensor([[first, 1 - first]])), torch.Generator().manual_seed(seeds[1])


def _candidates() -> BoxCandidates:
    return BoxCandidates(torch.tensor([[0.0], [1.0]], dtype=torch.float64), NUM_CANDIDATES)


def _metrics(est: torch.Tensor, u_true: torch.Tensor) -> dict[str, torch.Tensor]:
    """WRMS (eq. 14) and true positives among the top :data:`TOP_K` of estimated ratings on the
    grid (``... x GRID_POINTS``: one trial or a batch)."""
    return {"wrms": wrms(est, u_true), "tp": true_positives(est, u_true, k=TOP_K).to(est)}


def _record(hist) -> dict[str, list]:
    return {
        "wrms": hist.metric("wrms"),
        "tp": hist.metric("tp"),
        "cost": hist.cumulative_cost(),
        "kinds": [r.query.kind for r in hist.records],
    }


def run_trial(trial_seed: int, queries: int, strategies: tuple[str, ...] = tuple(STRATEGIES)) -> dict[str, Any]:
    r"""One trial, one model at a time (:func:`~torchpref.selection.active.run_active_learning`): every
    strategy on the same wave function and first comparison.

    Returns:
        ``{strategy: {"wrms": [Q + 1], "tp": [Q + 1], "cost": [Q + 1], "kinds": [Q]}}``.
    """
    runner.single_threaded()
    truth, seeds, u_true, x0 = _setup(trial_seed)
    grid = evaluation_grid(GRID_POINTS)

    def metrics(model) -> dict[str, float]:
        with torch.no_grad():
            return {k: float(v) for k, v in _metrics(model.expected_rating(grid), u_true).items()}

    out = {}
    with torch.inference_mode():  # nothing in a trial needs gradients (fixed hyperparameters)
        for name in strategies:
            user, model, gen = _start(truth, seeds, x0)
            hist = run_active_learning(
                model,
                user,
                _candidates(),
                make_selector(name),
                queries,
                generator=gen,
                metrics=metrics,
                costs={"rating": RATING_COST, "ranking": RANKING_COST},
            )
            out[name] = _record(hist)
    return out


def run_trial_batch(trial_seeds: tuple[int, ...], queries: int, strategy: str) -> list[dict[str, Any]]:
    r"""Several trials of one strategy at once (:func:`~torchpref.selection.active.run_active_learning_batch`,
    one batched model): per trial the same questions, answers and metrics as :func:`run_trial`
    (up to the Newton tolerance, which only matters where two candidates tie).

    Returns:
        One ``{strategy: {...}}`` per trial, as :func:`run_trial` for this strategy.
    """
    runner.single_threaded()
    setups = [_setup(s) for s in trial_seeds]
    u_true = torch.stack([u for _, _, u, _ in setups])
    grid = evaluation_grid(GRID_POINTS).expand(len(setups), -1, -1)

    def metrics(model) -> dict[str, torch.Tensor]:
        return _metrics(model.expected_rating(grid), u_true)

    with torch.inference_mode():
        starts = [_start(truth, seeds, x0) for truth, seeds, _, x0 in setups]
        model = BatchedPreferenceGP.from_models([m for _, m, _ in starts])
        hists = run_active_learning_batch(
            model,
            [u for u, _, _ in starts],
            _candidates(),
            make_selector(strategy),
            queries,
            generators=[g for _, _, g in starts],
            metrics=metrics,
            costs={"rating": RATING_COST, "ranking": RANKING_COST},
        )
    return [{strategy: _record(h)} for h in hists]


def summarise(results: list[dict[str, Any]], strategies: list[str]) -> dict[str, Any]:
    r"""Mean ± SEM curves per query count and per unit of effort, and the paired tests at the end."""
    budgets = effort_budgets(results, strategies)
    per_query = curves(results, strategies, METRICS)
    per_effort = curves(results, strategies, METRICS, budgets)
    final = {s: {k: [r[s][k][-1] for r in results] for k in METRICS} for s in strategies}
    at_budget = {
        s: {k: [at_budgets(r[s][k], r[s]["cost"], budgets)[-1] for r in results] for k in METRICS} for s in strategies
    }
    pairs = []
    if "UCBC" in strategies:
        pairs += [("UCBC", s) for s in strategies if s not in ("UCBC", "info per effort")]
    if "info per effort" in strategies:
        pairs += [("info per effort", s) for s in strategies if s != "info per effort"]
    tests: dict[str, Any] = {"queries": {}, "effort": {}}
    if len(results) >= 2:
        for a, b in pairs:
            key = f"{a} vs {b}"
            tests["queries"][key] = {k: paired_tests(final[a][k], final[b][k]) for k in METRICS}
            tests["effort"][key] = {k: paired_tests(at_budget[a][k], at_budget[b][k]) for k in METRICS}
    return {
        "queries": len(results[0][strategies[0]]["wrms"]) - 1,
        "per_query": per_query,
        "per_effort": per_effort,
        "budgets": budgets,
        "final": final_values(per_query, METRICS),
        "paired_tests": tests,
        "fraction_ratings": fraction_ratings(results, strategies),
    }


def run_wave_experiment(
    trials: int = 100,
    queries: int = 20,
    seed: int = 10,
    out: str | Path | None = "benchmarks/results",
    executor: Executor | None = None,
    *,
    workers: int | None = None,
    strategies: list[str] | None = None,
    progress: bool = True,
    batch_size: int | None = 50,
) -> dict[str, Any]:
    r"""Run the Fig. 6 experiment and (if ``out`` is given) write its files.

    Files in ``out``: ``wave.json`` (``{"trials", "queries", "strategies": {name: {"wrms_mean",
    "wrms_sem", "tp_mean", "tp_sem"}}}``, one entry per query count 0..Q), ``wave.csv`` (the
    same, long format), ``wave.png`` (Fig. 6's two panels, mean ± standard error),
    ``wave_effort.png`` and ``wave_effort.csv`` (the metrics against cumulative effort), and
    ``wave_summary.json`` (final values, paired tests, wall time).

    Args:
        trials: number of random wave functions.
        queries: queries per trial.
        seed: the run's seed; per-trial seeds derive from it.
        out: output folder, or ``None`` to write nothing.
        executor: any ``concurrent.futures.Executor`` (default: a process pool of ``workers``).
        workers: processes of the default pool.
        strategies: a subset of :data:`STRATEGIES` (default all).
        progress: show a progress bar.
        batch_size: trials of one strategy solved together (:func:`run_trial_batch`, one
            executor call each); ``None``: one trial, all strategies, one model at a time per
            call (:func:`run_trial`). Both give the same results.

    Returns:
        The ``wave.json`` content, with ``"summary"`` (the ``wave_summary.json`` content) added.
    """
    strategies = runner.check_run(queries, strategies, STRATEGIES, batch_size)
    t0 = time.perf_counter()
    seeds = trial_seeds(seed, trials)
    run_kw: dict[str, Any] = dict(executor=executor, progress=progress, workers=workers, description="wave trials")
    if batch_size is None:
        results = runner.run_trials(run_trial, [(s, queries, tuple(strategies)) for s in seeds], **run_kw)
    else:
        results = runner.run_by_strategy(
            run_trial_batch, seeds, strategies, batch_size, (queries,), first=("info per effort",), **run_kw
        )
    wall = time.perf_counter() - t0
    summary = summarise(results, strategies)
    summary.update(
        trials=trials,
        seed=seed,
        wall_time_s=wall,
        workers=workers,
        settings={
            "model": MODEL_SETTINGS,
            "m": M,
            "gamma": GAMMA,
            "candidates": NUM_CANDIDATES,
            "grid_points": GRID_POINTS,
            "top_k": TOP_K,
            "costs": {"rating": RATING_COST, "ranking": RANKING_COST},
        },
    )
    result = {"trials": trials, "queries": queries, "strategies": summary["per_query"]}
    if out is not None:
        _write_files(out, result, summary)
    result["summary"] = summary
    return result


def _write_files(out: str | Path, result: dict[str, Any], summary: dict[str, Any]) -> None:
    """The run's files and figures (see :func:`run_wave_experiment`)."""
    trials, queries = result["trials"], result["queries"]
    labels = {"wrms": "WRMS (eq. 14)", "tp": f"true positives (top {TOP_K})"}
    figures = {
        "wave.png": dict(
            panels=metric_panels(summary["per_query"], list(range(queries + 1)), labels),
            title=f"Wave functions, {trials} trials (mean ± s.e.)",
        ),
        "wave_effort.png": dict(
            panels=metric_panels(summary["per_effort"], summary["budgets"], labels),
            xlabel=f"effort (rating {RATING_COST:g}, best-of-{M} {RANKING_COST:g})",
            title=f"At equal effort, {trials} trials (mean ± s.e.)",
        ),
    }
    write_experiment_files(out, "wave", result, summary, figures, effort=summary["per_effort"])


def run(args: argparse.Namespace) -> int:
    """``torchpref reproduce wave``: run and report where the files went."""
    return runner.run_cli(args, run_wave_experiment)
