r"""Queries a person can answer, and the candidates they are built from (paper Sec. III.A).

* :class:`RatingQuery`: one item, answered with a rating in ``[0, 1]``.
* :class:`RankingQuery`: ``m`` items, answered with the index of the best one; recorded as
  ``m - 1`` comparisons ``[chosen, other]``.

Candidates are a finite pool of items (:class:`FinitePool`, e.g. a set of planned paths) or a
box to sample from (:class:`BoxCandidates`; the authors drew 100 fresh uniform points per
query).
"""

from __future__ import annotations

import operator
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal, Protocol, SupportsFloat, SupportsIndex, overload

import torch
from torch import Tensor

from torchpref.data.preference_data import best_of_m, best_of_m_with_ties, likert_to_unit, unit_to_likert


class ObservedModel(Protocol):
    """What :func:`record_answer` asks of a model: its
    :meth:`~torchpref.PreferenceGP.add_observations`, called with the query's items and keywords
    ``comparisons``, ``ratings`` and ``rating_index``, or ``ties`` (a Protocol: ``data`` is below
    ``models``; its parameters are not spelled out because a batch trial's wrapper takes no
    ``ties``)."""

    @property
    def add_observations(self) -> Callable[..., object]:
        """The model's method that adds items and observations among them."""


class Respondent(Protocol):
    """Who answers a query (:func:`ask_user`): a rating of one item, a choice among several
    (:class:`~torchpref.simulation.users.User` is one); the answers are validated where they are
    recorded (:func:`record_answer`)."""

    def rate(self, x: Tensor, /) -> object:
        """A rating of the item ``x`` (``d``)."""

    def choose(self, X: Tensor, /) -> object:
        """The index of the best row of ``X`` (``m x d``)."""


def as_integer(value: object) -> int | None:
    """``value`` as an ``int`` if it is an integer (a Python, NumPy or 0-d integer tensor one; not
    a bool, a float or text), else ``None``."""
    if isinstance(value, bool) or not isinstance(value, SupportsIndex):
        return None
    try:
        return operator.index(value)
    except TypeError:
        return None


class InvalidAnswer(ValueError):
    """An answer that does not answer its query: a rating out of range or not a number, a choice
    that is not one of the items shown, "equally best" items named twice. The one error every front
    end maps to its refusal (``torchpref serve``: HTTP 400); nothing is recorded."""


def _is_text_or_bool(answer) -> bool:
    return isinstance(answer, (str, bytes, bool))


@dataclass(frozen=True)
class RatingQuery:
    """Ask for a rating of ``item`` (``d``); ``index`` is its row in a finite pool, if any."""

    item: Tensor
    index: int | None = None
    kind: str = field(default="rating", init=False)

    @property
    def items(self) -> Tensor:
        """``1 x d``: the items shown."""
        return self.item.unsqueeze(0)

    def validate_answer(self, answer: object, num_levels: int | None = None) -> float:
        """The rating in ``[0, 1]`` that ``answer`` gives: ``answer`` itself, or with ``num_levels``
        a whole Likert level ``1..num_levels`` mapped by :func:`~torchpref.likert_to_unit`.

        Raises:
            InvalidAnswer: not a number (text and booleans included), or out of range.
        """
        if num_levels is not None:
            try:
                if _is_text_or_bool(answer) or not isinstance(answer, (SupportsFloat, SupportsIndex)):
                    raise TypeError
                return float(likert_to_unit(float(answer), num_levels))
            except (TypeError, ValueError):
                raise InvalidAnswer(f"a rating must be a whole level in 1..{num_levels}, got {answer!r}.") from None
        try:
            if _is_text_or_bool(answer) or not isinstance(answer, (SupportsFloat, SupportsIndex)):
                raise TypeError
            u = float(answer)
        except (TypeError, ValueError):
            raise InvalidAnswer(f"a rating must be a number in [0, 1], got {answer!r}.") from None
        if not 0.0 <= u <= 1.0:
            raise InvalidAnswer(f"a rating must be in [0, 1], got {u}.")
        return u


@dataclass(frozen=True)
class RankingQuery:
    """Ask which of ``items`` (``m x d``) is best; ``indices`` are their rows in a pool, if any."""

    items: Tensor
    indices: tuple[int, ...] | None = None
    kind: str = field(default="ranking", init=False)

    @property
    def m(self) -> int:
        """The number of items shown."""
        return self.items.shape[0]

    @overload
    def validate_answer(self, answer: object, no_preference: Literal[False] = False) -> int: ...

    @overload
    def validate_answer(self, answer: object, no_preference: bool) -> int | None: ...

    def validate_answer(self, answer: object, no_preference: bool = False) -> int | None:
        """The chosen row ``0..m-1`` (an integer; not a bool, float or text); ``None`` (no
        preference) where ``no_preference`` allows it.

        Raises:
            InvalidAnswer: anything else.
        """
        if answer is None and no_preference:
            return None
        j = as_integer(answer)
        if j is None or not 0 <= j < self.m:
            raise InvalidAnswer(f"a ranking answer must be an item index in 0..{self.m - 1}, got {answer!r}.")
        return j

    def comparisons(self, chosen: int) -> Tensor:
        """The ``(m - 1) x 2`` comparisons (indices into :attr:`items`) of the answer ``chosen``."""
        return best_of_m(chosen, list(range(self.m)))


Query = RatingQuery | RankingQuery


def record_answer(
    model: ObservedModel, query: Query, answer: object, *, num_levels: int | None = None
) -> float | int | list[int] | None:
    r"""Validate ``answer`` to ``query`` and add it to ``model``: the one path from an answer to
    observations (the active-learning loop, the session live and on replay).

    Answers, in one vocabulary: a rating query takes a rating in ``[0, 1]`` (or, with
    ``num_levels``, a Likert level ``1..num_levels``, see :meth:`RatingQuery.validate_answer`);
    a ranking query takes the index of the best row of ``query.items``, which becomes ``m - 1``
    comparisons ``[chosen, other]``; a list of several indices ("these are equally best"), which
    becomes :func:`~torchpref.data.preference_data.best_of_m_with_ties`' comparisons and ties; or ``None`` for no
    preference, a tie between every two items shown (:func:`no_preference_observations`). A model
    with ``rating_levels`` records a rating ``u`` as the level of its bin (``unit_to_likert``).

    Args:
        model: a :class:`~torchpref.PreferenceGP` (or anything with its ``add_observations``).
        query: the query answered, its items in the model's coordinates.
        answer: the answer.
        num_levels: ratings are Likert levels ``1..num_levels``.

    Returns:
        The validated answer: the rating in ``[0, 1]``, the chosen row, or ``None``.

    Raises:
        InvalidAnswer: an invalid answer (naming it); the model is unchanged.
    """
    if isinstance(query, RatingQuery):
        u = query.validate_answer(answer, num_levels)
        levels = getattr(model, "rating_levels", None)  # an ordinal model records the level of u's bin
        model.add_observations(
            query.items, ratings=[u] if levels is None else unit_to_likert(u, levels), rating_index=[0]
        )
        return u
    if isinstance(query, RankingQuery):
        if isinstance(answer, (list, tuple)) and len(answer) > 1:  # several equally best items
            best = [query.validate_answer(a) for a in answer]
            if len(set(best)) != len(best):
                raise InvalidAnswer(f"the items named equally best must differ, got {list(answer)!r}.")
            comparisons, ties = best_of_m_with_ties(best, list(range(query.m)))
            model.add_observations(query.items, comparisons=comparisons, ties=ties)
            return best
        j = query.validate_answer(answer, no_preference=True)
        if j is None:
            no_preference_observations(model, query)
        else:
            model.add_observations(query.items, comparisons=query.comparisons(j))
        return j
    raise TypeError(f"query must be a RatingQuery or RankingQuery, got {type(query).__name__}.")


def no_preference_observations(model: ObservedModel, query: RankingQuery) -> None:
    """No preference among ``query.items``: a tie between every two of them
    (:class:`~torchpref.TieLikelihood`; docs/likelihoods.md)."""
    model.add_observations(query.items, ties=torch.combinations(torch.arange(query.m), 2))


def rating_query(X: Tensor, indices: Tensor | None, i: int) -> RatingQuery:
    """A :class:`RatingQuery` of row ``i`` of the candidates ``X`` (``N x d``; ``indices``: their
    ``N`` pool rows, or ``None``)."""
    return RatingQuery(X[i], None if indices is None else int(indices[i]))


def ranking_query(X: Tensor, indices: Tensor | None, rows: Tensor) -> RankingQuery:
    """A :class:`RankingQuery` of the ``rows`` (``m``) of the candidates ``X`` (``N x d``;
    ``indices``: their ``N`` pool rows, or ``None``)."""
    rows = rows.reshape(-1)
    return RankingQuery(X[rows], None if indices is None else tuple(int(indices[r]) for r in rows))


def ask_user(user: Respondent, query: Query) -> object:
    """The answer of a user (``rate(x)`` / ``choose(X)``) to ``query``, as given (it is validated
    where it is used, by :func:`record_answer`)."""
    if isinstance(query, RatingQuery):
        return user.rate(query.item)
    return user.choose(query.items)


class Candidates:
    """Where queries' items come from."""

    def draw(self, generator: torch.Generator) -> tuple[Tensor, Tensor | None]:
        """``(X, indices)``: candidate items ``N x d`` and their pool indices (or ``None``)."""
        raise NotImplementedError


def first_unique_rows(X: Tensor) -> Tensor:
    """Indices of the first occurrence of each distinct row of ``X`` (``N x d``), in order:
    planners can return the same path twice, and a query must not show an item twice."""
    _, group = torch.unique(X, dim=0, return_inverse=True)
    rows = torch.arange(X.shape[0], device=X.device)
    first = torch.full((int(group.max()) + 1,), X.shape[0], device=X.device)
    return first.scatter_reduce(0, group, rows, reduce="amin").sort().values


class FinitePool(Candidates):
    """A fixed set of items (``N x d``), e.g. planned trajectories' objective vectors.

    Rows that repeat an earlier row are not offered again (``draw`` returns each distinct item
    once, with the index of its first row), so a ranking never shows the same item twice.
    """

    def __init__(self, X: Tensor):
        if X.dim() != 2 or X.shape[0] < 1:
            raise ValueError(f"a pool must be N x d with N >= 1, got shape {tuple(X.shape)}.")
        self.X = X
        self._rows = first_unique_rows(X)

    def draw(self, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        return self.X[self._rows], self._rows


class BoxCandidates(Candidates):
    """``num`` fresh uniform points in a box (``2 x d`` bounds) at every query."""

    def __init__(self, bounds: Tensor, num: int = 100):
        if bounds.dim() != 2 or bounds.shape[0] != 2 or not (bounds[1] > bounds[0]).all():
            raise ValueError(f"bounds must be 2 x d with lower < upper, got {bounds.tolist()}.")
        if num < 1:
            raise ValueError(f"num must be positive, got {num}.")
        self.bounds, self.num = bounds, num

    def draw(self, generator: torch.Generator) -> tuple[Tensor, None]:
        lo, hi = self.bounds
        u = torch.rand(self.num, lo.shape[0], generator=generator, dtype=lo.dtype, device=lo.device)
        return lo + (hi - lo) * u, None
