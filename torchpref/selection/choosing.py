r"""Choosing among given queries: which of a fixed list of questions to ask next.

A study often has its questions already: pre-planned trajectories, a stimulus set's pairs, the
recorded questions of a replay. ``selector.choose(model, queries, step=, num_steps=, generator=)``
returns the index of the query to ask among a list of :class:`~torchpref.data.queries.RatingQuery`
and :class:`~torchpref.data.queries.RankingQuery` (a pair is a ranking of two), valued as the
selector values the queries it builds itself:

* the queries' distinct items become the candidates ``X`` (in order of first appearance), so
  sample-based selectors draw their joint posterior samples over exactly these items and value a
  rating of item ``i`` and a best-of-``q`` of items ``Q`` with the same value functions (and the
  same samples, from the generator) as in ``select``;
* values are per unit of effort: a rating costs the selector's rating cost, a best-of-``q`` its
  ranking cost for ``q`` (:func:`ranking_cost`);
* ties go to the first query in the list.

:func:`query_items` builds ``X`` and each query's rows; :func:`choose_by_scores` is the common
end of the sample-based selectors.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from torchpref.data.effort import EffortModel
from torchpref.data.queries import Query, RankingQuery, RatingQuery, first_unique_rows

__all__ = ["QueryRows", "choose_by_scores", "query_items", "ranking_cost"]

#: a trial's rows ``T x R`` (ratings) or ``T x R x q`` (rankings) -> ``T x R`` values
Scorer = Callable[[Tensor], Tensor]


class QueryRows:
    """The distinct items of a list of queries and each query's rows among them.

    Attributes:
        X: ``N x d`` distinct items, in order of first appearance.
        rows: one long tensor of rows per query (``1`` for a rating, ``q`` for a ranking).
        kinds: ``"rating"`` or ``"ranking"`` per query.
    """

    def __init__(self, X: Tensor, rows: list[Tensor], kinds: list[str]):
        self.X, self.rows, self.kinds = X, rows, kinds

    def of_kind(self, kind: str) -> list[int]:
        """The positions of the queries of one kind."""
        return [i for i, k in enumerate(self.kinds) if k == kind]

    def groups(self) -> dict[int, list[int]]:
        """Queries by size: ``{1: ratings, q: rankings of q items}``."""
        out: dict[int, list[int]] = {}
        for i, r in enumerate(self.rows):
            out.setdefault(1 if self.kinds[i] == "rating" else r.numel(), []).append(i)
        return out


def query_items(queries: Sequence[Query]) -> QueryRows:
    """The distinct items of ``queries`` and each query's rows among them.

    Raises:
        ValueError: an empty list, something that is not a query, items of different dimensions,
            or a ranking that shows one item twice.
    """
    if isinstance(queries, (RatingQuery, RankingQuery)) or len(queries) == 0:
        raise ValueError(f"queries must be a non-empty list of RatingQuery / RankingQuery, got {queries!r:.80}.")
    blocks: list[Tensor] = []
    kinds: list[str] = []
    for i, q in enumerate(queries):
        if not isinstance(q, (RatingQuery, RankingQuery)):
            raise ValueError(f"queries[{i}] is not a RatingQuery or RankingQuery: {q!r:.80}.")
        items = q.items
        if items.dim() != 2 or (blocks and items.shape[-1] != blocks[0].shape[-1]):
            raise ValueError(f"queries[{i}] has items of shape {tuple(items.shape)}, unlike the first query's.")
        blocks.append(items)
        kinds.append(q.kind)
    allX = torch.cat([b.to(blocks[0]) for b in blocks])
    first = first_unique_rows(allX)
    _, group = torch.unique(allX, dim=0, return_inverse=True)
    row_of_group = torch.empty(int(group.max()) + 1, dtype=torch.long)
    row_of_group[group[first]] = torch.arange(first.numel())
    rows, start = [], 0
    for i, b in enumerate(blocks):
        r = row_of_group[group[start : start + b.shape[0]]]
        start += b.shape[0]
        if r.unique().numel() != r.numel():
            raise ValueError(f"queries[{i}] shows one item twice.")
        rows.append(r)
    return QueryRows(allX[first], rows, kinds)


def ranking_cost(rating_cost: float, ranking_cost: float, m: int, q: int) -> float:
    """The effort of a best-of-``q`` for a selector whose best-of-``m`` costs ``ranking_cost``: the
    same for ``q = m``, else scaled by the default effort ratio ``(1 + (q - 1) / 4) / (1 + (m - 1) / 4)``
    (:func:`~torchpref.selection.strategies.effort_model`)."""
    if q == m:
        return ranking_cost
    return ranking_cost * (1 + (q - 1) / 4) / (1 + (m - 1) / 4)


def choose_by_scores(
    qr: QueryRows,
    rating_value: Scorer,
    ranking_value: Scorer,
    cost: Callable[[int], float],
) -> int:
    """The query of largest value per effort: ratings valued by ``rating_value`` (rows ``1 x R``),
    best-of-``q`` by ``ranking_value`` (rows ``1 x R x q``), each divided by ``cost(q)`` (``q = 1``
    a rating); ties to the first query."""
    values = torch.full((len(qr.rows),), -torch.inf, dtype=torch.float64)
    for q, idx in qr.groups().items():
        rows = torch.stack([qr.rows[i] for i in idx])  # R x q (a rating: R x 1)
        v = rating_value(rows[:, 0].unsqueeze(0)) if q == 1 else ranking_value(rows.unsqueeze(0))
        values[idx] = v.reshape(-1).to(values) / cost(q)
    values = torch.nan_to_num(values, nan=-torch.inf)
    return int(values.argmax())


def uniform_among(qr: QueryRows, kind: str | None, generator: torch.Generator) -> int:
    """A uniformly random query of ``kind`` (any kind if ``None`` or none of that kind)."""
    pool = qr.of_kind(kind) if kind is not None else []
    pool = pool or list(range(len(qr.rows)))
    return pool[int(torch.randint(len(pool), (1,), generator=generator))]


def _ranking_size(m: int) -> int:
    """``m`` checked at construction: a whole number of items per ranking, at least 2."""
    if isinstance(m, bool) or int(m) != m or m < 2:
        raise ValueError(f"a ranking query needs m >= 2 items (a whole number), got m={m!r}.")
    return int(m)


def effort_model(
    m: int, rating_cost: float, ranking_cost: float | None, effort: EffortModel | dict[str, float] | None = None
) -> tuple[int, float, float]:
    """``m`` checked, and the efforts of a rating and a best-of-``m`` ranking: ``effort``'s seconds
    where an :class:`~torchpref.data.effort.EffortModel` is given, else ``rating_cost`` and
    ``ranking_cost`` (default ``1 + (m - 1) / 4``: one judgement and reading ``m - 1`` more items at
    a quarter each)."""
    m = _ranking_size(m)
    if effort is not None:
        effort = EffortModel.of(effort)
        return m, effort.rating(), effort.ranking(m)
    ranking_cost = 1.0 + (m - 1) / 4 if ranking_cost is None else ranking_cost
    if not (rating_cost > 0 and ranking_cost > 0):
        raise ValueError(f"costs must be positive, got rating_cost={rating_cost}, ranking_cost={ranking_cost}.")
    return m, float(rating_cost), float(ranking_cost)


def shown(rows: Tensor) -> Tensor:
    """A ranking's rows as :meth:`PerEffortSelector.values` gives them, without the ``-1`` that pad
    a smaller set than ``m``."""
    return rows[rows >= 0]
