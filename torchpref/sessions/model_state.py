r"""A session's model as a cache of its answers, kept at constant cost per answer.

* :func:`build_data`: the :class:`~torchpref.data.preference_data.PreferenceData` of the answers in
  force in one vectorised pass, equal (``torch.equal``, every field) to what feeding them one by
  one through :func:`~torchpref.data.queries.record_answer` builds, with the data's sizes before
  each answer (so that it can be undone later without a replay).
* :func:`truncate`: the model taken back to its data before an answer (the data are appended in
  order, so the earlier model's data are a prefix), its mode warm-started from the current one.
* :func:`write_snapshot` / :func:`read_snapshot`: the posterior mode after the latest record, kept
  beside the file (``FILE.mode``): a resume starts Newton there and replays only the answers
  after it, so that it is the interrupted process's posterior (to round-off) at constant cost.

Replay through ``record_answer`` stays the reference (``tests/sessions/test_session_scale.py`` checks the
two agree to Newton's tolerance, and give the same next query).
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import torch
from torch import Tensor

from torchpref.data.preference_data import PreferenceData, unit_to_likert
from torchpref.models.preference_gp import PreferenceGP
from torchpref.sessions.errors import SessionFileError
from torchpref.sessions.records import AnswerRecord

__all__ = [
    "MODE_MEMORY",
    "REPLAY_LIMIT",
    "Sizes",
    "build_data",
    "header_digest",
    "mode",
    "read_snapshot",
    "sizes",
    "snapshot_path",
    "truncate",
    "write_snapshot",
]


class Sizes(NamedTuple):
    """The numbers of items, comparisons, ratings and ties of a model's data."""

    items: int
    comparisons: int
    ratings: int
    ties: int


def session_data(model: PreferenceGP) -> PreferenceData:
    """A session model's data: one problem's :class:`~torchpref.data.preference_data.PreferenceData`
    (a session never holds a batch of problems)."""
    data = model.data
    if not isinstance(data, PreferenceData):
        raise TypeError(f"a session's model holds one problem's data, not {type(data).__name__}.")
    return data


def sizes(model: PreferenceGP) -> Sizes:
    """The sizes of ``model``'s data."""
    data = session_data(model)
    return Sizes(data.n, data.comparisons.shape[0], data.ratings.shape[0], data.ties.shape[0])


def _unique_in_order(Z: Tensor) -> tuple[Tensor, Tensor]:
    """``(first, index)``: the row of each distinct item's first occurrence in ``Z``, in order of
    first occurrence, and each row's item number (rows with equal coordinates share one, as
    :meth:`~torchpref.data.preference_data.PreferenceData.index_items` compares them: ``-0.0`` and
    ``0.0`` are one coordinate)."""
    seen: dict[tuple[float, ...], int] = {}
    first: list[int] = []
    index: list[int] = []
    for row, key in enumerate(map(tuple, Z.tolist())):
        i = seen.get(key)
        if i is None:
            i = seen[key] = len(first)
            first.append(row)
        index.append(i)
    return torch.tensor(first, dtype=torch.long), torch.tensor(index, dtype=torch.long)


def build_data(
    anchor: Tensor,
    records: list[AnswerRecord],
    transform: Callable[[Tensor], Tensor],
    rating_eps: float,
    rating_levels: int | None,
) -> tuple[PreferenceData, list[Sizes]]:
    """The data of a model built on ``anchor`` (``1 x d``) that was told the answer ``records``
    (in force, oldest first; items mapped by ``transform``), and its sizes before each.

    Items are numbered in order of first appearance (an item seen before reuses its number, as
    :meth:`~torchpref.data.preference_data.PreferenceData.add` does); a choice of row ``j`` of
    ``m`` is the comparisons ``[j, i]`` for ``i != j`` in order; no preference the ties of every
    two rows in order; a rating the record's value (its level, for an ordinal model).
    """
    rows: list[tuple[float, ...]] = []
    comparisons: list[list[int]] = []
    ties: list[list[int]] = []
    values: list[float] = []
    rated: list[int] = []
    ends: list[tuple[int, int, int, int]] = []  # after each record: rows, comparisons, ratings, ties
    pos = 1  # row 0 is the anchor
    for rec in records:
        items = rec.items
        m = len(items)
        rows.extend(items)
        kind = rec.kind
        if kind == "rating":
            if rec.value is None:
                raise SessionFileError(f"the rating record {rec.seq} has no value.")
            values.append(rec.value)
            rated.append(pos)
        elif kind == "choice":
            if not isinstance(rec.answer, int):
                raise SessionFileError(f"the choice record {rec.seq} has no chosen row: {rec.answer!r:.40}.")
            j = rec.answer
            comparisons.extend([pos + j, pos + i] for i in range(m) if i != j)
        else:
            ties.extend([pos + a, pos + b] for a in range(m) for b in range(a + 1, m))
        pos += m
        ends.append((pos, len(comparisons), len(values), len(ties)))
    new = transform(torch.tensor(rows, dtype=torch.float64)) if rows else anchor[:0]
    Z = torch.cat([anchor, new.to(anchor)])
    first, index = _unique_in_order(Z)
    C = index[torch.tensor(comparisons, dtype=torch.long).reshape(-1, 2)]
    T = index[torch.tensor(ties, dtype=torch.long).reshape(-1, 2)]
    R = torch.tensor(values, dtype=torch.float64)
    data = PreferenceData.create(
        Z[first],
        C,
        R if rating_levels is None else unit_to_likert(R, rating_levels),
        index[torch.tensor(rated, dtype=torch.long)],
        rating_eps=rating_eps,
        ties=T,
        rating_levels=rating_levels,
    )
    # items before each record: the distinct items first seen in the rows before it
    if not records:
        return data, []
    starts = torch.tensor([1] + [e[0] for e in ends[:-1]], dtype=torch.long)
    n_before = torch.searchsorted(first, starts).tolist()
    before = [(0, 0, 0)] + [e[1:] for e in ends[:-1]]
    return data, [Sizes(n, c, r, t) for n, (c, r, t) in zip(n_before, before, strict=True)]


def mode(model: PreferenceGP) -> Tensor:
    """The model's current posterior mode ``f`` (``n``), solving it if need be."""
    return model.mode.f.detach()


def truncate(model: PreferenceGP, before: Sizes, f: Tensor | None = None) -> None:
    """Take ``model`` back to its data of sizes ``before`` (a prefix of its data), the mode
    started from ``f`` (the mode it had then: Newton stops at once, and the model is bitwise the
    earlier one) or else from the current mode's first entries; on failure the model is as it was."""
    d = session_data(model)
    n, p, r, t = before
    prefix = PreferenceData(
        d.train_X[:n], d.comparisons[:p], d.ratings[:r], d.rating_index[:r], d.ties[:t], d.rating_levels
    )
    model.replace_data(prefix, mode(model)[:n] if f is None else f)


SNAPSHOT_FORMAT = "torchpref-session-mode"


def snapshot_path(path: Path) -> Path:
    """``FILE.mode`` beside the session file (shortened where the name would be too long)."""
    name = os.fsencode(path.name) + b".mode"
    if len(name) > 255:
        name = (
            os.fsencode(path.name)[:200]
            + b"~"
            + hashlib.sha256(os.fsencode(path.name)).hexdigest()[:8].encode()
            + b".mode"
        )
    return path.parent / os.fsdecode(name)


def header_digest(header: dict) -> str:
    """A short fingerprint of a session file's header (which file a snapshot belongs to)."""
    return hashlib.sha256(json.dumps(header, sort_keys=True).encode()).hexdigest()[:16]


def write_snapshot(path: Path, meta: dict, f: Tensor) -> None:
    """Write the model's mode after the record ``meta["seq"]`` beside the session file: a JSON line
    and the mode's float64 bytes, replaced atomically, not fsynced (it only speeds up a resume;
    a missing, stale or damaged snapshot is ignored), with the session file's permissions. Errors
    are ignored for the same reason."""
    target = snapshot_path(path)
    tmp = target.with_name(target.name + ".tmp")
    meta = dict(meta, format=SNAPSHOT_FORMAT, version=1, n=int(f.numel()))
    try:
        mode = stat.S_IMODE(os.stat(path).st_mode) & 0o666  # no more readable than the session file
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
        with os.fdopen(fd, "wb") as fh:
            os.fchmod(fh.fileno(), mode)
            fh.write(json.dumps(meta).encode() + b"\n")
            fh.write(f.detach().to(torch.float64).contiguous().numpy().astype("<f8").tobytes())
        os.replace(tmp, target)
    except (OSError, ValueError):
        pass


def read_snapshot(path: Path) -> tuple[dict, Tensor] | None:
    """The snapshot beside the session file ``path``, or ``None`` if there is none usable."""
    try:
        with open(snapshot_path(path), "rb") as fh:
            line = fh.readline(4096)
            meta = json.loads(line)
            n = int(meta["n"])
            if meta.get("format") != SNAPSHOT_FORMAT or not 0 < n <= 10**8:
                return None
            raw = fh.read(8 * n + 1)
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if len(raw) != 8 * n:
        return None
    f = torch.frombuffer(bytearray(raw), dtype=torch.float64).clone()
    if not torch.isfinite(f).all():
        return None
    return meta, f


REPLAY_LIMIT = 16
"""At most this many answers after the file's mode snapshot are replayed on resuming; more (a
snapshot left behind by a crash long ago) and the data are built in one pass instead."""

MODE_MEMORY = 4_000_000
"""How many floats of earlier posterior modes a session keeps for exact undos (32 MB in float64:
some 40,000 answers' worth on a pool of 100 items); an older answer's undo starts Newton from the
current mode instead (the posterior then agrees to Newton's tolerance)."""
