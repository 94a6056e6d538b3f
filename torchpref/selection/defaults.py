r"""The selector a session uses when none is given (:func:`default_selector`).

One default serves :class:`~torchpref.PreferenceSession`, ``torchpref elicit`` and ``torchpref
serve``; a resumed session keeps the selector its header recorded (an older file: the paper's
:class:`~torchpref.UCBC`). Why this one: docs/selection.md (twins of real people with and without
their population, the population replay of real people, the realistic and idealised families;
``benchmarks/results/default_choice.json``). The paper's experiments name UCBC explicitly.
"""

from __future__ import annotations

from collections.abc import Callable

from torchpref.data.effort import EffortModel
from torchpref.selection.combined import InformationAndProfile
from torchpref.selection.strategies import UCBC, InformationPerEffort, RandomMixed, Selector

__all__ = ["SELECTOR_NAMES", "default_ranking_size", "default_selector", "named_selector", "rating_bins"]


def default_ranking_size(num_items: int | None) -> int:
    """Items per ranking query for a pool of ``num_items`` distinct items: 5, or fewer than the
    pool (``num_items - 1``, at least 2), so that a small pool's rankings are not all the same set;
    5 where the items are not a finite pool (``None``)."""
    return 5 if num_items is None else max(2, min(5, int(num_items) - 1))


def rating_bins(num_levels: int | None) -> int:
    """The answers a rating can take, as the selectors value it: the ``K`` levels of a Likert
    scale (a coarse scale tells less than a fine one), 10 bins of a slider (``None``)."""
    return 10 if num_levels is None else int(num_levels)


def default_selector(num_items: int | None = None, num_levels: int | None = None) -> Selector:
    r"""The selector sessions use when none is given, for a pool of ``num_items`` distinct items
    (``None``: a box of candidates) rated on ``num_levels`` levels (``None``: a slider):
    :class:`~torchpref.selection.combined.InformationAndProfile` with ``decide="order"``: every
    question valued by the information its answer carries about the order of the likeliest
    maximisers, per second of the plain effort model (:class:`~torchpref.data.effort.EffortModel`:
    a rating 3.4 s, a best-of-``q`` ``3.4 + 0.9 (q - 2)`` s); a rating valued by the answers it can
    take (:func:`rating_bins`) under the person's calibrated rating likelihood; rankings of the size
    worth most per second, ``2 <= q <= m = default_ranking_size(num_items)``, built from the most
    valuable pair. Why: docs/real_raters.md (real people who both rated and ranked) and
    docs/selection.md."""
    return InformationAndProfile(
        m=default_ranking_size(num_items),
        decide="order",
        num_bins=rating_bins(num_levels),
        effort=EffortModel.plain(),
        choose_size=True,
    )


#: name -> factory(num_items, num_levels): the selectors ``torchpref elicit``, ``serve`` and
#: ``study serve`` take by name (``--selector``)
_NAMED: dict[str, Callable[[int | None, int | None], Selector]] = {
    "default": default_selector,
    "ucbc": lambda n, k: UCBC(m=default_ranking_size(n)),
    "information": lambda n, k: InformationPerEffort(
        m=default_ranking_size(n), target="utility", num_bins=rating_bins(k), effort=EffortModel.plain()
    ),
    "random": lambda n, k: RandomMixed(m=default_ranking_size(n)),
}
SELECTOR_NAMES = tuple(_NAMED)


def named_selector(name: str, num_items: int | None = None, num_levels: int | None = None) -> Selector:
    """The selector called ``name`` for a pool of ``num_items`` distinct items (``None``: a box),
    rated on ``num_levels`` levels, with ``m = default_ranking_size(num_items)``: ``"default"`` (:func:`default_selector`),
    ``"ucbc"`` (the paper's :class:`~torchpref.UCBC`, which asks rankings early and ratings late),
    ``"information"`` (:class:`~torchpref.selection.strategies.InformationPerEffort` of the utility,
    priced by the plain effort model)
    or ``"random"`` (:class:`~torchpref.selection.strategies.RandomMixed`: a random rating or
    best-of-``m``, even odds).

    Raises:
        ValueError: an unknown name, listing the known ones.
    """
    if name not in _NAMED:
        raise ValueError(f"unknown selector {name!r}: one of {', '.join(SELECTOR_NAMES)}.")
    return _NAMED[name](num_items, num_levels)
