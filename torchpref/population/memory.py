r"""How much memory a population fit takes at its peak, known before it is spent.

:func:`estimate_peak` adds up the fit's largest tensors from the problem's sizes: ``P`` people of
at most ``n`` items, ``N`` distinct items, the mean at ``M`` items, the shards' sizes (float64,
8 bytes a number): each shard's ``Phi_s`` (``N_s x M``, twice while a new evaluation replaces the
last), three states of its people's blocks (``P_s n^2`` each: the current point, its Fisher
variant, a trial), the largest shard's transient work with autograd (``P_s n M`` or ``N_s^2``
terms), and the master's ``M x M`` matrices (``k_m(Z, Z)``, its factor traced and untraced, ``S``
and its factor, the gradient). ``benchmarks/studies/population_scale.py`` records it beside
the measured peak.
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


def shard_transient(s: ShardSize, M: int) -> int:
    """Numbers the largest step of one shard holds at once (its gradient's autograd graph)."""
    P, n, N = s.people, s.items, s.distinct
    if s.by_rows:
        return 12 * P * n * M + 3 * N * M + 12 * P * n * n
    return 4 * N * N + 6 * N * M + 12 * P * n * n


def estimate_peak(shards: Sequence[ShardSize], N: int, M: int, d: int) -> int:
    """The fit's peak memory in bytes, estimated (module docstring)."""
    data = sum(s.people * s.items * (2 * d + 8) for s in shards) + 3 * N * d
    resident = sum(2 * s.distinct * M + 3 * 5 * s.people * s.items * s.items for s in shards)
    transient = max(shard_transient(s, M) for s in shards)
    master = 10 * M * M + 4 * N * d
    return int(1.25 * F64 * (data + resident + transient + master))


def gigabytes(b: float) -> str:
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
