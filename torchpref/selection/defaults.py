r"""The selector a session uses when none is given (:func:`default_selector`).

One default serves :class:`~torchpref.PreferenceSession`, ``torchpref elicit`` and ``torchpref
serve``; a resumed session keeps the selector its header recorded (an older file: the paper's
:class:`~torchpref.UCBC`). Why this one: docs/selection.md (twins of real people with and without
their population, the population replay of real people, the realistic and idealised families;
``benchmarks/results/default_choice.json``). The paper's experiments name UCBC explicitly.
"""

from __future__ import annotations

from torchpref.selection.combined import InformationAndProfile
from torchpref.selection.strategies import Selector
from torchpref.simulation.raters import EffortModel

__all__ = ["default_ranking_size", "default_selector"]


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
