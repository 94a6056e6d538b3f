r"""The active-learning loop: ask, record, update, measure (paper Sec. III.C, IV)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import torch
from botorch.fit import fit_gpytorch_mll

from torchpref.models import LaplaceMarginalLogLikelihood, PreferenceGP
from torchpref.queries import Candidates, Query, RatingQuery, ask_user, record_answer
from torchpref.strategies import Selector

DEFAULT_COSTS = {"rating": 1.0, "ranking": 1.0}


@dataclass
class QueryRecord:
    """One question and its answer."""

    step: int
    query: Query
    answer: float | int
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

    @property
    def num_ratings(self) -> int:
        return sum(isinstance(r.query, RatingQuery) for r in self.records)


def fit_model(model: PreferenceGP) -> PreferenceGP:
    """Fit the model's trainable hyperparameters by maximising the Laplace evidence."""
    fit_gpytorch_mll(LaplaceMarginalLogLikelihood(model))
    return model


def run_active_learning(
    model: PreferenceGP,
    user,
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
        selector: picks the query (:mod:`torchpref.strategies`).
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
        answer = ask_user(user, query)
        record_answer(model, query, answer)
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
