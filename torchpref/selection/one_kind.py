r"""A per-effort selector restricted to one kind of question: ratings only, or rankings only.

:class:`OneKind` asks what its selector would ask among questions of one kind: the selector's best
rating (``kind="rating"``) or its best best-of-``m`` (``kind="ranking"``), on the same posterior
samples and generator draws as the unrestricted selector. It answers "what does the choice between
the two kinds add?": compare a selector with its two restrictions at equal seconds
(``torchpref reproduce sushi``; docs/real_raters.md).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from torchpref.data.queries import Query, ranking_query, rating_query
from torchpref.selection.choosing import query_items
from torchpref.selection.samples import SelectorModel
from torchpref.selection.strategies import PerEffortSelector, Selector, shown

__all__ = ["KINDS", "OneKind"]

KINDS = ("rating", "ranking")


class OneKind(Selector):
    r"""``selector`` restricted to one ``kind`` of question (module notes).

    Args:
        selector: a per-effort selector (it values its best rating and best ranking:
            :meth:`~torchpref.selection.strategies.PerEffortSelector.values`).
        kind: ``"rating"`` or ``"ranking"``.

    Raises:
        ValueError: an unknown kind, or a selector that does not value both kinds.
    """

    def __init__(self, selector: PerEffortSelector, kind: str):
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {kind!r}.")
        if not isinstance(selector, PerEffortSelector):
            raise ValueError(
                f"OneKind needs a per-effort selector (one that values its best rating and ranking), got "
                f"{type(selector).__name__}."
            )
        self.selector, self.kind = selector, kind
        self.m = selector.m
        self.name = f"{selector.name} ({kind}s only)"

    def select_batch(
        self,
        model: SelectorModel,
        X: Tensor,
        indices: Sequence[Tensor | None],
        step: int,
        num_steps: int,
        generators: Sequence[torch.Generator],
    ) -> list[Query]:
        with torch.no_grad():
            rating_row, _, ranking_rows, _ = self.selector.values(model, X, generators)
        if self.kind == "ranking":
            if ranking_rows is None:
                raise ValueError(f"a ranking of m={self.m} needs at least {self.m} candidates, got {X.shape[1]}.")
            return [ranking_query(X[b], indices[b], shown(ranking_rows[b])) for b in range(X.shape[0])]
        return [rating_query(X[b], indices[b], int(rating_row[b])) for b in range(X.shape[0])]

    def choose(
        self,
        model: SelectorModel,
        queries: Sequence[Query],
        *,
        step: int = 0,
        num_steps: int = 1,
        generator: torch.Generator,
    ) -> int:
        """The selector's choice among the given queries of this kind (among all, where none is)."""
        mine = [i for i, q in enumerate(queries) if q.kind == self.kind]
        if not mine:
            return self.selector.choose(model, queries, step=step, num_steps=num_steps, generator=generator)
        query_items([queries[i] for i in mine])  # validates them
        k = self.selector.choose(model, [queries[i] for i in mine], step=step, num_steps=num_steps, generator=generator)
        return mine[k]
