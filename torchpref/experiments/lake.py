r"""The lake-monitoring experiment of the paper's Fig. 9 (Sec. IV.B).

One scenario (:func:`~torchpref.lake.scenario.make_scenario`) is built per run from the run's
``seed``: building one costs seconds (planning 400 paths), so the trials share it and differ
in their trial seed, which draws the first comparison and seeds the selectors' randomness.
The candidates are the distinct training paths (:class:`~torchpref.queries.FinitePool`), the
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
rated 5), ``wrms`` (:func:`torchpref.metrics.wrms`) and ``chosen_rating`` (the operator's level
of the test path with the largest posterior mean). For each strategy's final model in the first
``plan_trials`` trials, :func:`~torchpref.lake.plan.plan_with_utility` plans a path for the
posterior mean (wrapped by :func:`model_utility` to take the lake's objectives) and the operator's level of that path is compared with the best pool path's.

Command line: ``torchpref reproduce lake [--trials N] [--queries Q] [--seed S] [--out DIR]``;
from Python: :func:`run_lake_experiment`.
"""

from __future__ import annotations

import functools
import math
import time
from concurrent.futures import Executor
from pathlib import Path
from typing import Any

import torch

from torchpref.active import run_active_learning
from torchpref.data import likert_to_unit
from torchpref.experiments import runner
from torchpref.experiments.results import fraction_ratings, mean_sem, paired_tests, plot_mean_sem, write_json, write_summary_csv
from torchpref.experiments.runner import run_trials, single_threaded
from botorch.utils.transforms import normalize as normalise
from botorch.utils.transforms import unnormalize as unnormalise

from torchpref.lake.operator import LakeOperator
from torchpref.lake.plan import plan_with_utility
from torchpref.lake.scenario import LakeScenario, make_scenario
from torchpref.metrics import wrms
from torchpref.queries import FinitePool, first_unique_rows

#: fixed model hyperparameters (see the module docstring)
MODEL_SETTINGS = {"lengthscale": 0.15, "outputscale": 1.0, "comparison_noise": 0.1, "rating_scale": 1.0,
                  "rating_precision": 20.0}
M = 5
GAMMA = 3.0
STRATEGIES = ["UCBC", "random ratings", "UCB ratings", "info per effort"]
PLAN_TRIALS = 5
PLAN_OPTIONS = {"num_starts": 3, "steps": 100, "lr": 1.0}


make_selector = functools.partial(runner.make_selector, m=M, gamma=GAMMA)
make_model = functools.partial(runner.make_model, settings=MODEL_SETTINGS)


class NormalisedOperator:
    """A :class:`LakeOperator` answering about normalised objective vectors."""

    def __init__(self, operator: LakeOperator, bounds: torch.Tensor):
        self.operator, self.bounds = operator, bounds

    def rate(self, z) -> float:
        """The operator's rating of the normalised item ``z`` (``d``)."""
        return self.operator.rate(unnormalise(torch.as_tensor(z, dtype=torch.float64), self.bounds))

    def choose(self, Z) -> int:
        """The operator's choice among the normalised items ``Z`` (``m x d``)."""
        return self.operator.choose(unnormalise(torch.as_tensor(Z, dtype=torch.float64), self.bounds))


def pool_bounds(scenario: LakeScenario) -> torch.Tensor:
    """``2 x 2`` min and max of the training pool's objectives (the normalisation)."""
    X = scenario.train_X
    return torch.stack([X.min(0).values, X.max(0).values])


def model_utility(model, bounds: torch.Tensor):
    """The posterior mean of ``model`` (trained on objectives normalised by ``bounds``) as a
    differentiable function of the lake's objectives ``n x 2`` -> ``n``."""

    def utility(X: torch.Tensor) -> torch.Tensor:
        Z = normalise(X, bounds)
        return model.posterior(Z.unsqueeze(-2)).mean.reshape(Z.shape[:-1])

    return utility


def trial_seeds(seed: int, trials: int) -> list[int]:
    """``trials`` per-trial seeds derived from the run's ``seed``."""
    return runner.trial_seeds(int(seed) + 1, trials)


def run_trial(scenario: LakeScenario, trial_seed: int, queries: int, strategies: tuple[str, ...],
              plan: bool = False) -> dict[str, Any]:
    r"""One trial: every strategy from the same first comparison on the shared scenario.

    Returns:
        ``{strategy: {"error5": [Q+1], "wrms": [Q+1], "chosen_rating": [Q+1], "kinds": [Q],
        "plan": {...} or None}}``.
    """
    single_threaded()
    operator = LakeOperator()
    bounds = pool_bounds(scenario)
    keep = first_unique_rows(scenario.train_X)
    pool = normalise(scenario.train_X[keep], bounds)
    Z_test = normalise(scenario.test_X, bounds)
    level_test = operator.level(scenario.test_X)
    u_true = likert_to_unit(level_test).to(torch.float64)
    five = level_test == 5
    user = NormalisedOperator(operator, bounds)
    g = torch.Generator().manual_seed(trial_seed)
    first_idx = torch.randperm(pool.shape[0], generator=g)[:2]
    sel_seed = int(torch.randint(0, 2**62, (1,), generator=g))
    x0 = pool[first_idx]

    def metrics(model) -> dict[str, float]:
        with torch.no_grad():
            est = model.expected_rating(Z_test)
            mean = model.posterior(Z_test.unsqueeze(-2)).mean.reshape(-1)
        e5 = float((est[five] - u_true[five]).abs().mean()) if five.any() else float("nan")
        return {"error5": e5, "wrms": float(wrms(est, u_true)), "chosen_rating": float(level_test[mean.argmax()])}

    out = {}
    for name in strategies:
        first = user.choose(x0)
        model = make_model(x0.clone(), torch.tensor([[first, 1 - first]]))
        hist = run_active_learning(model, user, FinitePool(pool), make_selector(name), queries,
                                   generator=torch.Generator().manual_seed(sel_seed), metrics=metrics)
        entry = {k: hist.metric(k) for k in ("error5", "wrms", "chosen_rating")}
        entry["kinds"] = [r.query.kind for r in hist.records]
        entry["plan"] = None
        if plan:
            res = plan_with_utility(scenario, model_utility(model, bounds), **PLAN_OPTIONS)
            entry["plan"] = {"planned_level": int(operator.level(res.objectives)),
                             "pool_level": int(operator.level(res.start_objectives)),
                             "planned": bool(res.planned),
                             "planned_objectives": res.objectives.tolist(),
                             "pool_objectives": res.start_objectives.tolist(),
                             "utility_gain": res.utility - res.start_utility}
        out[name] = entry
    return out


def summarise(results: list[dict[str, Any]], strategies: list[str]) -> dict[str, Any]:
    """Per-query mean ± SEM, final values, share rated 5, paired tests and planning results."""
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
                tests[f"UCBC vs {b}"] = {k: paired_tests(final["UCBC"][k], final[b][k])
                                         for k in ("error5", "wrms", "chosen_rating")
                                         if not any(math.isnan(v) for v in final["UCBC"][k] + final[b][k])}
    planning = {}
    for s in strategies:
        plans = [r[s]["plan"] for r in results if r[s]["plan"] is not None]
        if plans:
            planning[s] = {
                "n": len(plans),
                "planned_level_mean": sum(p["planned_level"] for p in plans) / len(plans),
                "pool_level_mean": sum(p["pool_level"] for p in plans) / len(plans),
                "planned_better": sum(p["planned_level"] > p["pool_level"] for p in plans),
                "planned_worse": sum(p["planned_level"] < p["pool_level"] for p in plans),
                "optimised_path_kept": sum(p["planned"] for p in plans),
                "trials": plans,
            }
    return {"per_query": per_query,
            "final": {s: {k: [per_query[s][f"{k}_mean"][-1], per_query[s][f"{k}_sem"][-1]]
                          for k in ("error5", "wrms", "chosen_rating")} for s in strategies},
            "share_rated_5": share5, "paired_tests": tests, "planning": planning,
            "fraction_ratings": fraction_ratings(results, strategies)}


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
    plan_trials: int = PLAN_TRIALS,
    progress: bool = True,
) -> dict[str, Any]:
    r"""Run the lake experiment and (if ``out`` is given) write its files.

    One scenario is built from ``seed`` for the whole run (unless ``scenario`` is given); the
    trials share it and differ by their trial seed (first comparison, selector randomness).

    Files in ``out``: ``lake.json`` (``{"trials", "queries", "strategies": {name: {"error5_mean",
    "error5_sem", "wrms_mean", "wrms_sem", "chosen_rating_mean", "chosen_rating_sem"}}}``, one
    value per query count 0..Q), ``lake.csv`` (the same, long format), ``lake.png`` (three
    panels, mean ± standard error) and ``lake_summary.json`` (final values, share of trials
    whose chosen path is rated 5, paired tests, planned vs pool path, wall time).

    Args:
        trials: number of trials.
        queries: queries per trial.
        seed: the run's seed (scenario and per-trial seeds).
        out: output folder, or ``None``.
        executor: any ``concurrent.futures.Executor`` (default: a process pool of ``workers``).
        workers: processes of the default pool.
        strategies: a subset of :data:`STRATEGIES` (default all).
        scenario: a prebuilt scenario (default ``make_scenario(seed)``).
        plan_trials: plan with each strategy's final model in this many first trials.
        progress: show a progress bar.

    Returns:
        The ``lake.json`` content with ``"summary"`` added.
    """
    strategies = runner.check_run(queries, strategies, STRATEGIES)
    t0 = time.perf_counter()
    if scenario is None:
        scenario = make_scenario(seed)
    t_scenario = time.perf_counter() - t0
    args = [(scenario, s, queries, tuple(strategies), i < plan_trials)
            for i, s in enumerate(trial_seeds(seed, trials))]
    results = run_trials(run_trial, args, executor=executor, progress=progress, workers=workers,
                         description="lake trials")
    wall = time.perf_counter() - t0
    summary = summarise(results, strategies)
    summary.update(trials=trials, queries=queries, seed=seed, wall_time_s=wall, scenario_time_s=t_scenario,
                   workers=workers, settings={"model": MODEL_SETTINGS, "m": M, "gamma": GAMMA,
                                              "plan": PLAN_OPTIONS, "plan_trials": plan_trials,
                                              "test_paths_rated_5": int((LakeOperator().level(scenario.test_X) == 5).sum())})
    result = {"trials": trials, "queries": queries, "strategies": summary["per_query"]}
    if out is not None:
        out = Path(out)
        write_json(out / "lake.json", result)
        write_summary_csv(out / "lake.csv", summary["per_query"], x_name="queries")
        write_json(out / "lake_summary.json", summary)
        x = list(range(queries + 1))
        pq = summary["per_query"]
        plot_mean_sem(out / "lake.png", [
            ("error on paths rated 5", {s: (x, pq[s]["error5_mean"], pq[s]["error5_sem"]) for s in strategies}),
            ("WRMS", {s: (x, pq[s]["wrms_mean"], pq[s]["wrms_sem"]) for s in strategies}),
            ("rating of chosen path", {s: (x, pq[s]["chosen_rating_mean"], pq[s]["chosen_rating_sem"])
                                       for s in strategies}),
        ], title=f"Lake monitoring, {trials} trials (mean ± s.e.)")
    result["summary"] = summary
    return result


def run(args) -> int:
    """``torchpref reproduce lake``: run and report."""
    res = run_lake_experiment(trials=args.trials, queries=args.queries, seed=args.seed, out=args.out,
                              workers=getattr(args, "workers", None))
    s = res["summary"]
    print(f"{args.trials} trials x {args.queries} queries in {s['wall_time_s']:.1f} s "
          f"(scenario {s['scenario_time_s']:.1f} s); files in {args.out}")
    for name, v in s["final"].items():
        p = s["planning"].get(name)
        plan = f"   plan {p['planned_level_mean']:.2f} vs pool {p['pool_level_mean']:.2f}" if p else ""
        print(f"  {name:16s} error5 {v['error5'][0]:.3f} ± {v['error5'][1]:.3f}   WRMS {v['wrms'][0]:.3f} ± "
              f"{v['wrms'][1]:.3f}   chosen {v['chosen_rating'][0]:.2f}   share 5 {s['share_rated_5'][name]:.2f}{plan}")
    return 0
