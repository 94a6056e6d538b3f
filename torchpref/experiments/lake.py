r"""The lake-monitoring experiment of the paper's Fig. 9 (Sec. IV.B).

One scenario (:func:`~torchpref.lake.scenario.make_scenario`) is built per run from the run's
``seed``: building one costs seconds (planning 400 paths), so the trials share it and differ
in their trial seed, which draws the first comparison and seeds the selectors' randomness.
The candidates are the distinct training paths (:class:`~torchpref.data.queries.FinitePool`), the
simulated user is :class:`~torchpref.lake.operator.LakeOperator` (Likert level ``k`` ->
``(k - 1/2) / 5``), and the metrics are taken on the 200 test paths.

The model sees objectives normalised to the unit cube by the training pool's min and max
(done here, not with BoTorch's ``Normalize``), and the operator is wrapped to map normalised
points back. Fixed hyperparameters (:data:`MODEL_SETTINGS`): lengthscale 0.15 in the unit
cube (the operator's levels change over about a tenth of each axis' range, 50 distance units
or 25 information units), outputscale 1, comparison noise 0.1 (the operator is noise-free but
a little slack keeps the Laplace mode well conditioned), rating scale 1 and rating precision 20
(Likert ratings are coarse: a level is a bin 0.2 wide, so the Beta likelihood should not be
sharper than that).

Metrics per query count: ``error5`` (mean ``|expected rating - true rating|`` on the test paths
rated 5), ``wrms`` (:func:`torchpref.simulation.metrics.wrms`) and ``chosen_rating`` (the operator's level
of the test path with the largest posterior mean). For each strategy's final model in the first
``plan_trials`` trials, :func:`~torchpref.lake.plan.plan_with_utility` plans a path for the
posterior mean (wrapped by :func:`model_utility` to take the lake's objectives) and the operator's level of that path is compared with the best pool path's.

Files written by :func:`run_lake_experiment` in its ``out`` folder: ``lake.json``
(``{"trials", "queries", "lakes", "strategies": {name: {"error5_mean", "error5_sem", "wrms_mean",
"wrms_sem", "chosen_rating_mean", "chosen_rating_sem"}}}``, one value per query count 0..Q, pooled over lakes), ``lake.csv``
(the same, long format), ``lake.png`` (three panels, mean ± standard error),
``lake_summary.json`` (pooled and per-lake final values, share of trials whose chosen path is
rated 5, paired tests, planned vs pool path, wall time), the first lake's maps
``lake_field.png`` and ``lake_objectives.png``, and with planning ``lake_plan_maps.png`` (the
first trial's paths per strategy) and ``lake_plan_levels.png`` (levels over the trials).

Command line: ``torchpref reproduce lake [--trials N] [--queries Q] [--seed S] [--out DIR]``;
from Python: :func:`run_lake_experiment`.
"""

from __future__ import annotations

import argparse
import functools
import math
import os
import pickle
import time
from concurrent.futures import Executor
from pathlib import Path
from typing import Any

import torch
from botorch.utils.transforms import normalize as normalise
from botorch.utils.transforms import unnormalize as unnormalise
from torch import Tensor

from torchpref.data.preference_data import likert_to_unit
from torchpref.data.queries import FinitePool, first_unique_rows
from torchpref.experiments import runner
from torchpref.experiments.lake_plan import (
    PLAN_SETTINGS,
    fresh_paths,
    plan_for_model,
    plot_plan_levels,
    plot_plan_maps,
    summarise_plans,
)
from torchpref.experiments.results import (
    fraction_ratings,
    mean_sem,
    paired_tests,
    plot_mean_sem,
    write_json,
    write_summary_csv,
)
from torchpref.experiments.runner import run_trials, single_threaded
from torchpref.lake.operator import LakeOperator, RealisticLakeOperator
from torchpref.lake.plotting import plot_field, plot_objectives
from torchpref.lake.scenario import SCENARIO_VERSION, LakeScenario, cached_scenario, scenario_cache_path
from torchpref.selection.active import run_active_learning
from torchpref.simulation.metrics import wrms
from torchpref.simulation.raters import EffortModel

#: fixed model hyperparameters (see the module docstring)
MODEL_SETTINGS = {
    "lengthscale": 0.15,
    "outputscale": 1.0,
    "comparison_noise": 0.1,
    "rating_scale": 1.0,
    "rating_precision": 20.0,
}
M = 5
GAMMA = 3.0
STRATEGIES = ["UCBC", "random ratings", "UCB ratings", "info per effort"]


make_selector = functools.partial(runner.make_selector, m=M, gamma=GAMMA)
#: the operator variants: the paper's deterministic operator, or a realistic person
#: (:class:`~torchpref.lake.operator.RealisticLakeOperator`: offset ``N(0, 0.29^2)`` levels, drift,
#: noise 0.39 levels, lapses ``U(0.05, 0.25)``) who looks at every path shown (10 s each)
OPERATORS = ("paper", "realistic")
#: the realistic operator's seconds: FIRE's per answer plus 10 s of viewing per path shown
LAKE_EFFORT = EffortModel.trajectories()


def operator_user(variant: str, user: Any, trial_seed: int) -> Any:
    """The operator of ``variant`` (:data:`OPERATORS`) answering through ``user`` (the paper's,
    normalised); a realistic one is drawn from ``trial_seed`` (the same person for every strategy)."""
    if variant == "paper":
        return user
    if variant != "realistic":
        raise ValueError(f"unknown operator {variant!r}; choose from {list(OPERATORS)}.")
    g = torch.Generator().manual_seed(int(trial_seed) + 7)
    offset = 0.29 * float(torch.randn((), generator=g, dtype=torch.float64))
    lapse = 0.05 + 0.2 * float(torch.rand((), generator=g, dtype=torch.float64))
    return RealisticLakeOperator(user, g, level_offset=offset, lapse_rate=lapse)


make_model = functools.partial(runner.make_model, settings=MODEL_SETTINGS)


class NormalisedOperator:
    """A :class:`LakeOperator` answering about normalised objective vectors."""

    def __init__(self, operator: LakeOperator, bounds: torch.Tensor):
        self.operator, self.bounds = operator, bounds

    def rate(self, z: Tensor) -> float:
        """The operator's rating of the normalised item ``z`` (``d``)."""
        return self.operator.rate(unnormalise(torch.as_tensor(z, dtype=torch.float64), self.bounds))

    def choose(self, Z: Tensor) -> int:
        """The operator's choice among the normalised items ``Z`` (``m x d``)."""
        return self.operator.choose(unnormalise(torch.as_tensor(Z, dtype=torch.float64), self.bounds))


def pool_bounds(scenario: LakeScenario) -> torch.Tensor:
    """``2 x 2`` min and max of the training pool's objectives (the normalisation)."""
    X = scenario.train_X
    return torch.stack([X.min(0).values, X.max(0).values])


def trial_seeds(seed: int, trials: int) -> list[int]:
    """``trials`` per-trial seeds derived from the run's ``seed``."""
    return runner.trial_seeds(int(seed) + 1, trials)


def _lake_metrics(Z_test: torch.Tensor, level_test: torch.Tensor):
    """The lake's metrics of a model: the error on the paths rated 5, WRMS of the expected rating
    against the operator's, and the operator's rating of the path of highest posterior mean."""
    u_true = likert_to_unit(level_test).to(torch.float64)
    five = level_test == 5

    def metrics(model) -> dict[str, float]:
        with torch.no_grad():
            est = model.expected_rating(Z_test)
            mean = model.posterior(Z_test.unsqueeze(-2)).mean.reshape(-1)
        e5 = float((est[five] - u_true[five]).abs().mean()) if five.any() else float("nan")
        return {"error5": e5, "wrms": float(wrms(est, u_true)), "chosen_rating": float(level_test[mean.argmax()])}

    return metrics


def run_trial(
    scenario: LakeScenario,
    trial_seed: int,
    queries: int,
    strategies: tuple[str, ...],
    plan: tuple[str, ...] = (),
    plan_settings: dict[str, Any] | None = None,
    fresh: torch.Tensor | None = None,
    operator_variant: str = "paper",
) -> dict[str, Any]:
    r"""One trial: every strategy from the same first comparison on the shared scenario.

    Args:
        plan: the strategies whose final model plans a path
            (:func:`~torchpref.experiments.lake_plan.plan_for_model`).
        plan_settings: overrides of :data:`~torchpref.experiments.lake_plan.PLAN_SETTINGS`.
        fresh: fresh planner paths to start from too.
        operator_variant: ``"paper"`` or ``"realistic"`` (:data:`OPERATORS`); the realistic
            operator's selectors weigh its seconds (:data:`LAKE_EFFORT`).

    Returns:
        ``{strategy: {"error5": [Q+1], "wrms": [Q+1], "chosen_rating": [Q+1], "kinds": [Q],
        "seconds": [Q+1] (cumulative, :data:`LAKE_EFFORT`), "plan": {...} or None}}``.
    """
    single_threaded()
    operator = LakeOperator()
    bounds = pool_bounds(scenario)
    keep = first_unique_rows(scenario.train_X)
    pool = normalise(scenario.train_X[keep], bounds)
    Z_test = normalise(scenario.test_X, bounds)
    level_test = operator.level(scenario.test_X)
    user = NormalisedOperator(operator, bounds)
    g = torch.Generator().manual_seed(trial_seed)
    first_idx = torch.randperm(pool.shape[0], generator=g)[:2]
    sel_seed = int(torch.randint(0, 2**62, (1,), generator=g))
    x0 = pool[first_idx]

    metrics = _lake_metrics(Z_test, level_test)
    costs = LAKE_EFFORT.costs(M)
    out = {}
    for name in strategies:
        person = operator_user(operator_variant, user, trial_seed)
        first = person.choose(x0)
        model = make_model(x0.clone(), torch.tensor([[first, 1 - first]]))
        selector = (
            make_selector(name)
            if operator_variant == "paper"
            else make_selector(name, rating_cost=costs["rating"], ranking_cost=costs["ranking"])
        )
        hist = run_active_learning(
            model,
            person,
            FinitePool(pool),
            selector,
            queries,
            generator=torch.Generator().manual_seed(sel_seed),
            metrics=metrics,
        )
        entry: dict[str, Any] = {k: hist.metric(k) for k in ("error5", "wrms", "chosen_rating")}
        entry["kinds"] = [r.query.kind for r in hist.records]
        seconds = [0.0]
        for kind in entry["kinds"]:
            seconds.append(seconds[-1] + costs[kind])
        entry["seconds"] = seconds
        entry["plan"] = None
        if name in plan:
            entry["plan"] = plan_for_model(scenario, model, bounds, keep, fresh, plan_settings)
        out[name] = entry
    return out


def summarise(results: list[dict[str, Any]], strategies: list[str]) -> dict[str, Any]:
    """Per-query mean ± SEM, final values, share rated 5, paired tests and planning results
    (:func:`~torchpref.experiments.lake_plan.summarise_plans`)."""
    per_query = {}
    for s in strategies:
        entry = {}
        for k in ("error5", "wrms", "chosen_rating"):
            m, e = mean_sem([r[s][k] for r in results])  # NaN: a trial without a value
            entry[f"{k}_mean"], entry[f"{k}_sem"] = m, e
        per_query[s] = entry
    final = {s: {k: [r[s][k][-1] for r in results] for k in ("error5", "wrms", "chosen_rating")} for s in strategies}
    share5 = {s: sum(v == 5 for v in final[s]["chosen_rating"]) / len(results) for s in strategies}
    tests: dict[str, Any] = {}
    if len(results) >= 2 and "UCBC" in strategies:
        for b in strategies:
            if b != "UCBC":
                tests[f"UCBC vs {b}"] = {
                    k: paired_tests(final["UCBC"][k], final[b][k])
                    for k in ("error5", "wrms", "chosen_rating")
                    if not any(math.isnan(v) for v in final["UCBC"][k] + final[b][k])
                }
    planning = {}
    for s in strategies:
        plans = [r[s]["plan"] for r in results if r[s]["plan"] is not None]
        if plans:
            planning[s] = summarise_plans(plans)
    return {
        "per_query": per_query,
        "final": {
            s: {
                k: [per_query[s][f"{k}_mean"][-1], per_query[s][f"{k}_sem"][-1]]
                for k in ("error5", "wrms", "chosen_rating")
            }
            for s in strategies
        },
        "share_rated_5": share5,
        "paired_tests": tests,
        "planning": planning,
        "fraction_ratings": fraction_ratings(results, strategies),
    }


def prepare_lake(seed: int, cache_dir: str | Path | None, num_fresh: int) -> tuple[LakeScenario, torch.Tensor | None]:
    """The scenario of ``seed`` (:func:`~torchpref.lake.scenario.cached_scenario`) and, with
    ``num_fresh > 0``, its fresh planner paths (:func:`~torchpref.experiments.lake_plan.fresh_paths`,
    cached beside it)."""
    single_threaded()
    scenario = cached_scenario(seed, cache_dir)
    if num_fresh <= 0:
        return scenario, None
    path = scenario_cache_path(seed, cache_dir).with_name(f"fresh-v{SCENARIO_VERSION}-seed{seed}-n{num_fresh}.pt")
    try:
        return scenario, torch.load(path, weights_only=True)
    except (OSError, RuntimeError, EOFError, pickle.UnpicklingError):
        fresh = fresh_paths(scenario, num_fresh, torch.Generator().manual_seed(seed))
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        torch.save(fresh, tmp)
        os.replace(tmp, path)
        return scenario, fresh


def _write_files(
    out: Path,
    result: dict[str, Any],
    summary: dict[str, Any],
    strategies: list[str],
    scenarios: list[LakeScenario],
    results: list[dict[str, Any]],
    lake_of: list[int],
) -> None:
    write_json(out / "lake.json", result)
    write_summary_csv(out / "lake.csv", summary["per_query"], x_name="queries")
    write_json(out / "lake_summary.json", summary)
    x = list(range(result["queries"] + 1))
    pq = summary["per_query"]
    plot_mean_sem(
        out / "lake.png",
        [
            ("error on paths rated 5", {s: (x, pq[s]["error5_mean"], pq[s]["error5_sem"]) for s in strategies}),
            ("WRMS", {s: (x, pq[s]["wrms_mean"], pq[s]["wrms_sem"]) for s in strategies}),
            (
                "rating of chosen path",
                {s: (x, pq[s]["chosen_rating_mean"], pq[s]["chosen_rating_sem"]) for s in strategies},
            ),
        ],
        title=f"Lake monitoring, {len(scenarios)} lake(s) x {result['trials']} trials (mean ± s.e.)",
    )
    plot_field(scenarios[0], out / "lake_field.png")
    plot_objectives(scenarios[0], out / "lake_objectives.png")
    planned = [s for s in strategies if results[0][s]["plan"] is not None]
    if planned:
        plot_plan_maps(scenarios[0], {s: results[0][s]["plan"] for s in planned}, out / "lake_plan_maps.png")
        s = planned[0]
        rows = [i for i, r in enumerate(results) if r[s]["plan"] is not None]
        plot_plan_levels(
            [results[i][s]["plan"] for i in rows],
            [lake_of[i] for i in rows],
            out / "lake_plan_levels.png",
            title=f"{s}: operator's level of the planned path, the pool pick and the best shown path",
        )


def run_lake_experiment(
    trials: int = 20,
    queries: int = 14,
    seed: int = 10,
    out: str | Path | None = "benchmarks/results",
    executor: Executor | None = None,
    *,
    workers: int | None = None,
    strategies: list[str] | None = None,
    scenario: LakeScenario | None = None,
    lakes: int = 1,
    plan: list[str] | None = None,
    plan_trials: int | None = None,
    plan_settings: dict[str, Any] | None = None,
    cache_dir: str | Path | None = None,
    progress: bool = True,
    operator: str = "paper",
) -> dict[str, Any]:
    r"""Run the lake experiment and (if ``out`` is given) write its files (see the module docstring).

    Lake ``k`` (``k = 0 .. lakes - 1``) is the scenario of seed ``seed + k``, built once and
    cached on disk (:func:`~torchpref.lake.scenario.cached_scenario`); its ``trials`` trials
    differ by their trial seed (first comparison, selector randomness), derived from the lake's
    seed.

    Args:
        trials: trials per lake.
        queries: queries per trial.
        seed: the run's seed (lake ``k`` has seed ``seed + k``).
        out: output folder, or ``None``.
        executor: any ``concurrent.futures.Executor`` (default: a process pool of ``workers``).
        workers: processes of the default pool.
        strategies: a subset of :data:`STRATEGIES` (default all).
        scenario: a prebuilt scenario (then ``lakes`` must be 1).
        lakes: number of lakes.
        plan: strategies whose final model plans a path (default ``["UCBC"]``, the default
            selector of a session; ``[]``: no planning).
        plan_trials: plan in this many first trials of each lake (default all).
        plan_settings: overrides of :data:`~torchpref.experiments.lake_plan.PLAN_SETTINGS`.
        cache_dir: where scenarios are cached (default
            :func:`~torchpref.lake.scenario.default_cache_dir`).
        progress: show progress bars (scenarios, then trials).
        operator: ``"paper"`` (the paper's deterministic operator) or ``"realistic"``
            (:func:`operator_user`).

    Returns:
        The ``lake.json`` content with ``"summary"`` added.
    """
    if lakes < 1 or (scenario is not None and lakes != 1):
        raise ValueError(f"lakes must be a positive integer (1 with a given scenario), got {lakes}.")
    strategies = runner.check_run(queries, strategies, STRATEGIES)
    operator_user(operator, None, 0)  # a known variant
    plan = runner.check_run(queries, ["UCBC"] if plan is None else plan, STRATEGIES)
    settings = {**PLAN_SETTINGS, **(plan_settings or {})}
    num_fresh = int(settings["fresh_weights"]) if plan and settings["num_fresh"] > 0 else 0
    t0 = time.perf_counter()
    seeds = [seed + k for k in range(lakes)]
    run_kw: dict[str, Any] = dict(executor=executor, progress=progress, workers=workers)
    prepared = _prepare_lakes(seeds, scenario, cache_dir, num_fresh, run_kw)
    t_scenario = time.perf_counter() - t0
    plan_trials = trials if plan_trials is None else plan_trials
    args, lake_of = _trial_args(seeds, prepared, trials, queries, strategies, plan, plan_trials, settings)
    args = [(*a, operator) for a in args]
    results = run_trials(run_trial, args, description="lake trials", **run_kw)
    wall = time.perf_counter() - t0
    summary = _summarise_run(results, strategies, seeds, lake_of)
    summary.update(trials=trials, queries=queries, seed=seed, lakes=lakes, lake_seeds=seeds)
    summary.update(wall_time_s=wall, scenario_time_s=t_scenario, workers=workers)
    summary["settings"] = {"model": MODEL_SETTINGS, "m": M, "gamma": GAMMA, "plan": settings}
    summary["settings"].update(plan_strategies=plan, plan_trials=plan_trials, operator=operator)
    summary["settings"]["test_paths_rated_5"] = [_rated_5(sc) for sc, _ in prepared]
    result = {"trials": trials, "queries": queries, "lakes": lakes, "strategies": summary["per_query"]}
    if out is not None:
        _write_files(Path(out), result, summary, strategies, [sc for sc, _ in prepared], results, lake_of)
    result["summary"] = summary
    return result


def _prepare_lakes(
    seeds: list[int],
    scenario: LakeScenario | None,
    cache_dir: str | Path | None,
    num_fresh: int,
    run_kw: dict[str, Any],
) -> list[tuple[LakeScenario, torch.Tensor | None]]:
    """Each lake's scenario and fresh paths (:func:`prepare_lake`, one executor call a lake), or
    the given ``scenario`` (of seed ``seeds[0]``) and its fresh paths."""
    if scenario is None:
        return run_trials(
            prepare_lake,
            [(s, cache_dir, num_fresh) for s in seeds],
            description="lake scenarios",
            unit="lake",
            **run_kw,
        )
    return [
        (scenario, fresh_paths(scenario, num_fresh, torch.Generator().manual_seed(seeds[0])) if num_fresh else None)
    ]


def _rated_5(scenario: LakeScenario) -> int:
    """How many of the scenario's test paths the operator rates 5."""
    return int((LakeOperator().level(scenario.test_X) == 5).sum())


def _trial_args(
    seeds: list[int],
    prepared: list[tuple],
    trials: int,
    queries: int,
    strategies: list[str],
    plan: list[str],
    plan_trials: int,
    settings: dict[str, Any],
) -> tuple[list[tuple], list[int]]:
    """:func:`run_trial`'s arguments for every trial of every lake (``prepared``: each lake's scenario
    and fresh paths), planning in the first ``plan_trials`` of each, and each trial's lake."""
    args, lake_of = [], []
    for k, (lake_seed, (scen, fresh)) in enumerate(zip(seeds, prepared)):
        for i, ts in enumerate(trial_seeds(lake_seed, trials)):
            args.append((scen, ts, queries, tuple(strategies), tuple(plan) if i < plan_trials else (), settings, fresh))
            lake_of.append(k)
    return args, lake_of


def _summarise_run(
    results: list[dict[str, Any]], strategies: list[str], seeds: list[int], lake_of: list[int]
) -> dict[str, Any]:
    """:func:`summarise` over all trials, per lake where there are several (trial ``i`` is of lake
    ``lake_of[i]``, seed ``seeds[lake_of[i]]``), and every plan without its path (the paths are
    drawn, not stored)."""
    summary = summarise(results, strategies)
    if len(seeds) > 1:
        summary["per_lake"] = {
            str(s): _lake_summary(summarise([r for r, k2 in zip(results, lake_of) if k2 == k], strategies))
            for k, s in enumerate(seeds)
        }
    summary["plans"] = [
        {"lake": seeds[k], "strategy": s, **{key: v for key, v in r[s]["plan"].items() if key != "path"}}
        for r, k in zip(results, lake_of)
        for s in strategies
        if r[s]["plan"] is not None
    ]
    return summary


def _lake_summary(summary: dict[str, Any]) -> dict[str, Any]:
    """The per-lake part of a summary: final values, share rated 5 and planning (no trials)."""
    return {
        "final": summary["final"],
        "share_rated_5": summary["share_rated_5"],
        "planning": {s: {k: v for k, v in p.items() if k != "paired"} for s, p in summary["planning"].items()},
    }


def run(args: argparse.Namespace) -> int:
    """``torchpref reproduce lake``: run and report."""
    lakes = getattr(args, "lakes", 1) or 1
    res = run_lake_experiment(
        trials=args.trials,
        queries=args.queries,
        seed=args.seed,
        out=args.out,
        workers=getattr(args, "workers", None),
        lakes=lakes,
        cache_dir=getattr(args, "cache", None),
    )
    s = res["summary"]
    print(
        f"{lakes} lake(s) x {args.trials} trials x {args.queries} queries in {s['wall_time_s']:.1f} s "
        f"(scenarios {s['scenario_time_s']:.1f} s); files in {args.out}"
    )
    print(
        "  error5: mean |expected - true rating| on test paths rated 5 (lower is better); WRMS: weighted RMS "
        "error (lower is better);\n  chosen: level of the test path the model ranks first; share 5: share of "
        "trials where it is rated 5; mean ± standard error over trials"
    )
    pm = (lambda e: f" ± {e:.3f}") if lakes * args.trials > 1 else (lambda e: "")  # no s.e. from one trial
    for name, v in s["final"].items():
        print(
            f"  {name:16s} error5 {v['error5'][0]:.3f}{pm(v['error5'][1])}   WRMS {v['wrms'][0]:.3f}"
            f"{pm(v['wrms'][1])}   chosen {v['chosen_rating'][0]:.2f}   share 5 {s['share_rated_5'][name]:.2f}"
        )
    for name, p in s["planning"].items():
        print(
            f"  planning with {name}'s model ({p['n']} plans): planned path rated at least as high as the pool pick "
            f"in {100 * p['at_least_as_good']:.0f} %, strictly better (finer measure) in {100 * p['strictly_better']:.0f} %; "
            f"mean level planned {p['planned_level_mean']:.2f}, pick {p['pick_level_mean']:.2f}, "
            f"best shown {p['shown_level_mean']:.2f}"
        )
    return 0
