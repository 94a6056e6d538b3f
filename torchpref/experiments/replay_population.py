r"""The replay of real people's answers (:mod:`~torchpref.experiments.replay`) with the population's
prior: each person is started from the population fitted without them (leave-people-out).

The people of a data set are split into ``folds`` seeded folds (:func:`fold_population`, also the
twins' folds: :mod:`~torchpref.experiments.twins`); for each fold the population is fitted on the
other folds' people (at most :data:`TRAIN_CAP`, a seeded sample) and ``people // folds`` of the
fold's people with at least 9 choices (a seeded sample) are replayed, each on ``splits`` splits,
their model ``pop.person_model(their items and the answers revealed)``. Random is the mean of
``random_orders`` random orders of the same pool (its expected curve), so that a selector is
compared with what random does on average, not with one lucky or unlucky order.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from torch import Tensor

from torchpref.data.preference_data import PreferenceData
from torchpref.experiments.replay import Person, load, replay_person
from torchpref.models.preference_gp import PreferenceGP
from torchpref.models.recipe import NO_TIES_OFFERED
from torchpref.population.fit import fit_population
from torchpref.population.io import load_population, save_population
from torchpref.population.model import Population
from torchpref.selection.strategies import Selector

__all__ = ["TRAIN_CAP", "fold_population", "person_data", "run_population_replay"]

#: the most training people a population is fitted on (rail's 1,785 distinct trips cost N^3)
TRAIN_CAP = {"electricity": 1000, "rail": 100}


def person_data(p: Person, choices: Sequence[tuple[tuple[int, ...], int]] | None = None) -> PreferenceData:
    """A person's items and (all, or the given) choices, each best-of-``m`` as its ``m - 1`` comparisons."""
    choices = p.choices if choices is None else choices
    C = [[rows[j], r] for rows, j in choices for r in rows if r != rows[j]]
    return PreferenceData.create(p.X, torch.tensor(C, dtype=torch.long) if C else None)


def fold_population(
    name: str, people: Sequence[Person], fold: int, folds: int, seed: int, cache: Path | None, max_iter: int = 40
) -> tuple[Population, list[Person]]:
    """The population fitted without fold ``fold`` of ``people`` (a seeded split into ``folds``;
    at most :data:`TRAIN_CAP` training people) and the fold's people; cached in ``cache``."""
    perm = torch.randperm(len(people), generator=torch.Generator().manual_seed(seed)).tolist()
    held = [people[i] for i in perm[fold::folds]]
    others = [people[i] for k, i in enumerate(perm) if k % folds != fold]
    pick = torch.randperm(len(others), generator=torch.Generator().manual_seed(seed + 1 + fold))
    train = [others[i] for i in sorted(pick[: TRAIN_CAP.get(name, 100)].tolist())]
    path = None if cache is None else Path(cache) / f"{name}_fold{fold}of{folds}_seed{seed}_iter{max_iter}.pt"
    if path is not None and path.is_file():
        return load_population(path), held
    # the data sets' people chose without a "no preference" option: strict choices are the probit's
    pop = fit_population([person_data(p) for p in train], max_iter=max_iter, model=NO_TIES_OFFERED)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        save_population(pop, path)
    return pop, held


def _person_model(pop: Population) -> Callable[[Tensor, list[list[int]]], PreferenceGP]:
    def make(X: Tensor, comparisons: list[list[int]]) -> PreferenceGP:
        C = torch.tensor(comparisons, dtype=torch.long) if comparisons else None
        return pop.person_model(PreferenceData.create(X, C))

    return make


def _mean_curves(runs: list[dict[str, list[float]]]) -> dict[str, list[float]]:
    return {k: [sum(r[k][i] for r in runs) / len(runs) for i in range(len(runs[0][k]))] for k in runs[0]}


def run_population_replay(
    data: str | os.PathLike,
    selectors: dict[str, Callable[[int], Selector]],
    datasets: Sequence[str] = ("electricity", "rail"),
    people: int = 60,
    splits: int = 3,
    seed: int = 0,
    *,
    folds: int = 3,
    random_orders: int = 5,
    cache: str | os.PathLike | None = None,
    progress: bool = True,
    on_row: Callable[[dict], object] | None = None,
) -> list[dict]:
    """Every selector on ``people`` people per data set (``people // folds`` of each fold), each
    started from the population fitted without their fold: one row per (data set, person, split,
    selector) with its curves (random's: the mean of ``random_orders`` orders)."""
    from tqdm.auto import tqdm

    cache_dir = Path(cache) if cache is not None else Path.home() / ".cache" / "torchpref" / "twins"
    rows: list[dict] = []
    bar = tqdm(total=len(datasets) * folds, disable=not progress, desc="replay folds", mininterval=5)
    for ds in datasets:
        everyone = load(ds, data)
        for f in range(folds):
            pop, held = fold_population(ds, everyone, f, folds, seed, cache_dir)
            held = [p for p in held if len(p.choices) >= 9]
            pick = torch.randperm(len(held), generator=torch.Generator().manual_seed(seed + 31 * f))
            for person in [held[i] for i in sorted(pick[: people // folds].tolist())]:
                rows += _replay_one(ds, person, pop, selectors, splits, seed, random_orders, on_row)
            bar.update()
    bar.close()
    return rows


def _replay_one(ds, person, pop, selectors, splits, seed, random_orders, on_row) -> list[dict]:
    """One person's rows: every selector on every split (random: the mean of its orders)."""
    m = max(len(r) for r, _ in person.choices)
    make = _person_model(pop)
    rows = []
    for s in range(splits):
        for name, factory in selectors.items():
            t = time.perf_counter()
            orders = random_orders if name == "random" else 1
            runs = [replay_person(person, s, factory(m), seed, make, order=k) for k in range(orders)]
            curves = _mean_curves(runs)
            row = dict(dataset=ds, person=person.pid, split=s, selector=name, seconds=time.perf_counter() - t, **curves)
            rows.append(row)
            if on_row is not None:
                on_row(row)
    return rows


def run(args: argparse.Namespace) -> int:
    """``torchpref reproduce replay``: with ``--population``, the replay with the population's
    prior (this module); without, :func:`torchpref.experiments.replay.run`."""
    from torchpref.experiments import replay

    if not getattr(args, "population", False):
        return replay.run(args)
    torch.set_num_threads(1)
    out, data = replay.prepare(args)
    start, load0 = time.time(), os.getloadavg()[0]
    with open(out / "replay_rows.jsonl", "w") as f:
        chosen = {k: replay.SELECTORS[k] for k in dict.fromkeys(["random", *args.selectors])}
        rows = run_population_replay(
            data, chosen, tuple(args.datasets), args.people, args.splits, args.seed, folds=args.folds,
            random_orders=args.random_orders, cache=args.cache, on_row=replay.keeper(f),
        )  # fmt: skip
    meta = dict(people=args.people, splits=args.splits, seed=args.seed, folds=args.folds)
    meta.update(random_orders=args.random_orders, train_cap=TRAIN_CAP)
    meta["model"] = "pop.person_model of the population fitted without the person's fold (leave-people-out)"
    replay.write_files(rows, out, meta, start, load0)
    return 0
