r"""A measured dose of exploration: ask a random question with probability ``epsilon``, else the
base selector's.

Real features predict little, and a selector that trusts one fitted model asks where that model
is uncertain, which may be where it is wrong; uniformly random questions cover what the study can
ask. :class:`EpsilonExplore` mixes the two at a fixed rate (a coin per question from the trial's
generator; no tuning to a data set). Where it helps and where not: docs/suite.md ("Real people").
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from torchpref.data.queries import Query
from torchpref.selection.choosing import query_items, uniform_among
from torchpref.selection.samples import SelectorModel
from torchpref.selection.strategies import RandomMixed, Selector

__all__ = ["EpsilonExplore"]


class EpsilonExplore(Selector):
    r"""With probability ``epsilon`` a random question (:class:`~torchpref.RandomMixed`: a rating or
    a best-of-``m``, each with probability 1/2; among given queries, uniformly), else ``base``'s.

    Args:
        base: the selector asked otherwise.
        epsilon: the probability of a random question, in ``[0, 1]``.
        m: items of a random ranking (default ``base.m``, else 5).

    Raises:
        ValueError: ``epsilon`` outside ``[0, 1]``.
    """

    def __init__(self, base: Selector, epsilon: float = 0.5, m: int | None = None):
        if not 0.0 <= float(epsilon) <= 1.0:
            raise ValueError(f"epsilon must be in [0, 1], got {epsilon!r}.")
        self.base, self.epsilon = base, float(epsilon)
        self.random = RandomMixed(m=int(m if m is not None else getattr(base, "m", 5)))
        self.name = f"{getattr(base, 'name', type(base).__name__)} + {self.epsilon:g} random"

    def _explore(self, generator: torch.Generator) -> bool:
        return float(torch.rand((), generator=generator, dtype=torch.float64)) < self.epsilon

    def select_batch(
        self,
        model: SelectorModel,
        X: Tensor,
        indices: Sequence[Tensor | None],
        step: int,
        num_steps: int,
        generators: Sequence[torch.Generator],
    ) -> list[Query]:
        explore = [self._explore(g) for g in generators]
        out = self.base.select_batch(model, X, indices, step, num_steps, generators)
        for b, g in enumerate(generators):
            if explore[b]:
                out[b] = self.random.select_batch(model, X[b : b + 1], indices[b : b + 1], step, num_steps, [g])[0]
        return out

    def choose(
        self,
        model: SelectorModel,
        queries: Sequence[Query],
        *,
        step: int = 0,
        num_steps: int = 1,
        generator: torch.Generator,
    ) -> int:
        if self._explore(generator):
            return uniform_among(query_items(queries), None, generator)
        return self.base.choose(model, queries, step=step, num_steps=num_steps, generator=generator)
