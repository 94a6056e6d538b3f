r"""The selector a session uses when none is given (:func:`default_selector`).

One default serves :class:`~torchpref.PreferenceSession`, ``torchpref elicit`` and ``torchpref
serve``; a resumed session keeps the selector its header recorded (an older file: the paper's
:class:`~torchpref.UCBC`). Why this one: docs/selection.md (twins of real people with and without
their population, the population replay of real people, the realistic and idealised families;
``benchmarks/results/default_choice.json``). The paper's experiments name UCBC explicitly.
"""

from __future__ import annotations

from collections.abc import Callable

from torchpref.selection.combined import InformationAndProfile
from torchpref.selection.strategies import UCBC, InformationPerEffort, RandomMixed, Selector
from torchpref.simulation.raters import EffortModel

__all__ = ["SELECTOR_NAMES", "default_ranking_size", "default_selector", "named_selector"]


def default_ranking_size(num_items: int | None) -> int:
    """Items per ranking query for a pool of ``num_items`` distinct items: 5, or fewer than the
    pool (``num_items - 1``, at least 2), so that a small pool's rankings are not all the same set;
    5 where the items are not a finite pool (``None``)."""
    return 5 if num_items is None else max(2, min(5, int(num_items) - 1))


def default_selector(num_items: int | None = None) -> Selector:
    r"""The selector sessions use when none is given, for a pool of ``num_items`` distinct items
    (``None``: a box of candidates): :class:`~torchpref.selection.combined.InformationAndProfile`
    with ``decide="sum"`` (every question valued by the expected information about the utility and
    the clipped profile's expected variance reduction, each relative to its best rating, per second
    of the plain effort model: a rating 3.4 s, a best-of-``m`` ``3.4 + 0.9 (m - 2)`` s) and ``m =
    default_ranking_size(num_items)``."""
    m = default_ranking_size(num_items)
    effort = EffortModel.plain()
    return InformationAndProfile(m=m, rating_cost=effort.rating(), ranking_cost=effort.ranking(m), decide="sum")


#: name -> factory(num_items): the selectors ``torchpref elicit`` and ``serve`` take by name (``--selector``)
_NAMED: dict[str, Callable[[int | None], Selector]] = {
    "default": lambda n: default_selector(n),
    "ucbc": lambda n: UCBC(m=default_ranking_size(n)),
    "information": lambda n: InformationPerEffort(m=default_ranking_size(n), target="utility"),
    "random": lambda n: RandomMixed(m=default_ranking_size(n)),
}
SELECTOR_NAMES = tuple(_NAMED)


def named_selector(name: str, num_items: int | None = None) -> Selector:
    """The selector called ``name`` for a pool of ``num_items`` distinct items (``None``: a box),
    with ``m = default_ranking_size(num_items)``: ``"default"`` (:func:`default_selector`),
    ``"ucbc"`` (the paper's :class:`~torchpref.UCBC`, which asks rankings early and ratings late),
    ``"information"`` (:class:`~torchpref.selection.strategies.InformationPerEffort` of the utility)
    or ``"random"`` (:class:`~torchpref.selection.strategies.RandomMixed`: a random rating or
    best-of-``m``, even odds).

    Raises:
        ValueError: an unknown name, listing the known ones.
    """
    if name not in _NAMED:
        raise ValueError(f"unknown selector {name!r}: one of {', '.join(SELECTOR_NAMES)}.")
    return _NAMED[name](num_items)
