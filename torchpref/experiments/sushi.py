r"""Replay real people who both rated and ranked (SUSHI, :mod:`torchpref.experiments.sushi_data`).

Per held-out person and seed, the person's 10 items are split at random into 6 *askable* items and
4 *held-out* items. A policy asks questions about the askable items only, answered from the
person's record: a rating is their 0-4 rating (a Likert level ``1..5`` of the session's scale), a
best-of-``m`` is the item they ranked highest among those shown. After each answer the model's
posterior mean over all 10 items is scored by **concordance**: the share of the pairs that touch a
held-out item ordered as the person ordered them, against their ranking (30 pairs) and against their
ratings (the pairs whose ratings differ; a pair the mean ties counts 1/2).

Answers are priced by the library's effort model (:class:`~torchpref.data.effort.EffortModel`,
plain stimuli): scores are compared at equal answers and at equal seconds (the score after the last
answer within each budget). A rating of an item already rated is not asked: as a
:class:`~torchpref.PreferenceSession` does, the policy then chooses among the unrated items.

Two conditions: ``"none"`` (a session's default model, :data:`~torchpref.models.recipe.DEFAULT_MODEL`)
and ``"population"`` (the population fitted on other people's ratings and rankings, leave-people-out:
the held-out people are never in it; its prior at the 100 items computed once). Two references use
*all* the askable answers at once: the 6 ratings, the ranking of the 6 (its 15 comparisons, as a
sequence of best-of-``m`` answers gives them), and both.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from torchpref.data.effort import EffortModel
from torchpref.data.preference_data import PreferenceData, likert_to_unit, unit_to_likert
from torchpref.data.queries import Query, RatingQuery, ask_user, record_answer
from torchpref.experiments.sushi_data import LEVELS, SushiData, SushiPerson
from torchpref.experiments.twins import PriorAtItems, _LookupKernel, _LookupMean
from torchpref.models.batch import BatchedPreferenceGP
from torchpref.models.preference_gp import PreferenceGP
from torchpref.models.recipe import DEFAULT_MODEL, ModelSettings
from torchpref.population.model import Population
from torchpref.selection.active import _Trial
from torchpref.selection.defaults import named_selector
from torchpref.selection.one_kind import OneKind
from torchpref.selection.strategies import PerEffortSelector, RandomRankings, RandomRatings, Selector

__all__ = [
    "ASKABLE",
    "BUDGETS",
    "CONDITIONS",
    "POLICIES",
    "Split",
    "at_budgets",
    "concordance",
    "person_data",
    "population_prior",
    "references",
    "replay",
    "split",
]

ASKABLE = 6
#: seconds at which policies are compared (two ratings to eight)
BUDGETS = (6.8, 10.2, 13.6, 20.4, 27.2)
CONDITIONS = ("none", "population")
EFFORT = EffortModel.plain()


def _default_only(kind: str) -> Callable[[int], Selector]:
    def make(n: int) -> Selector:
        sel = named_selector("default", n, LEVELS)
        assert isinstance(sel, PerEffortSelector)
        return OneKind(sel, kind)

    return make


#: name -> selector for a pool of ``n`` askable items: every selector the library ships by name,
#: random baselines, and the default restricted to one kind of question
POLICIES: dict[str, Callable[[int], Selector]] = {
    "default": lambda n: named_selector("default", n, LEVELS),
    "ucbc": lambda n: named_selector("ucbc", n, LEVELS),
    "information": lambda n: named_selector("information", n, LEVELS),
    "random": lambda n: named_selector("random", n, LEVELS),
    "random ratings": lambda n: RandomRatings(),
    "random best-of-3": lambda n: RandomRankings(3),
    "random best-of-5": lambda n: RandomRankings(min(5, n)),
    "default (ratings only)": _default_only("rating"),
    "default (rankings only)": _default_only("ranking"),
}


@dataclass(frozen=True)
class Split:
    """One person's split: ``X`` (``10 x d``, their items), ``position`` (each item's place in their
    ranking, 0 = most preferred), ``levels`` (0-4), and the ``askable`` / ``held`` rows."""

    X: Tensor
    position: Tensor
    levels: Tensor
    askable: Tensor
    held: Tensor


def _seed(*parts: object) -> int:
    return int.from_bytes(hashlib.sha256(":".join(map(str, parts)).encode()).digest()[:7], "little")


def split(data: SushiData, person: SushiPerson, key: int, seed: int) -> Split:
    """Person ``key``'s items and a seeded askable / held-out split (the same for every policy)."""
    n = len(person.items)
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(_seed("sushi-split", key, seed)))
    return Split(
        data.X[list(person.items)],
        torch.arange(n),
        torch.tensor(person.levels),
        perm[:ASKABLE].sort().values,
        perm[ASKABLE:].sort().values,
    )


def person_data(s: Split, rows: Tensor | None = None, ratings: bool = True, ranking: bool = True) -> PreferenceData:
    """A person's answers about ``rows`` (default all 10 items) as data: their ratings (Likert
    levels mapped to ``[0, 1]``) and their ranking as the comparisons of successive best-of-``m``."""
    rows = torch.arange(s.X.shape[0]) if rows is None else rows
    order = rows[s.position[rows].argsort()]
    C = torch.tensor([[int(a), int(b)] for k, a in enumerate(order) for b in order[k + 1 :]], dtype=torch.long)
    u = likert_to_unit(s.levels[rows].double() + 1, num_levels=LEVELS)
    return PreferenceData.create(
        s.X,
        C if ranking else None,
        ratings=u if ratings else None,
        rating_index=rows if ratings else None,
    )


class _Recorded:
    """A person answering from their record (module notes)."""

    def __init__(self, s: Split):
        self.s = s

    def _row(self, x: Tensor) -> int:
        d = (self.s.X - x).abs().amax(-1)
        return int(d.argmin())

    def rate(self, x: Tensor) -> float:
        return float(likert_to_unit(self.s.levels[self._row(x)].double() + 1, num_levels=LEVELS))

    def choose(self, X: Tensor) -> int:
        return int(torch.stack([self.s.position[self._row(x)] for x in X]).argmin())


def _pairs(s: Split) -> tuple[Tensor, Tensor, Tensor]:
    """The pairs touching a held-out item, ``P x 2`` ordered by the ranking (preferred first), the
    same pairs ordered by the ratings, and which of them the ratings separate."""
    held = set(s.held.tolist())
    P = [(i, j) for i in range(len(s.position)) for j in range(i + 1, len(s.position)) if i in held or j in held]
    by_rank = torch.tensor([(i, j) if s.position[i] < s.position[j] else (j, i) for i, j in P])
    by_rating = torch.tensor([(i, j) if s.levels[i] >= s.levels[j] else (j, i) for i, j in P])
    return by_rank, by_rating, s.levels[by_rating[:, 0]] != s.levels[by_rating[:, 1]]


def concordance(mean: Tensor, pairs: Tensor, mask: Tensor | None = None) -> Tensor:
    """``T`` concordances of means ``T x n`` with ``T x P x 2`` ordered pairs (ties 1/2), over ``mask``."""
    d = mean.gather(1, pairs[..., 0]) - mean.gather(1, pairs[..., 1])
    agree = torch.where(d.abs() <= 1e-9, 0.5, (d > 0).to(mean))
    if mask is None:
        return agree.mean(-1)
    w = mask.to(mean)
    return (agree * w).sum(-1) / w.sum(-1).clamp_min(1.0)


def _metrics(splits: Sequence[Split]) -> Callable[[Tensor], dict[str, Tensor]]:
    parts = [_pairs(s) for s in splits]
    rank = torch.stack([p[0] for p in parts])
    rating = torch.stack([p[1] for p in parts])
    mask = torch.stack([p[2] for p in parts])

    def metrics(mean: Tensor) -> dict[str, Tensor]:
        return {"ranking": concordance(mean, rank), "ratings": concordance(mean, rating, mask)}

    return metrics


def _start(
    splits: Sequence[Split], prior: PriorAtItems | None, settings: ModelSettings = DEFAULT_MODEL
) -> list[PreferenceGP]:
    """The starting models, no answers: a session's model of ``settings`` (default a session's
    default, :data:`~torchpref.models.recipe.DEFAULT_MODEL`), or with the population's prior."""
    if prior is None:
        return [settings.session_model(s.X) for s in splits]
    return [
        PreferenceGP(s.X, covar_module=_LookupKernel(prior), mean_module=_LookupMean(prior), **settings.model_kwargs())
        for s in splits
    ]


def population_prior(pop: Population, data: SushiData) -> PriorAtItems:
    """The population's prior at the 100 items, computed once."""
    return PriorAtItems(pop.person_model, data.X)


def replay(
    splits: Sequence[Split],
    policy: str,
    prior: PriorAtItems | None,
    num_queries: int,
    seed: int,
    settings: ModelSettings = DEFAULT_MODEL,
) -> list[dict]:
    """One policy over a batch of people (``splits``): per person the scores after ``0..Q`` answers
    (``"ranking"``, ``"ratings"``), the kinds asked, each answer's seconds and the re-asked ratings avoided."""
    T = len(splits)
    selector = POLICIES[policy](ASKABLE)
    models = BatchedPreferenceGP.from_models(_start(splits, prior, settings))
    gens = [torch.Generator().manual_seed(_seed("sushi-policy", policy, seed, b)) for b in range(T)]
    pools = [s.X[s.askable] for s in splits]
    users = [_Recorded(s) for s in splits]
    metrics = _metrics(splits)
    Xall = torch.stack([s.X for s in splits])
    rated: list[set[int]] = [set() for _ in range(T)]
    out: list[dict[str, Any]] = [
        {"ranking": [], "ratings": [], "kinds": [], "seconds": [], "redirected": 0} for _ in range(T)
    ]

    def measure() -> None:
        mean, _ = models.joint(Xall)
        for k, v in metrics(mean).items():
            for b in range(T):
                out[b][k].append(float(v[b]))

    with torch.no_grad():
        measure()
        for step in range(num_queries):
            X = torch.stack(pools)
            queries = selector.select_batch(models, X, [None] * T, step, num_queries, gens)
            for b, q in enumerate(queries):
                q = _unrated(selector, models, q, pools[b], rated[b], b, step, num_queries, gens[b], out[b])
                answer = ask_user(users[b], q)
                record_answer(_Trial(models, b), q, answer)
                if isinstance(q, RatingQuery):
                    rated[b].add(_pool_row(pools[b], q.item))
                out[b]["kinds"].append(q.kind)
                out[b]["seconds"].append(EFFORT.rating() if q.kind == "rating" else EFFORT.ranking(q.items.shape[0]))
            measure()
    return out


def _pool_row(pool: Tensor, x: Tensor) -> int:
    return int((pool - x).abs().amax(-1).argmin())


def _unrated(
    selector: Selector,
    models: BatchedPreferenceGP,
    q: Query,
    pool: Tensor,
    rated: set[int],
    b: int,
    step: int,
    num_queries: int,
    g: torch.Generator,
    rec: dict,
) -> Query:
    """``q``, or where it rates an item already rated, the selector's question among the unrated
    items, while at least ``max(2, m)`` are left (as a session asks:
    :func:`~torchpref.sessions.settings.unrated_rows`)."""
    if not isinstance(q, RatingQuery) or _pool_row(pool, q.item) not in rated:
        return q
    keep = [k for k in range(pool.shape[0]) if k not in rated]
    if len(keep) < max(2, int(getattr(selector, "m", 2))):
        return q
    rec["redirected"] += 1
    return selector.select(models.trial_model(b), pool[keep], None, step, num_queries, g)


def at_budgets(curve: Sequence[float], seconds: Sequence[float], budgets: Sequence[float] = BUDGETS) -> list[float]:
    """The score after the last answer within each budget of seconds (``curve[0]``: no answer)."""
    out, spent, k = [], 0.0, 0
    for budget in budgets:
        while k < len(seconds) and spent + seconds[k] <= budget + 1e-9:
            spent += seconds[k]
            k += 1
        out.append(curve[k])
    return out


def references(
    splits: Sequence[Split], prior: PriorAtItems | None, settings: ModelSettings = DEFAULT_MODEL
) -> dict[str, list[dict[str, float]]]:
    """The three "all answers" references per person: all 6 ratings, the ranking of the 6, both."""
    metrics = _metrics(splits)
    out: dict[str, list[dict[str, float]]] = {}
    for name, ratings, ranking in (("all ratings", True, False), ("the ranking", False, True), ("both", True, True)):
        models = _start(splits, prior, settings)
        for m, s in zip(models, splits):
            d = person_data(s, s.askable, ratings=ratings, ranking=ranking)
            r = d.ratings if m.rating_levels is None else unit_to_likert(d.ratings, m.rating_levels)
            m.add_observations(
                comparisons=d.comparisons if ranking else None,
                ratings=r if ratings else None,
                rating_index=d.rating_index if ratings else None,
            )
        with torch.no_grad():
            mean = torch.stack([m.posterior(s.X).mean.reshape(-1) for m, s in zip(models, splits)])
        scores = metrics(mean)
        out[name] = [{k: float(v[b]) for k, v in scores.items()} for b in range(len(splits))]
    return out
