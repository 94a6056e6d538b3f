r"""The user-family benchmark suite: every strategy on every kind of simulated user.

For each family of :data:`~torchpref.experiments.families.FAMILIES` (``d = 1..6``, shapes from
the paper's waves to plateaus and BoTorch test functions, answering styles from near-exact to
noisy choices and from precise to Likert ratings) and each condition,

* ``"fixed"``: the family's fixed hyperparameters (:func:`~torchpref.experiments.families.model_settings`);
* ``"learned"``: the kernel's lengthscale and outputscale learned from the answers, a maximum
  a posteriori estimate on a grid (:func:`learn_kernel`: Laplace evidence plus the log prior),
  refit after queries :data:`REFIT_AFTER`; the likelihoods keep the answering style's noise,

every strategy asks ``queries`` questions in each of ``trials`` paired trials (the same user,
first comparison and candidate draws for every strategy of a trial). Metrics after each query
on the family's metric points: ``wrms`` (eq. 14, :func:`~torchpref.simulation.metrics.wrms`), ``tp`` (true
top-:data:`TOP_K` points in the estimated top-:data:`TOP_K`) and ``regret`` (the best point's
utility minus that of the point of largest posterior mean, over the best's margin above the
median point: 0 is the best, 1 a median point). Effort: a rating costs :data:`RATING_COST`, a
best-of-``m`` ranking :data:`RANKING_COST`.

Trials run batched (:class:`~torchpref.BatchedPreferenceGP`), one executor call per family,
condition, strategy and batch of trials (:func:`run_batch`). Command line:
``torchpref reproduce suite [--families ...] [--strategies ...] [--trials N] [--queries Q] [--seed S] [--out DIR]``;
from Python: :func:`run_suite`. Results: ``docs/suite.md``.
"""

from __future__ import annotations

import argparse
import copy
import math
import time
from collections.abc import Iterable, Sequence
from concurrent.futures import Executor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from torchpref.data.preference_data import PreferenceData
from torchpref.data.queries import BoxCandidates, Candidates, FinitePool
from torchpref.experiments import runner
from torchpref.experiments.families import (
    ALL_FAMILIES,
    FAMILIES,
    NUM_CANDIDATES,
    REALISTIC_FAMILIES,
    Family,
    model_settings,
    setup,
)
from torchpref.experiments.results import write_json
from torchpref.experiments.suite_report import summarise, write_suite_files
from torchpref.models.batch import BatchedPreferenceGP
from torchpref.models.kernels import FixedRBFKernel
from torchpref.models.preference_gp import PreferenceGP
from torchpref.selection.active import run_active_learning_batch
from torchpref.simulation.metrics import true_positives, wrms
from torchpref.simulation.raters import EffortModel

if TYPE_CHECKING:
    from torchpref.selection.strategies import Selector

M = 5
GAMMA = 3.0
TOP_K = 15
RATING_COST = 1.0
RANKING_COST = 1.0 + (M - 1) / 4
#: the effort models a run can use: ``"units"`` (a rating 1, a best-of-5 2: the suite's first
#: model), ``"plain"`` (seconds, FIRE's measurements: 3.4 s and 6.1 s) and ``"trajectories"``
#: (seconds, plus 10 s of viewing per option shown: 13.4 s and 56.1 s)
EFFORTS: dict[str, EffortModel | None] = {
    "units": None,
    "plain": EffortModel.plain(),
    "trajectories": EffortModel.trajectories(),
}
#: family groups ``--families`` accepts besides names
FAMILY_GROUPS = {"idealised": list(FAMILIES), "realistic": list(REALISTIC_FAMILIES), "all": list(ALL_FAMILIES)}
CONDITIONS = ("fixed", "learned")
#: verdicts after these many queries (and the last) and at these efforts
CHECKPOINTS = (10, 20)
#: the strategies a run compares by default; any other of the registry's
#: (:data:`~torchpref.experiments.runner.STRATEGIES`, e.g. ``"top & level info"``) can be named
#: (``strategies=`` / ``--strategies``). "top & level info" left the default when the two profile
#: selectors came in: it was best or tied in the fewest cells but random ratings' and costs as
#: much CPU as the costliest, and the default run must fit in 10 minutes (docs/suite.md).
STRATEGIES = [
    "UCBC",
    "random ratings",
    "random rankings",
    "UCB ratings",
    "info per effort",
    "variance per effort",
    "profile per effort",
    "clipped profile",
]
#: the default strategies of a run on the realistic families: the paper's, the random baselines,
#: the two profile selectors and the selector per second
REALISTIC_STRATEGIES = [
    "UCBC",
    "random ratings",
    "random rankings",
    "UCB ratings",
    "profile per effort",
    "clipped profile",
    "profile per second",
]
METRICS = ("wrms", "tp", "regret")
#: the learned condition refits after these many queries
REFIT_AFTER = (3, 6, 10, 15)
#: the learned condition's grid: lengthscales ``0.2 sqrt(d) e^t`` and outputscales
LENGTHSCALE_STEPS = tuple(torch.linspace(-3.5, 1.0, 10).tolist())
OUTPUTSCALES = (0.3, 1.0, 3.0)
#: its prior: ``log lengthscale ~ N(log(0.2 sqrt d), 1.5^2)``, ``outputscale ~ Gamma(2, 1)``
LENGTHSCALE_PRIOR_SD = 1.5


def _grid(dim: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The learned condition's ``G`` (lengthscale, outputscale) pairs and their log prior."""
    centre = 0.2 * math.sqrt(dim)
    steps = torch.tensor(LENGTHSCALE_STEPS, dtype=torch.float64)
    ls = (centre * steps.exp()).repeat_interleave(len(OUTPUTSCALES))
    os_ = torch.tensor(OUTPUTSCALES, dtype=torch.float64).repeat(len(LENGTHSCALE_STEPS))
    prior = torch.distributions.Normal(math.log(centre), LENGTHSCALE_PRIOR_SD).log_prob(
        ls.log()
    ) + torch.distributions.Gamma(2.0, 1.0).log_prob(os_)
    return ls, os_, prior


def learn_kernel(model: BatchedPreferenceGP, dim: int) -> torch.Tensor:
    r"""Set each trial's kernel to the maximum a posteriori (lengthscale, outputscale) on the grid.

    For all ``T`` trials and ``G`` grid values at once (one batched model of ``T G`` problems),
    the Laplace evidence ``log q(Y)`` plus the log prior; each trial takes its best grid value.
    ``model``'s kernel must be a :class:`~torchpref.models.kernels.FixedRBFKernel` with ``T`` values.

    Returns:
        ``T`` chosen grid indices.
    """
    ls, os_, prior = _grid(dim)
    T, G = model.num_trials, ls.numel()
    template = copy.deepcopy(model.model)  # its likelihoods, a kernel of T G values
    template.covar_module = FixedRBFKernel(ls.repeat(T), os_.repeat(T))
    grid = BatchedPreferenceGP(template, [model.data(b) for b in range(T) for _ in range(G)])
    with torch.no_grad():
        evidence = grid.model.log_marginal_likelihood().reshape(T, G)
    score = torch.where(torch.isfinite(evidence), evidence + prior, -math.inf)
    best = score.argmax(-1)
    model.covar_module.lengthscale = ls[best]
    model.covar_module.outputscale = os_[best]
    return best


def effort_costs(effort: str) -> dict[str, float]:
    """The loop's and the selectors' ``{"rating", "ranking"}`` costs of the effort model ``effort``."""
    if effort not in EFFORTS:
        raise ValueError(f"unknown effort model {effort!r}; choose from {list(EFFORTS)}.")
    model = EFFORTS[effort]
    return {"rating": RATING_COST, "ranking": RANKING_COST} if model is None else model.costs(M)


def effort_budgets(effort: str) -> tuple[float, ...]:
    """The efforts the verdicts are taken at: :data:`CHECKPOINTS` ratings' worth."""
    rating = effort_costs(effort)["rating"]
    return tuple(round(rating * q, 9) for q in CHECKPOINTS)


def _start_model(family: Family, condition: str, x0s: list[torch.Tensor], firsts: list[int]) -> BatchedPreferenceGP:
    settings = model_settings(family)
    models = [runner.make_model(x0, torch.tensor([[f, 1 - f]]), settings) for x0, f in zip(x0s, firsts)]
    if condition == "fixed":
        return BatchedPreferenceGP.from_models(models)
    T = len(models)
    ls, os_, prior = _grid(family.dim)
    start = int(prior.argmax())  # before any refit: the prior's mode on the grid
    kernel = FixedRBFKernel(ls[start].expand(T).clone(), os_[start].expand(T).clone())
    template = PreferenceGP(
        x0s[0],
        torch.tensor([[firsts[0], 1 - firsts[0]]]),
        covar_module=kernel,
        comparison_noise=settings["comparison_noise"],
        rating_scale=settings["rating_scale"],
        rating_precision=settings["rating_precision"],
    )
    datas = [m.data for m in models if isinstance(m.data, PreferenceData)]
    if len(datas) != len(models):
        raise ValueError("the suite's trial models must each be one problem (PreferenceData), not batched.")
    return BatchedPreferenceGP(template, datas)


def _suite_metrics(eval_X: torch.Tensor, f_true: torch.Tensor, u_true: torch.Tensor):
    """The suite's metrics of a batched model, per trial: WRMS and true positives of the expected
    ratings at ``eval_X``, and the regret of the item of highest posterior mean (relative to the
    best item's margin over the median)."""
    best = f_true.max(-1).values
    margin = (best - f_true.median(-1).values).clamp_min(1e-12)

    def metrics(model) -> dict[str, torch.Tensor]:
        mean, var = model.marginals(eval_X)
        est = model.likelihood.rating.expected_rating(mean, var)
        chosen = f_true.gather(1, mean.argmax(-1, keepdim=True)).squeeze(-1)
        return {
            "wrms": wrms(est, u_true),
            "tp": true_positives(est, u_true, k=TOP_K).to(est),
            "regret": (best - chosen) / margin,
        }

    return metrics


def run_batch(
    trial_seeds: tuple[int, ...], family_name: str, condition: str, queries: int, strategy: str, effort: str = "units"
) -> list[dict[str, Any]]:
    r"""Trials of one family, condition and strategy at once (one batched model).

    Returns:
        One ``{strategy: {"wrms", "tp", "regret", "cost": [Q + 1], "kinds": [Q], "cpu_s"}}`` per
        seed (``cpu_s``: the batch's CPU time of this process, per trial).
    """
    runner.single_threaded()
    cpu0 = time.process_time()
    family = ALL_FAMILIES[family_name]
    costs = effort_costs(effort)
    setups = [setup(family, s, EFFORTS[effort]) for s in trial_seeds]
    firsts = [s.user.choose(s.x0) for s in setups]
    eval_X = torch.stack([s.eval_X for s in setups])
    f_true = torch.stack([s.f_true for s in setups])
    metrics = _suite_metrics(eval_X, f_true, torch.stack([s.u_true for s in setups]))

    def refit(step: int, model: BatchedPreferenceGP) -> None:
        if condition == "learned" and step + 1 in REFIT_AFTER:
            learn_kernel(model, family.dim)

    with torch.inference_mode():
        model = _start_model(family, condition, [s.x0 for s in setups], firsts)
        gens = [torch.Generator().manual_seed(s.selector_seed) for s in setups]
        candidates: Candidates
        if family.pool is None:
            candidates = BoxCandidates(
                torch.tensor([[0.0] * family.dim, [1.0] * family.dim], dtype=torch.float64), NUM_CANDIDATES
            )
        else:
            candidates = _TrialPools([s.pool for s in setups], gens)
        hists = run_active_learning_batch(
            model,
            [s.user for s in setups],
            candidates,
            make_selector(strategy, effort),
            queries,
            generators=gens,
            metrics=metrics,
            costs=costs,
            refit=refit,
        )
    cpu = (time.process_time() - cpu0) / len(hists)
    return [
        {
            strategy: {
                **{k: h.metric(k) for k in METRICS},
                "cost": h.cumulative_cost(),
                "kinds": [r.query.kind for r in h.records],
                "cpu_s": cpu,
            }
        }
        for h in hists
    ]


class _TrialPools(Candidates):
    """Each trial's own finite pool (:class:`~torchpref.data.queries.FinitePool`), found by its generator."""

    def __init__(self, pools: Sequence[torch.Tensor | None], generators: Sequence[torch.Generator]):
        if any(p is None for p in pools):
            raise ValueError("every trial of a pool family needs its pool, got None.")
        self._by_generator = {id(g): FinitePool(p) for p, g in zip(pools, generators) if p is not None}

    def draw(self, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor | None]:
        return self._by_generator[id(generator)].draw(generator)


def make_selector(name: str, effort: str = "units") -> Selector:
    """The suite's selector ``name`` (:func:`~torchpref.experiments.runner.make_selector` with
    ``m``, ``gamma`` and the costs of the effort model ``effort``)."""
    costs = effort_costs(effort)
    return runner.make_selector(name, m=M, gamma=GAMMA, rating_cost=costs["rating"], ranking_cost=costs["ranking"])


def run_suite(
    families: Sequence[str] | None = None,
    trials: int = 50,
    queries: int = 20,
    seed: int = 0,
    out: str | Path | None = "benchmarks/results",
    executor: Executor | None = None,
    *,
    workers: int | None = None,
    strategies: Sequence[str] | None = None,
    conditions: Sequence[str] = CONDITIONS,
    batch_size: int = 50,
    progress: bool = True,
    effort: str = "units",
) -> dict[str, Any]:
    r"""Run the suite and (if ``out`` is given) write ``suite.json``, ``suite.csv``,
    ``suite_summary.json`` and the figures ``suite_fixed.png`` / ``suite_learned.png``.

    Args:
        families: names from :data:`~torchpref.experiments.families.ALL_FAMILIES` or groups of
            :data:`FAMILY_GROUPS` (default: the idealised families, :data:`~torchpref.experiments.families.FAMILIES`).
        trials: paired trials per family and condition.
        queries: queries per trial.
        seed: the run's seed (per-trial seeds derive from it, one set per family).
        out: output folder, or ``None``.
        executor: any ``concurrent.futures.Executor`` (a Dask client's ``get_executor()``, ...).
        workers: processes of the default pool.
        strategies: any of the registry's strategies
            (:data:`~torchpref.experiments.runner.STRATEGIES`; default :data:`STRATEGIES`).
        conditions: ``"fixed"`` and/or ``"learned"``.
        batch_size: trials per executor call.
        progress: show a progress bar.
        effort: the effort model (:data:`EFFORTS`): what a query costs the loop and the selectors
            that weigh effort, and the efforts of the verdicts (:func:`effort_budgets`).

    Returns:
        ``{"families", "conditions", "strategies", "trials", "queries", "curves", "summary"}``.
    """
    families = _checked(FAMILIES if families is None else families, conditions)
    effort_costs(effort)  # a known effort model
    default = REALISTIC_STRATEGIES if all(f in REALISTIC_FAMILIES for f in families) else STRATEGIES
    strategies = runner.check_run(queries, strategies, default, batch_size)
    seeds = {f: runner.trial_seeds(seed + 7919 * i, trials) for i, f in enumerate(ALL_FAMILIES) if f in families}
    keys = [
        (f, c, s, i) for f in families for c in conditions for s in strategies for i in range(0, trials, batch_size)
    ]
    keys.sort(key=lambda k: (k[1] != "learned", k[2] != "info per effort"))  # the costliest first
    tasks = [(tuple(seeds[f][i : i + batch_size]), f, c, queries, s, effort) for f, c, s, i in keys]
    t0 = time.perf_counter()
    parts = runner.run_trials(
        run_batch,
        tasks,
        executor=executor,
        progress=progress,
        workers=workers,
        description="suite trials",
        sizes=[len(t[0]) for t in tasks],
    )
    wall = time.perf_counter() - t0
    results: dict[tuple[str, str], list[dict[str, Any]]] = {
        (f, c): [{} for _ in range(trials)] for f in families for c in conditions
    }
    for (f, c, s, i), part in zip(keys, parts):
        runner.place_records(results[f, c], i, s, part)
    checkpoints = sorted({q for q in CHECKPOINTS if q <= queries} | {queries})
    summary = summarise(results, strategies, METRICS, budgets=effort_budgets(effort), checkpoints=checkpoints)
    cpu = sum(r[s]["cpu_s"] for trials_ in results.values() for r in trials_ for s in strategies)
    summary.update(trials=trials, queries=queries, seed=seed, wall_time_s=wall, cpu_time_s=cpu, workers=workers)
    summary["settings"] = _settings(families, effort)
    if out is not None:
        Path(out).mkdir(parents=True, exist_ok=True)
        trials_by_cell = {f"{f}/{c}": v for (f, c), v in results.items()}
        write_json(Path(out) / "suite_trials.json", trials_by_cell, stamp=False)  # keyed by cell
        write_suite_files(Path(out), summary, families, conditions, strategies, METRICS)
    result = {"families": families, "conditions": list(conditions), "strategies": strategies, "trials": trials}
    return {**result, "queries": queries, "summary": summary}


def _checked(families: Iterable[str], conditions: Sequence[str]) -> list[str]:
    """``families`` as a list (groups of :data:`FAMILY_GROUPS` expanded), each a known family and
    each condition a known one.

    Raises:
        ValueError: naming an unknown family or condition.
    """
    families = list(dict.fromkeys(g for f in families for g in FAMILY_GROUPS.get(f, [f])))
    for f in families:
        if f not in ALL_FAMILIES:
            raise ValueError(
                f"unknown family {f!r}; choose from {list(ALL_FAMILIES)} or a group {list(FAMILY_GROUPS)}."
            )
    for c in conditions:
        if c not in CONDITIONS:
            raise ValueError(f"unknown condition {c!r}; choose from {list(CONDITIONS)}.")
    return list(families)


def _settings(families: list[str], effort: str = "units") -> dict[str, Any]:
    """The run's settings as the summary records them."""
    fams = ALL_FAMILIES  # every family, realistic ones included
    return {
        "m": M,
        "gamma": GAMMA,
        "top_k": TOP_K,
        "refit_after": REFIT_AFTER,
        "effort": effort,
        "costs": effort_costs(effort),
        "effort_budgets": effort_budgets(effort),
        "families": {
            f: {
                "dim": fams[f].dim,
                "description": fams[f].description,
                "model": model_settings(fams[f]),
                "pool": fams[f].pool,
                "likert": fams[f].likert,
                "realistic": fams[f].realistic,
            }
            for f in families
        },
    }


def run(args: argparse.Namespace) -> int:
    """``torchpref reproduce suite``: run and report."""
    res = run_suite(
        families=args.families,
        trials=args.trials,
        queries=args.queries,
        seed=args.seed,
        out=args.out,
        workers=getattr(args, "workers", None),
        strategies=getattr(args, "strategies", None),
        effort=getattr(args, "effort", "units"),
    )
    s = res["summary"]
    print(
        f"{len(res['families'])} families x {len(res['conditions'])} conditions x {args.trials} trials x "
        f"{args.queries} queries in {s['wall_time_s']:.1f} s ({s['cpu_time_s']:.0f} s of trial CPU time); "
        f"files in {args.out}"
    )
    for line in s["verdict_lines"]:
        print("  " + line)
    return 0
