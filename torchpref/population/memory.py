r"""How much memory a population fit takes at its peak, known before it is spent.

:func:`estimate_peak` adds up the fit's largest tensors from the problem's sizes (float64, 8 bytes
a number): ``P_s`` people of at most ``n`` items and ``N_s`` distinct items per shard, the mean at
``M`` items. The terms and their multiples were measured (the peak resident memory of a fit less
that before it, ``benchmarks/studies/population_scale.py`` records both):

* the people's blocks, ``55 P n^2`` (a point's ``C``, ``W``, ``W~`` and ``L_P``, a trial's and a
  Fisher variant's, and their autograd graph in the gradient);
* each shard's ``Phi_s`` (``N_s x M``) and its copies while an evaluation replaces the last,
  ``3 N_s M``;
* the largest shard's work at once, ``12 P_s n M`` by rows or ``4 N_s^2 + 12 N_s M`` through the
  scatter;
* the master's ``M x M`` matrices (``k_m(Z, Z)``, its factor traced and untraced, ``S``, its
  factor and the parts summed into it, the gradient), ``14 M^2``;
* the data, and :data:`BASE` for the allocator's own.

Measured against it (one thread, two L-BFGS iterations; the peak less that before the fit):
1,000 people x 30 of 300 shared items, exact, 0.45 GB (estimate 0.57); 2,000 people with their
own 10 items at M = 256, 0.59 GB (0.86); 500 people with their own 10 items, exact
(M = N = 5,000), 2.7 GB (4.05); over 50 iterations, ``population_scale.py``'s records.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

#: The fraction of the machine's memory a fit may plan to use by default.
MEMORY_FRACTION = 0.75
#: Bytes of a float64.
F64 = 8


@dataclass(frozen=True)
class ShardSize:
    """A shard's people ``P``, padded items per person ``n``, distinct items ``N`` and route."""

    people: int
    items: int
    distinct: int
    by_rows: bool


def machine_memory() -> int:
    """This machine's physical memory in bytes (16 GB where the platform does not say)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 16 * 2**30


def default_memory_limit() -> int:
    """:data:`MEMORY_FRACTION` of :func:`machine_memory`."""
    return int(MEMORY_FRACTION * machine_memory())


#: Bytes the allocator holds beyond the fit's tensors (measured: the intercept over fit sizes).
BASE = 150 * 10**6


def shard_transient(s: ShardSize, M: int) -> int:
    """Numbers the largest step of one shard holds at once (its gradient's autograd graph)."""
    if s.by_rows:
        return 12 * s.people * s.items * M
    return 4 * s.distinct * s.distinct + 12 * s.distinct * M


def estimate_peak(shards: Sequence[ShardSize], N: int, M: int, d: int) -> int:
    """The fit's peak memory in bytes, estimated (module docstring)."""
    data = sum(s.people * s.items * (2 * d + 8) for s in shards) + 4 * N * d
    people = sum(55 * s.people * s.items * s.items + 3 * s.distinct * M for s in shards)
    transient = max(shard_transient(s, M) for s in shards)
    return BASE + F64 * (data + people + transient + 14 * M * M)


def gigabytes(b: float) -> str:
    """``n`` bytes in gigabytes (for messages)."""
    return f"{b / 1e9:.3g} GB"


def check_memory(peak: int, limit: int | None, what: str, way_out: str) -> None:
    """Refuse a fit whose estimated ``peak`` exceeds ``limit`` (``None``: the default), with the
    number and ``way_out``.

    Raises:
        ValueError: naming the estimate, the limit and the way out.
    """
    if limit is None:
        limit = default_memory_limit()
        source = f"the default, {MEMORY_FRACTION:.0%} of this machine's {gigabytes(machine_memory())}"
    else:
        source = "memory_limit"
    if peak > limit:
        raise ValueError(
            f"fit_population would need about {gigabytes(peak)} at its peak ({what}), more than "
            f"{gigabytes(limit)} ({source}): {way_out}, or pass a larger memory_limit (bytes)."
        )
