r"""The active-learning loop: ask, record, update, measure (paper Sec. III.C, IV)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from botorch.fit import fit_gpytorch_mll
from torch import Tensor

from torchpref.data.queries import Candidates, Query, ask_user, record_answer
from torchpref.models.batch import BatchedPreferenceGP
from torchpref.models.preference_gp import LaplaceMarginalLogLikelihood, PreferenceGP
from torchpref.selection.strategies import Selector
from torchpref.simulation.users import User

DEFAULT_COSTS = {"rating": 1.0, "ranking": 1.0}


@dataclass
class QueryRecord:
    """One question and its answer: a rating, the chosen row, several rows "equally best", or
    ``None`` for no preference (:func:`~torchpref.data.queries.record_answer`)."""

    step: int
    query: Query
    answer: float | int | list[int] | None
    cost: float


@dataclass
class History:
    """Everything a run asked, heard and measured.

    Attributes:
        records: one :class:`QueryRecord` per query, in order.
        metrics: ``num_queries + 1`` dicts: before any query, then after each.
        model: the final model.
    """

    records: list[QueryRecord] = field(default_factory=list)
    metrics: list[dict[str, float]] = field(default_factory=list)
    model: PreferenceGP | None = None

    def metric(self, name: str) -> list[float]:
        """A metric's values, one per query count (0 .. num_queries)."""
        return [m[name] for m in self.metrics]

    def cumulative_cost(self) -> list[float]:
        """Effort spent after 0 .. num_queries queries."""
        out = [0.0]
        for r in self.records:
            out.append(out[-1] + r.cost)
        return out


def fit_model(model: PreferenceGP) -> PreferenceGP:
    """Fit the model's trainable hyperparameters by maximising the Laplace evidence."""
    fit_gpytorch_mll(LaplaceMarginalLogLikelihood(model))
    return model


def run_active_learning(
    model: PreferenceGP,
    user: User,
    candidates: Candidates,
    selector: Selector,
    num_queries: int,
    *,
    generator: torch.Generator,
    metrics: Callable[[PreferenceGP], dict[str, float]] | None = None,
    callback: Callable[[int, QueryRecord, PreferenceGP, dict[str, float]], Any] | None = None,
    refit_every: int | None = None,
    costs: dict[str, float] | None = None,
) -> History:
    r"""Ask ``num_queries`` questions of ``user``, updating ``model`` (in place, warm-started).

    Args:
        model: the starting model (with whatever initial observations it has).
        user: any object with ``rate(x) -> float in [0, 1]`` and ``choose(X) -> int``.
        candidates: where each query's items come from.
        selector: picks the query (:mod:`torchpref.selection.strategies`).
        num_queries: how many questions.
        generator: seeds every random choice of the selector and the candidates.
        metrics: ``model -> {name: value}``, evaluated before the first query and after each.
        callback: called after each query with ``(step, record, model, metrics)``.
        refit_every: refit the hyperparameters every this many queries (default: never, as
            in the paper's experiments).
        costs: effort of a ``"rating"`` and of a ``"ranking"`` query (default 1 each).

    Returns:
        The :class:`History`.
    """
    if num_queries < 0:
        raise ValueError(f"num_queries must be non-negative, got {num_queries}.")
    if refit_every is not None and refit_every < 1:
        raise ValueError(f"refit_every must be a positive integer, got {refit_every}.")
    costs = {**DEFAULT_COSTS, **(costs or {})}
    history = History(model=model)
    if metrics is not None:
        history.metrics.append(metrics(model))
    for step in range(num_queries):
        X, indices = candidates.draw(generator)
        query = selector.select(model, X, indices, step, num_queries, generator)
        answer = record_answer(model, query, ask_user(user, query))
        record = QueryRecord(step, query, answer, costs[query.kind])
        history.records.append(record)
        if refit_every is not None and (step + 1) % refit_every == 0:
            fit_model(model)
        values = metrics(model) if metrics is not None else {}
        if metrics is not None:
            history.metrics.append(values)
        if callback is not None:
            callback(step, record, model, values)
    return history


class _Trial:
    """One trial of a batched model, with :meth:`PreferenceGP.add_observations`'s signature."""

    def __init__(self, model: BatchedPreferenceGP, trial: int):
        self.model, self.trial = model, trial

    def add_observations(self, X=None, comparisons=None, ratings=None, rating_index=None, ties=None):
        self.model.add_observations(self.trial, X, comparisons, ratings, rating_index, ties)


def run_active_learning_batch(
    model: BatchedPreferenceGP,
    users: Sequence[User],
    candidates: Candidates,
    selector: Selector,
    num_queries: int,
    *,
    generators: Sequence[torch.Generator],
    metrics: Callable[[BatchedPreferenceGP], dict[str, Tensor]] | None = None,
    costs: dict[str, float] | None = None,
    refit: Callable[[int, BatchedPreferenceGP], Any] | None = None,
) -> list[History]:
    r""":func:`run_active_learning` for ``T`` independent trials at once (fixed hyperparameters).

    Trial ``b`` asks ``users[b]``, draws its candidates and makes its selector's random choices
    with ``generators[b]`` exactly as a single run with that generator would, so each trial's
    questions and answers are those of ``run_active_learning`` on
    ``model.trial_model(b)`` (up to the Newton tolerance, which can only matter where two
    candidates tie); only the modes are solved together (:class:`~torchpref.models.batch.BatchedPreferenceGP`)
    and the selector decides for all trials in one call (:meth:`Selector.select_batch`).

    Args:
        model: the trials' starting models, updated in place.
        users: one user per trial.
        candidates: where each query's items come from (drawn per trial).
        selector: picks the queries; needs :meth:`~torchpref.selection.strategies.Selector.select_batch`.
        num_queries: how many questions per trial.
        generators: one per trial.
        metrics: ``model -> {name: T values}``, evaluated before the first query and after each.
        costs: effort of a ``"rating"`` and of a ``"ranking"`` query (default 1 each).
        refit: called as ``refit(step, model)`` after each query's answers are recorded and
            before the metrics, e.g. to set new hyperparameters learned from the answers (a
            schedule of its own: it decides at which steps to change anything).

    Returns:
        One :class:`History` per trial (``model`` is ``None``: ``model`` holds all trials).
    """
    T = model.num_trials
    if len(users) != T or len(generators) != T:
        raise ValueError(f"need one user and one generator per trial ({T}), got {len(users)} and {len(generators)}.")
    if num_queries < 0:
        raise ValueError(f"num_queries must be non-negative, got {num_queries}.")
    costs = {**DEFAULT_COSTS, **(costs or {})}
    histories = [History() for _ in range(T)]
    _measure(metrics, model, histories)
    for step in range(num_queries):
        draws = [candidates.draw(g) for g in generators]
        X = torch.stack([x for x, _ in draws])
        queries = selector.select_batch(model, X, [i for _, i in draws], step, num_queries, generators)
        for b, query in enumerate(queries):
            answer = record_answer(_Trial(model, b), query, ask_user(users[b], query))
            histories[b].records.append(QueryRecord(step, query, answer, costs[query.kind]))
        if refit is not None:
            refit(step, model)
        _measure(metrics, model, histories)
    return histories


def _measure(
    metrics: Callable[[BatchedPreferenceGP], dict[str, Tensor]] | None,
    model: BatchedPreferenceGP,
    histories: list[History],
) -> None:
    """Append each trial's metrics (``metrics(model)``: ``T`` values per name) to its history."""
    if metrics is not None:
        values = {k: v.tolist() for k, v in metrics(model).items()}
        for b, h in enumerate(histories):
            h.metrics.append({k: v[b] for k, v in values.items()})
