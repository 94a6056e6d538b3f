r"""The selector a session uses when none is given (:func:`default_selector`).

One default serves :class:`~torchpref.PreferenceSession`, ``torchpref elicit`` and ``torchpref
serve``; a resumed session keeps the selector its header recorded. Why this one, with the replay of
real people's answers and the user-family suite: docs/suite.md ("Real people").
"""

from __future__ import annotations

from torchpref.selection.strategies import UCBC, Selector

__all__ = ["default_ranking_size", "default_selector"]


def default_ranking_size(num_items: int | None) -> int:
    """Items per ranking query for a pool of ``num_items`` distinct items: 5, or fewer than the
    pool (``num_items - 1``, at least 2), so that a small pool's rankings are not all the same set;
    5 where the items are not a finite pool (``None``)."""
    return 5 if num_items is None else max(2, min(5, int(num_items) - 1))


def default_selector(num_items: int | None = None) -> Selector:
    """The selector sessions use when none is given, for a pool of ``num_items`` distinct items
    (``None``: a box of candidates): the paper's :class:`~torchpref.UCBC` with ``m =
    default_ranking_size(num_items)``. The evidence of docs/suite.md ("Real people") did not
    support replacing it (no candidate beat asking at random on real answers)."""
    return UCBC(m=default_ranking_size(num_items))
