r"""Twins of real people: how many questions does each selector need for a new person of a real
population, with and without the population's prior?

For each data set of the replay (:mod:`~torchpref.experiments.replay`: Train's electricity
suppliers, the Dutch rail trips) and each of ``folds`` seeds, the people are split into
``folds`` seeded folds; the population (:func:`torchpref.fit_population`) is fitted on the other
folds' people (leave-people-out; at most :data:`TRAIN_CAP` of them, a seeded sample), and
``twins`` twins are drawn from it (:func:`torchpref.simulation.twins.draw_twin`): a new person's
utility from the population, the deviation drawn with another kernel than the learner's (a
rougher Matérn, other lengthscales and spread), answering as a realistic person
(:meth:`~torchpref.simulation.raters.RaterProfile.typical`: lapses, rating offset, gain, drift and
partial use of the scale; 1-7 Likert ratings) best-of-:data:`M` choices and ratings.

**The pool** is the data set's design space: every distinct item of the data set (electricity's
35 supplier profiles), or, where there are too many to value jointly (rail's 1,785 trips), a
seeded sample of :data:`POOL_SIZE` of them per twin. Every selector asks :data:`QUERIES`
questions among the pool's items.

**The learner**, per condition: ``"population"``: the person model of the population fitted
without the twin's fold (``pop.person_model``: the population's mean and covariance), the nominal
person's likelihoods (no offset, gain 1, no lapses; Beta ratings of precision
:data:`LEARNER_PRECISION` read at the Likert box's centre); ``"no population"``: the same model
with a zero mean and the hierarchical kernel ``k_m + k_g`` (the population's hyperparameters,
not its mean). Hyperparameters are fixed. All twins of a batch run as one batched model.

**Scores** after each answer: ``concordance``, the share of the pool's item pairs that the
posterior mean orders as the true utility does (ties 1/2); ``value``, the true utility of the
recommended item (largest posterior mean) relative to the pool, ``(f(rec) - median f) / (max f -
median f)`` (1: the best); ``log_loss`` of :data:`FRESH` fresh pairwise answers of the twin (its
noise and lapses), predicted by the model. Seconds per answer come from the effort models of
docs/suite.md (``plain``, ``trajectories``); selectors that weigh effort run once per effort model.
Summary, tests and files: :mod:`~torchpref.experiments.twins_report`. Results: docs/selection.md.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from gpytorch.kernels import AdditiveKernel, Kernel
from gpytorch.means import Mean
from torch import Tensor

from torchpref.data.queries import Candidates
from torchpref.experiments import runner
from torchpref.experiments.replay import Person, load
from torchpref.experiments.replay_population import TRAIN_CAP, fold_population
from torchpref.experiments.twins_report import EFFORTS, append_rows, read_rows, report
from torchpref.models.batch import BatchedPreferenceGP
from torchpref.models.preference_gp import PreferenceGP
from torchpref.population.model import Population
from torchpref.selection.active import run_active_learning_batch
from torchpref.simulation.raters import RaterProfile, RealisticUser
from torchpref.simulation.twins import PoolUtility, TwinDraw, draw_twin, population_mean_posterior

__all__ = ["Twin", "make_twins", "run_twins", "twin_batch"]

DATASETS = ("electricity", "rail")
CONDITIONS = ("population", "no population")
#: items per ranking (the session default for a pool of more than 5 items; the suite's)
M = 5
QUERIES = 20
FOLDS = 3
#: the pool's items: all of the data set's (``None``) or a seeded sample of this many per twin
POOL_SIZE = {"electricity": None, "rail": 48}
FRESH = 100
#: the scores after each answer (module notes)
SCORES = ("concordance", "value", "log_loss")
LIKERT = 7
LEARNER_PRECISION = 20.0
#: the selectors a run compares by default (names of :data:`~torchpref.experiments.runner.STRATEGIES`)
SELECTORS = (
    "random mixed",
    "random rankings",
    "UCBC",
    "utility info",
    "clipped profile",
    "combination",
    "combination (profile)",
    "information + profile",  # issue 41's default (issue 50's: torchpref.default_selector)
    "qEUBO",
)
BASELINE = "random mixed"
#: the random baselines, whose curves are the mean of :data:`RANDOM_REPEATS` runs (their expected curve)
RANDOM = ("random mixed", "random rankings", "random ratings")
RANDOM_REPEATS = 4


@dataclass
class Twin:
    """One twin: its pool (``N x d``), true utility there, how it answers, its fresh pairs
    (``P x 2``: the row chosen, the other) and what was drawn."""

    X: Tensor
    utility: PoolUtility
    profile: RaterProfile
    fresh: Tensor
    draw: TwinDraw
    user_seed: int
    selector_seed: int


def nominal_spread(pop: Population, X: Tensor) -> float:
    r"""The population's typical spread of a new person's utility over the items ``X``:
    ``sqrt(mean prior variance + variance of the prior mean)``: the learner's and the twins'
    rating scale ``sigma_B`` (so ratings use the scale), the same for every twin of a population."""
    with torch.no_grad():
        post = pop.person_model(X).posterior(X)
        mean, var = post.mean.reshape(-1), post.variance.reshape(-1)
    return float((var.mean() + mean.var()).sqrt())


def make_twins(pop: Population, items: Tensor, name: str, fold: int, count: int, seed: int) -> list[Twin]:
    """``count`` twins of ``pop`` over the data set's distinct ``items`` (module notes)."""
    scale = nominal_spread(pop, items if items.shape[0] <= 400 else items[:400])
    noise = float(pop.settings["comparison_noise"])
    out = []
    size = POOL_SIZE.get(name)
    whole = size is None or size >= items.shape[0]
    prior = population_mean_posterior(pop, items) if whole else None  # one pool for every twin
    for j in range(count):
        g = torch.Generator().manual_seed(hash_seed(seed, name, fold, j))
        X = items if whole else items[torch.randperm(items.shape[0], generator=g)[:size]]
        utility, draw = draw_twin(pop, X, g, prior)
        profile = RaterProfile.typical(
            g, spread=float(utility.f.std()), rating_scale=scale, comparison_noise=noise, levels=LIKERT
        )
        fresh = _fresh_pairs(utility.f, profile, g)
        seeds = torch.randint(0, 2**62, (2,), generator=g).tolist()
        out.append(Twin(X, utility, profile, fresh, draw, seeds[0], seeds[1]))
    return out


def hash_seed(seed: int, name: str, fold: int, j: int) -> int:
    """A twin's seed from the run's seed, the data set, the fold and its number (stable across runs)."""
    return (seed * 1_000_003 + sum(ord(c) * 31**i for i, c in enumerate(name)) * 7919 + fold * 104_729 + j) % 2**62


def _fresh_pairs(f: Tensor, profile: RaterProfile, g: torch.Generator) -> Tensor:
    """:data:`FRESH` random pairs answered by the twin (lapses, then noisy utilities): ``P x 2``,
    the chosen row first."""
    N = f.shape[0]
    a = torch.randint(N, (FRESH,), generator=g)
    b = (a + torch.randint(1, N, (FRESH,), generator=g)) % N
    noisy = torch.randn(FRESH, 2, generator=g, dtype=f.dtype) * profile.comparison_noise
    first = (f[a] + noisy[:, 0]) >= (f[b] + noisy[:, 1])
    lapse = torch.rand(FRESH, generator=g, dtype=f.dtype) < profile.lapse_rate
    first = torch.where(lapse, torch.rand(FRESH, generator=g, dtype=f.dtype) < 0.5, first)
    return torch.stack([torch.where(first, a, b), torch.where(first, b, a)], -1)


class PriorAtItems:
    r"""A prior known at finitely many items (a batch's pools and the zero vector, the batch's
    padding): the mean and covariance there of ``model_of(items)`` before any answer,
    computed once, looked up by exact match (an item that is not one of them is refused by name).
    For the population condition: ``pop.person_model``'s prior at the pools, without the
    population's ``N^3``-sized products at every prediction (rail's ~800 distinct items)."""

    def __init__(self, model_of: Callable[[Tensor], PreferenceGP], items: Tensor):
        U = torch.unique(torch.cat([items, torch.zeros(1, items.shape[-1], dtype=items.dtype)]), dim=0)
        with torch.no_grad():
            prior = model_of(U).posterior(U).distribution  # a model of these items, no answers: the prior
        self.U, self.mean = U, prior.mean.reshape(-1)
        self.cov = prior.covariance_matrix.reshape(U.shape[0], U.shape[0])

    def rows(self, x: Tensor) -> Tensor:
        flat = x.reshape(-1, x.shape[-1])
        dist, rows = (flat.unsqueeze(-2) - self.U.to(flat)).abs().amax(-1).min(-1)
        if bool((dist > 1e-12).any()):
            raise ValueError(f"item {flat[dist > 1e-12][0].tolist()} is not one of the prior's items.")
        return rows.reshape(x.shape[:-1])


class _LookupMean(Mean):
    def __init__(self, prior: PriorAtItems):
        super().__init__()
        self.prior = prior

    def forward(self, x: Tensor) -> Tensor:
        return self.prior.mean.to(x)[self.prior.rows(x)]


class _LookupKernel(Kernel):
    def __init__(self, prior: PriorAtItems):
        super().__init__()
        self.prior = prior

    def forward(self, x1: Tensor, x2: Tensor, diag: bool = False, last_dim_is_batch: bool = False, **params) -> Tensor:
        r1, r2 = self.prior.rows(x1), self.prior.rows(x2)
        cov = self.prior.cov.to(x1)
        if diag:
            return cov[r1, r2]
        return cov[r1.unsqueeze(-1), r2.unsqueeze(-2)]


def learner(pop: Population, twins: Sequence[Twin], condition: str, scale: float) -> BatchedPreferenceGP:
    """The twins' starting model (no answers) in ``condition`` (module notes), batched. The
    population condition's prior is ``pop.person_model``'s, looked up at the pools (:class:`PriorAtItems`)."""
    settings: dict[str, Any] = dict(rating_scale=scale, rating_precision=LEARNER_PRECISION)
    if condition == "population":
        prior = PriorAtItems(pop.person_model, torch.cat([t.X for t in twins]))
        models = [
            PreferenceGP(t.X, covar_module=_LookupKernel(prior), mean_module=_LookupMean(prior), **_likelihoods(pop), **settings)
            for t in twins
        ]  # fmt: skip
    elif condition == "no population":
        kernel = AdditiveKernel(pop.k_m, pop.k_g)
        models = [PreferenceGP(t.X, covar_module=kernel, **_likelihoods(pop), **settings) for t in twins]
    else:
        raise ValueError(f"unknown condition {condition!r}; choose from {list(CONDITIONS)}.")
    return BatchedPreferenceGP.from_models(models)


def _likelihoods(pop: Population) -> dict:
    """The population's person-model settings but the ratings' (the learner's nominal person's):
    its comparison noise, rating levels and whether ties are offered (:attr:`Population.model_settings`)."""
    recipe = pop.model_settings
    return dict(
        comparison_noise=recipe.comparison_noise, rating_levels=recipe.rating_levels, ties_offered=recipe.ties_offered
    )


def twin_metrics(twins: Sequence[Twin], noise: float) -> Callable[[BatchedPreferenceGP], dict[str, Tensor]]:
    """The scores of a batched model of ``twins`` (module notes), ``T`` values each."""
    X = torch.stack([t.X for t in twins])
    f = torch.stack([t.utility.f for t in twins])
    fresh = torch.stack([t.fresh for t in twins])  # T x P x 2
    iu = torch.triu_indices(f.shape[1], f.shape[1], 1)
    true_sign = torch.sign(f[:, iu[0]] - f[:, iu[1]])
    best, median = f.max(-1).values, f.median(-1).values

    def metrics(model: BatchedPreferenceGP) -> dict[str, Tensor]:
        mean, cov = model.joint(X)
        d = mean[:, iu[0]] - mean[:, iu[1]]
        agree = torch.where(d.abs() < 1e-12, 0.5, (torch.sign(d) == true_sign).to(d))
        rec = f.gather(1, mean.argmax(-1, keepdim=True)).squeeze(-1)
        w, lo = fresh[..., 0], fresh[..., 1]
        var = cov.diagonal(dim1=-2, dim2=-1)
        v = var.gather(1, w) + var.gather(1, lo) - 2 * cov.flatten(1).gather(1, w * cov.shape[-1] + lo)
        z = (mean.gather(1, w) - mean.gather(1, lo)) / (2 * noise**2 + v.clamp_min(0)).sqrt()
        return {
            "concordance": agree.mean(-1),
            "value": (rec - median) / (best - median).clamp_min(1e-12),
            "log_loss": -torch.special.log_ndtr(z).mean(-1),
        }

    return metrics


class _Pools(Candidates):
    """Each twin's own pool, found by its generator."""

    def __init__(self, twins: Sequence[Twin], generators: Sequence[torch.Generator]):
        self._pools = {id(g): t.X for t, g in zip(twins, generators)}

    def draw(self, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        X = self._pools[id(generator)]
        return X, torch.arange(X.shape[0])


def twin_batch(
    pop: Population,
    twins: Sequence[Twin],
    condition: str,
    strategy: str,
    effort: str,
    queries: int = QUERIES,
    repeats: int = 1,
) -> list[dict]:
    """One strategy on a batch of twins: per twin ``{"concordance", "value", "log_loss": [Q + 1],
    "kinds": [Q], "seconds": [Q] (the twin's own response times), "cpu_s"}``. With ``repeats > 1``
    (a random baseline: its expected curve) the run is repeated with other selector and answer
    seeds; the curves are the repeats' means and ``"repeats"`` holds each repeat's curves and kinds."""
    runner.single_threaded()
    cpu0 = time.process_time()
    runs = [_run_once(pop, twins, condition, strategy, effort, queries, r) for r in range(repeats)]
    cpu = (time.process_time() - cpu0) / len(twins)
    out = []
    for j in range(len(twins)):
        recs = [run[j] for run in runs]
        rec = dict(recs[0], cpu_s=cpu)
        if repeats > 1:
            for k in SCORES:
                rec[k] = [sum(r[k][i] for r in recs) / repeats for i in range(queries + 1)]
            rec["repeats"] = [{k: r[k] for k in (*SCORES, "kinds")} for r in recs]
        out.append(rec)
    return out


def _run_once(
    pop: Population, twins: Sequence[Twin], condition: str, strategy: str, effort: str, queries: int, repeat: int
) -> list[dict]:
    """One run of a strategy on a batch of twins (repeat ``r > 0``: other selector and answer seeds)."""
    ranking = EFFORTS[effort].ranking(M)
    scale = twins[0].profile.rating_scale  # the population's nominal spread, every twin's
    selector = runner.make_selector(strategy, m=M, rating_cost=EFFORTS[effort].rating(), ranking_cost=ranking)
    shift = 0 if repeat == 0 else 7919 * repeat + 1
    users = [
        RealisticUser(t.utility, t.profile.with_effort(EFFORTS[effort]), torch.Generator().manual_seed(t.user_seed + shift))
        for t in twins
    ]  # fmt: skip
    gens = [torch.Generator().manual_seed(t.selector_seed + shift) for t in twins]
    with torch.inference_mode():
        model = learner(pop, twins, condition, scale)
        hists = run_active_learning_batch(
            model,
            users,
            _Pools(twins, gens),
            selector,
            queries,
            generators=gens,
            metrics=twin_metrics(twins, float(pop.settings["comparison_noise"])),
            costs=EFFORTS[effort].costs(M),
        )
    return [
        {
            **{k: h.metric(k) for k in SCORES},
            "kinds": [r.query.kind for r in h.records],
            "seconds": [s for _, _, s in u.seconds],
        }
        for h, u in zip(hists, users)
    ]


def run_twins(
    data: str | os.PathLike,
    out: str | os.PathLike,
    *,
    datasets: Sequence[str] = DATASETS,
    twins: int = 20,
    folds: int = FOLDS,
    seed: int = 0,
    strategies: Sequence[str] = SELECTORS,
    conditions: Sequence[str] = CONDITIONS,
    efforts: Sequence[str] = tuple(EFFORTS),
    queries: int = QUERIES,
    progress: bool = True,
    cache: str | os.PathLike | None = None,
) -> list[dict]:
    """Every strategy on every twin, condition and effort model (effort-free strategies once, their
    records serving every effort model): one row per (data set, fold, twin, condition, strategy,
    effort) with its records; rows are also appended to ``out/twins_rows.jsonl`` as they finish
    (a run resumes from it: rows already there are not run again). Fitted populations are kept in
    ``cache`` (default ``~/.cache/torchpref/twins``)."""
    from tqdm.auto import tqdm

    strategies = runner.check_run(queries, strategies, SELECTORS)
    rows_path = Path(out) / "twins_rows.jsonl"
    done = read_rows(rows_path)
    jobs = [(ds, f, c, s, e) for ds in datasets for f in range(folds) for c in conditions for s in strategies
            for e in ((efforts[0],) if s in runner.EFFORT_FREE else efforts)]  # fmt: skip
    bar = tqdm(total=len(jobs) * twins, disable=not progress, desc="twins", unit="twin run", mininterval=5)
    fitted: dict = {}
    for ds, f, c, s, e in jobs:
        key = (ds, f, c, s, e)
        if key in done:
            bar.update(twins)
            continue
        if (ds, f) not in fitted:
            fitted.clear()
            pop, _ = fold_population(ds, load(ds, data), f, folds, seed, _cache_dir(cache))
            fitted[ds, f] = (pop, make_twins(pop, _items(load(ds, data)), ds, f, twins, seed))
        pop, tw = fitted[ds, f]
        recs = twin_batch(pop, tw, c, s, e, queries, RANDOM_REPEATS if s in RANDOM else 1)
        new = [dict(dataset=ds, fold=f, twin=j, condition=c, strategy=s, effort=e, **r) for j, r in enumerate(recs)]
        append_rows(rows_path, new)
        done[key] = new
        bar.update(twins)
    bar.close()
    return [r for rs in done.values() for r in rs]


def _cache_dir(cache: str | os.PathLike | None) -> Path:
    return Path(cache) if cache is not None else Path.home() / ".cache" / "torchpref" / "twins"


def _items(people: Sequence[Person]) -> Tensor:
    """The data set's distinct items (its design space), in a fixed order."""
    return torch.unique(torch.cat([p.X for p in people]), dim=0)


def run(args: argparse.Namespace) -> int:
    """``torchpref reproduce twins``: run and write the files (:mod:`~torchpref.experiments.twins_report`)."""
    torch.set_num_threads(1)
    data = Path(args.data) if args.data else Path(__file__).resolve().parents[2] / "benchmarks" / "studies" / "data"
    if not (data / "electricity.csv.gz").is_file():
        raise FileNotFoundError(f"no data in {data}: give --data (benchmarks/studies/data of a clone).")
    start, load0 = time.time(), os.getloadavg()[0]
    rows = run_twins(
        data, args.out, datasets=args.datasets, twins=args.twins, folds=args.folds, seed=args.seed,
        strategies=args.strategies or SELECTORS, queries=args.queries, cache=getattr(args, "cache", None),
    )  # fmt: skip
    meta = dict(twins=args.twins, folds=args.folds, seed=args.seed, queries=args.queries, m=M, pool=POOL_SIZE)
    meta.update(train_cap=TRAIN_CAP, likert=LIKERT, learner_precision=LEARNER_PRECISION, fresh=FRESH)
    meta.update(wall_s=round(time.time() - start, 1), load_average_start_end=[load0, os.getloadavg()[0]])
    for line in report(rows, Path(args.out), meta, baseline=BASELINE):
        print(line)
    return 0
