r"""The records of a session file (format version 1) and their validation.

Every record is checked when a file is opened and before a record is written
(:class:`~torchpref.sessions.journal.Journal`): the header's fields with their types and ranges, each
answer's sequence number, time, kind, items (one row for a rating, at least two for a choice or no
preference), answer (a whole level whose value is that level's rating, a row index, or null) and
query, and each undo's target. A failure is a :class:`SessionFileError` (a ``ValueError``) that
names the file, the line and the field. See ``docs/sessions.md`` for the format.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Container
from dataclasses import dataclass, field
from typing import Any, NoReturn, TypeGuard

import torch

from torchpref.data.preference_data import likert_to_unit
from torchpref.sessions.errors import (  # noqa: F401  (the errors stay importable from here, as before)
    SessionFileCorrupt,
    SessionFileError,
    SessionMismatchError,
    SessionRepairWarning,
    SessionVersionError,
)
from torchpref.version import __version__

__all__ = [
    "ANSWER_KINDS",
    "FORMAT_VERSION",
    "AnswerRecord",
    "Record",
    "SessionHeader",
    "UndoRecord",
    "parse_record",
    "check_new_record",
    "dumps_settings",
    "pool_size",
    "records_in_force",
    "validate_header",
    "validate_records",
]

FORMAT_VERSION = 1
"""The newest session-file format this version reads and the one it writes."""

ANSWER_KINDS = ("rating", "choice", "no_preference")
"""An answer is a rating (of one item), a choice (the best of ``m >= 2``) or no preference."""


@dataclass(frozen=True, slots=True)
class AnswerRecord:
    """One ``answer`` line of a session file, typed (``to_json`` gives the line's object).

    Attributes:
        seq: its sequence number (1, 2, ... over answers and undos).
        time: when it was written (ISO 8601, UTC).
        kind: ``"rating"``, ``"choice"`` or ``"no_preference"`` (:data:`ANSWER_KINDS`).
        items: the items shown, one row each (one row for a rating).
        answer: a rating's level (or its value in ``[0, 1]`` without levels), the chosen row, or ``None``.
        value: a rating's value in ``[0, 1]`` (ratings only, else ``None``).
        query: the question it answered (``{"kind", "step", "pool_indices"}``), or ``None`` out of turn.
        response_time: seconds from shown to answered where the front end measured them.
        shown_at, answered_at: when the front end showed the question and got the answer, if it said.
        v: the record's format version.
    """

    seq: int
    time: str
    kind: str
    items: tuple[tuple[float, ...], ...]
    answer: int | float | None
    value: float | None = None
    query: dict[str, Any] | None = None
    response_time: float | None = None
    shown_at: str | None = None
    answered_at: str | None = None
    v: int = FORMAT_VERSION
    type: str = field(default="answer", init=False)

    @property
    def step(self) -> int | None:
        """The query number it answered, or ``None`` if given out of turn."""
        return None if self.query is None else self.query.get("step")

    @property
    def query_kind(self) -> str | None:
        """The kind of question it answered (``"rating"`` or ``"ranking"``), or ``None`` out of turn."""
        return None if self.query is None else self.query.get("kind")

    @property
    def pool_indices(self) -> list[int] | None:
        """The items' rows in the session's pool, where known."""
        return None if self.query is None else self.query.get("pool_indices")

    def to_json(self) -> dict[str, Any]:
        """The record as written to the file (the keys and their order of format version 1)."""
        rec: dict[str, Any] = {"type": "answer", "v": self.v, "seq": self.seq, "time": self.time, "kind": self.kind}
        rec["items"] = [list(row) for row in self.items]
        rec["answer"] = self.answer
        if self.kind == "rating":
            rec["value"] = self.value
        rec.update(query=self.query, response_time=self.response_time)
        rec.update({k: t for k, t in (("shown_at", self.shown_at), ("answered_at", self.answered_at)) if t is not None})
        return rec

    @classmethod
    def from_json(
        cls, rec: dict[str, Any], header: dict[str, Any] | None = None, where: str = "record"
    ) -> AnswerRecord:
        """The typed record of a file's ``answer`` object; with the file's ``header``, checked first
        as when the file is read (:class:`~torchpref.sessions.errors.SessionFileError` naming ``where``
        and the field)."""
        c = _Line(where, rec)
        if rec.get("type") != "answer":
            c.fail(f"not an answer record: {rec.get('type')!r:.40}")
        if header is not None:
            c.integer("seq", lo=1)
            _check_answer(c, rec, header)
        return cls(
            seq=rec["seq"],
            time=rec["time"],
            kind=rec["kind"],
            items=tuple(tuple(float(x) for x in row) for row in rec["items"]),
            answer=rec.get("answer"),
            value=rec.get("value"),
            query=rec.get("query"),
            response_time=rec.get("response_time"),
            shown_at=rec.get("shown_at"),
            answered_at=rec.get("answered_at"),
            v=rec.get("v", 1),
        )


@dataclass(frozen=True, slots=True)
class UndoRecord:
    """One ``undo`` line of a session file: the answer ``undoes`` is withdrawn."""

    seq: int
    time: str
    undoes: int
    v: int = FORMAT_VERSION
    type: str = field(default="undo", init=False)

    def to_json(self) -> dict[str, Any]:
        """The record as written to the file."""
        return {"type": "undo", "v": self.v, "seq": self.seq, "time": self.time, "undoes": self.undoes}

    @classmethod
    def from_json(cls, rec: dict[str, Any], where: str = "record") -> UndoRecord:
        """The typed record of a file's ``undo`` object."""
        c = _Line(where, rec)
        if rec.get("type") != "undo":
            c.fail(f"not an undo record: {rec.get('type')!r:.40}")
        seq, undoes = c.integer("seq", lo=1), c.integer("undoes", lo=1)
        if not isinstance(rec.get("time"), str):
            c.fail(f"'time' must be a string, got {rec.get('time')!r:.80}")
        assert seq is not None and undoes is not None  # required fields: c.integer raised otherwise
        return cls(seq=seq, time=rec["time"], undoes=undoes, v=rec.get("v", 1))


@dataclass(frozen=True)
class SessionHeader:
    """A session file's header (its first line), typed: the only reader of the header's keys
    (:meth:`from_json`, after :func:`validate_header`); ``to_json`` gives the line's object.

    Attributes:
        version: the file's format version.
        dim: the items' dimension ``d``.
        seed, num_queries: the session's seed and planned number of questions.
        num_levels: ratings on ``1..K`` (``None``: in ``[0, 1]``).
        bounds: ``2 x d``, the lower and upper bounds of the model's unit cube.
        names: the features' names, or ``None``.
        candidates: the candidates as recorded (``{"kind": "pool", "items"}`` or ``{"kind": "box", ...}``).
        metadata: the extra settings the session was created with (a JSON object).
        model: the recorded model's description (``None`` in files of torchpref 0.1.0).
        selector: the recorded selector's description (``None`` likewise).
        queries: the fixed question list (``[kind, pool rows...]``), or ``None``.
        created: when the file was created (ISO 8601); ``torchpref``: the version that created it.
    """

    version: int
    dim: int
    seed: int
    num_queries: int
    num_levels: int | None
    bounds: tuple[tuple[float, ...], tuple[float, ...]]
    names: tuple[str, ...] | None
    candidates: dict[str, Any]
    metadata: dict[str, Any]
    model: dict[str, Any] | None = None
    selector: dict[str, Any] | None = None
    queries: list | None = None
    created: str = ""
    torchpref: str = ""

    @classmethod
    def from_json(cls, h: dict[str, Any], path: object = "session file") -> SessionHeader:
        """The typed header of the header object ``h`` of the file ``path`` (validated first).

        Raises:
            SessionFileError: ``h`` is not a valid header (:func:`validate_header`).
        """
        validate_header(path, h)
        lo, hi = h["bounds"]
        return cls(
            version=h["version"],
            dim=h["dim"],
            seed=h["seed"],
            num_queries=h["num_queries"],
            num_levels=h["num_levels"],
            bounds=(tuple(float(x) for x in lo), tuple(float(x) for x in hi)),
            names=None if h.get("names") is None else tuple(h["names"]),
            candidates=h["candidates"],
            metadata=dict(h.get("metadata") or {}),
            model=h.get("model"),
            selector=h.get("selector"),
            queries=h.get("queries"),
            created=str(h.get("created", "")),
            torchpref=str(h.get("torchpref", "")),
        )

    def to_json(self) -> dict[str, Any]:
        """The header's object as written to the file (the keys and their order of format version 1)."""
        out: dict[str, Any] = {
            "type": "header",
            "version": self.version,
            "dim": self.dim,
            "created": self.created,
            "torchpref": self.torchpref,
            "seed": self.seed,
            "num_queries": self.num_queries,
            "num_levels": self.num_levels,
            "bounds": [list(self.bounds[0]), list(self.bounds[1])],
            "names": None if self.names is None else list(self.names),
            "candidates": self.candidates,
            "metadata": self.metadata,
        }
        for key in ("model", "selector", "queries"):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        return out

    @property
    def pool(self) -> list[list[float]] | None:
        """The pool's items (rows), or ``None`` for a box of candidates or a pool recorded by
        reference (a large one: :attr:`first_item` and the digest only)."""
        return self.candidates.get("items") if self.candidates["kind"] == "pool" else None

    @property
    def first_item(self) -> list[float] | None:
        """The pool's first item (the one a session's model is built on), written out or by reference."""
        if self.candidates["kind"] != "pool":
            return None
        items = self.candidates.get("items")
        return items[0] if items else self.candidates.get("first_item")

    @property
    def bounds_tensor(self) -> torch.Tensor:
        """``bounds`` as a ``2 x d`` float64 tensor."""
        return torch.tensor(self.bounds, dtype=torch.float64)


Record = AnswerRecord | UndoRecord
"""A typed line of a session file after its header."""


def parse_record(rec: dict[str, Any]) -> Record:
    """The typed form of a record already validated (a :attr:`~torchpref.PreferenceSession.records` entry)."""
    return AnswerRecord.from_json(rec) if rec.get("type") == "answer" else UndoRecord.from_json(rec)


class _Line:
    """Checks on one record; every failure names the file and the line."""

    def __init__(self, where: str, rec: dict):
        self.where, self.rec = where, rec

    def fail(self, msg: str, error: type[Exception] = SessionFileError) -> NoReturn:
        raise error(f"{self.where}: {msg}.")

    def get(self, key: str, required: bool = True) -> object:
        if key not in self.rec:
            if required:
                self.fail(f"the {self.rec.get('type')} record has no {key!r}")
            return None
        return self.rec[key]

    def integer(self, key: str, lo: int | None = None, hi: int | None = None) -> int:
        """The required integer ``key`` in ``lo..hi``."""
        v = self.get(key)
        if not isinstance(v, int) or isinstance(v, bool) or (lo is not None and v < lo) or (hi is not None and v > hi):
            rng = f" in {lo}..{hi}" if hi is not None else (f" >= {lo}" if lo is not None else "")
            self.fail(f"{key!r} must be an integer{rng}, got {v!r:.80}")
        return v

    def matrix(self, value, name: str, cols: int, min_rows: int = 1, max_rows: int | None = None) -> list:
        ok = isinstance(value, list) and all(
            isinstance(r, list) and len(r) == cols and all(_is_number(x) and math.isfinite(x) for x in r) for r in value
        )
        if not ok:
            self.fail(f"{name} must be a list of rows of {cols} finite numbers, got {value!r:.120}")
        if len(value) < min_rows or (max_rows is not None and len(value) > max_rows):
            want = f"exactly {min_rows}" if max_rows == min_rows else f"at least {min_rows}"
            self.fail(f"{name} must have {want} row(s), got {len(value)}")
        return value

    def bounds(self, value, name: str, dim: int) -> list:
        b = self.matrix(value, name, dim, 2, 2)
        if not all(lo < hi for lo, hi in zip(*b, strict=True)):
            self.fail(f"{name} must have lower < upper in every dimension, got {b!r:.120}")
        return b


@functools.lru_cache(maxsize=64)
def _level_values(levels: int) -> tuple[float, ...]:
    """The rating of each Likert level ``1..levels`` (:func:`~torchpref.likert_to_unit`), computed once."""
    return tuple(likert_to_unit(torch.arange(1, levels + 1), levels).tolist())


def _is_number(x: object) -> TypeGuard[int | float]:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def validate_header(path: object, h: dict) -> None:
    """Check a header record (line 1 of ``path``); raises :class:`SessionFileError` naming the field."""
    c = _Line(f"session file {path}, line 1", h)
    if h.get("type") != "header":
        c.fail(f"the first record must be the header, got {h!r:.200}")
    version = c.integer("version", lo=1)
    if version > FORMAT_VERSION:
        c.fail(
            f"format version {version} is newer than this torchpref {__version__} reads (up to "
            f"{FORMAT_VERSION}); upgrade torchpref to open it",
            SessionVersionError,
        )
    dim = c.integer("dim", lo=1)
    c.integer("seed")
    c.integer("num_queries", lo=1)
    if c.get("num_levels") is not None:  # required, null for ratings in [0, 1]
        c.integer("num_levels", lo=2)
    c.bounds(c.get("bounds"), "bounds", dim)
    names = h.get("names")
    names_ok = isinstance(names, list) and len(names) == dim and all(isinstance(n, str) for n in names)
    if names is not None and not names_ok:
        c.fail(f"names must be null or {dim} strings, got {names!r:.120}")
    if not isinstance(h.get("metadata", {}), dict):
        c.fail(f"metadata must be a JSON object, got {h.get('metadata')!r:.80}")
    for key in ("model", "selector"):  # what the session started with (absent before torchpref 0.2)
        if h.get(key) is not None and not isinstance(h[key], dict):
            c.fail(f"{key} must be a JSON object, got {h[key]!r:.80}")
    spec = c.get("candidates")
    if not isinstance(spec, dict) or spec.get("kind") not in ("pool", "box"):
        c.fail(f"candidates must be {{'kind': 'pool' or 'box', ...}}, got {spec!r:.120}")
    if spec["kind"] == "pool" and "items" not in spec:  # a large pool, by reference (its digest)
        ref = _Line(c.where, spec)
        ref.integer("num_items", lo=1)
        c.matrix([spec.get("first_item")], "candidates' first_item", dim, 1, 1)
        if not (isinstance(spec.get("sha256"), str) and len(spec["sha256"]) == 64):
            c.fail(f"candidates' sha256 must be 64 hexadecimal digits, got {spec.get('sha256')!r:.80}")
        pool = None
    elif spec["kind"] == "pool":
        pool = c.matrix(spec.get("items"), "candidates' items", dim)
    else:
        c.bounds(spec.get("bounds"), "candidates' bounds", dim)
        _Line(c.where, spec).integer("num", lo=1)
        pool = None
    if h.get("queries") is not None:
        _check_question_list(c, h["queries"], pool if pool is not None or spec["kind"] != "pool" else spec["num_items"])


def _check_question_list(c: _Line, queries: object, pool: list | int | None) -> None:
    """A header's ``"queries"``: a non-empty list of ``["rating", row]`` or ``["ranking", row,
    row, ...]``, rows of the pool, distinct items within a question (a pool by reference, its
    size: rows only; the session checks the items against its pool)."""
    if pool is None:
        c.fail("a question list ('queries') needs a pool of candidates, not a box")
    if not isinstance(queries, list) or not queries:
        c.fail(f"'queries' must be a non-empty list of questions, got {queries!r:.80}")
    n = pool if isinstance(pool, int) else len(pool)
    for i, q in enumerate(queries):
        rows = q[1:] if isinstance(q, list) else []
        ok = (
            isinstance(q, list)
            and q[:1] in (["rating"], ["ranking"])
            and all(isinstance(r, int) and not isinstance(r, bool) and 0 <= r < n for r in rows)
            and (len(rows) == 1 if q[0] == "rating" else len(rows) >= 2)
            and (isinstance(pool, int) or len({tuple(pool[r]) for r in rows}) == len(rows))
        )
        if not ok:
            c.fail(
                f"queries[{i}] must be ['rating', row] or ['ranking', row, row, ...] with rows of distinct "
                f"items in 0..{n - 1}, got {q!r:.80}"
            )


def _check_answer(c: _Line, rec: dict, header: dict) -> None:
    kind = rec.get("kind")
    if kind not in ANSWER_KINDS:
        c.fail(f"unknown answer kind {kind!r:.80} (one of {', '.join(ANSWER_KINDS)})")
    c.get("time")
    if not isinstance(rec["time"], str):
        c.fail(f"'time' must be a string, got {rec['time']!r:.80}")
    dim = header["dim"]
    if kind == "rating":
        items = c.matrix(c.get("items"), "a rating's items", dim, 1, 1)
    else:
        items = c.matrix(c.get("items"), f"a {kind.replace('_', ' ')}'s items", dim, 2)
    answer, levels = c.get("answer"), header.get("num_levels")
    if kind == "rating":
        value = c.get("value")
        if levels is not None:
            level = c.integer("answer", lo=1, hi=levels)
            expected = _level_values(levels)[level - 1]
        else:
            if not (_is_number(answer) and 0.0 <= answer <= 1.0):
                c.fail(f"a rating must be a number in [0, 1], got {answer!r:.80}")
            expected = float(answer)
        if not _is_number(value) or value != expected:
            c.fail(f"the rating's value {value!r:.80} does not match its answer {answer!r} (expected {expected})")
    elif kind == "choice":
        c.integer("answer", lo=0, hi=len(items) - 1)
    elif answer is not None:
        c.fail(f"no preference has answer null, got {answer!r:.80}")
    rt = rec.get("response_time")
    if rt is not None and not (_is_number(rt) and math.isfinite(rt) and rt >= 0):
        c.fail(f"'response_time' must be null or a finite number of seconds >= 0, got {rt!r:.80}")
    for key in ("shown_at", "answered_at"):  # optional: when the front end showed and got the answer
        if key in rec and not (isinstance(rec[key], str) and 0 < len(rec[key]) <= 40):
            c.fail(f"'{key}' must be an ISO 8601 time string, got {rec[key]!r:.80}")
    _check_query(c, rec.get("query"), kind, len(items), header)


def _check_query(c: _Line, q, kind: str, m: int, header: dict) -> None:
    if q is None:
        return
    if not isinstance(q, dict):
        c.fail(f"'query' must be null or a JSON object, got {q!r:.80}")
    want = "rating" if kind == "rating" else "ranking"
    if q.get("kind") != want:
        c.fail(f"a {kind} answers a {want} query, not {q.get('kind')!r:.80}")
    if q.get("step") is not None:  # null (or absent) for an answer given out of turn
        _Line(c.where, q).integer("step", lo=0)
    idx = q.get("pool_indices")
    if idx is None:
        return
    spec = header["candidates"]
    n = pool_size(spec)
    if not (
        isinstance(idx, list)
        and len(idx) == m
        and all(isinstance(i, int) and not isinstance(i, bool) and 0 <= i < n for i in idx)
    ):
        c.fail(f"pool_indices must be {m} rows of the pool of {n} items, got {idx!r:.80}")
    if "items" in spec and any(spec["items"][i] != row for i, row in zip(idx, c.rec["items"], strict=True)):
        c.fail(f"the items are not the pool's rows {idx}")


def pool_size(spec: dict) -> int:
    """The number of items of a header's candidates: a pool's (written out or by reference), 0 for a box."""
    if spec.get("kind") != "pool":
        return 0
    return len(spec["items"]) if "items" in spec else int(spec["num_items"])


def validate_records(path: object, header: dict, records: list[dict], first_line: int = 2) -> None:
    """Check every record after the header: format version, sequence numbers, answer schema,
    undo targets. Raises :class:`SessionFileError` (or :class:`SessionVersionError`) naming the line."""
    last_seq, active = 0, set[int]()
    for i, rec in enumerate(records, start=first_line):
        last_seq = _check_record(_Line(f"session file {path}, line {i}", rec), header, last_seq, active)


def _check_record(c: _Line, header: dict, last_seq: int, active: Container[int], update: bool = True) -> int:
    """Check one record after those with sequence numbers up to ``last_seq`` and answers
    ``active`` in force (a set, updated; or, with ``update=False``, any container, read only);
    returns its sequence number."""
    rec = c.rec
    v = rec.get("v", 1)
    if not isinstance(v, int) or isinstance(v, bool) or v < 1:
        c.fail(f"record format version 'v' must be a positive integer, got {v!r:.80}")
    if v > FORMAT_VERSION:
        c.fail(
            f"record format version {v} is newer than {FORMAT_VERSION}; upgrade torchpref to open it",
            SessionVersionError,
        )
    seq = c.integer("seq", lo=1)
    if seq <= last_seq:
        c.fail(f"sequence number {seq} does not follow {last_seq}")
    if rec["type"] == "answer":
        _check_answer(c, rec, header)
        if update and isinstance(active, set):
            active.add(seq)
    elif rec["type"] == "undo":
        if not isinstance(rec.get("time"), str):
            c.fail(f"'time' must be a string, got {rec.get('time')!r:.80}")
        undoes = rec.get("undoes")
        if not isinstance(undoes, int) or isinstance(undoes, bool) or undoes not in active:
            c.fail(f"undo of {undoes!r:.80}, not an answer in force")
        if update and isinstance(active, set):
            active.discard(undoes)
    else:
        c.fail(f"unknown record type {rec['type']!r:.80}")
    return seq


def check_new_record(
    where: str,
    header: dict,
    records: list[dict] | None,
    record: dict,
    *,
    last_seq: int = 0,
    in_force: Container[int] | None = None,
) -> None:
    """Check ``record`` as the next one after ``records`` (before it is written: the file never
    gets a record it could not read back). ``last_seq`` and ``in_force`` (the sequence numbers of
    the answers in force, any container) given instead of ``records`` make it constant-time."""
    if in_force is None:
        in_force = {r["seq"] for r in records_in_force(records or [])}
        last_seq = records[-1]["seq"] if records else 0
    _check_record(_Line(where, record), header, last_seq, in_force, update=False)


def records_in_force(records: list[dict]) -> list[dict]:
    """The answer records not undone, oldest first."""
    active: dict[int, dict] = {}
    for rec in records:
        if rec["type"] == "answer":
            active[rec["seq"]] = rec
        else:
            active.pop(rec["undoes"], None)
    return list(active.values())


def dumps_settings(value: object) -> str:
    """A canonical JSON text of a header setting, to compare a file's settings with a session's."""
    return json.dumps(value, sort_keys=True)
