r"""An ask/tell elicitation session that keeps every answer in an append-only file.

:class:`PreferenceSession` proposes the next query (:meth:`~PreferenceSession.ask`), takes the
answer (:meth:`~PreferenceSession.tell`), and keeps a :class:`~torchpref.PreferenceGP` current.
It also takes answers given out of turn (:meth:`~PreferenceSession.tell_rating`,
:meth:`~PreferenceSession.tell_choice`, :meth:`~PreferenceSession.tell_no_preference`) and
undoes the last answer (:meth:`~PreferenceSession.undo`).

With a ``session_file`` every answer is appended as one JSON line and flushed to disk
(``fsync``) before ``tell`` returns. The model is a pure function of the answers in the file:
starting again from the file replays them, in order, through exactly the same sequence of
warm-started updates, so the restored posterior is bitwise the one the interrupted process had,
and the next query is the one it would have asked (the selector's random numbers for query
``k`` come from ``(seed, k)``, not from a stream that a restart would lose).

File format (version 1, see ``docs/sessions.md``)::

    {"type": "header", "version": 1, "dim": 2, "created": "...", "seed": 0, ...}
    {"type": "answer", "v": 1, "seq": 1, "time": "...", "kind": "rating", "items": [[...]], ...}
    {"type": "undo", "v": 1, "seq": 2, "time": "...", "undoes": 1}

A last line without its newline, or one that is not valid JSON (a crash mid-write), raises
:class:`SessionFileCorrupt` with the line number; ``repair=True`` reports it (a
:class:`SessionRepairWarning`), moves the partial bytes to ``FILE.dropped`` and truncates the
file to its last complete record.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import torch
from torch import Tensor

from torchpref.data import best_of_m, likert_to_unit
from torchpref.models import PreferenceGP, default_covar_module
from torchpref.queries import (BoxCandidates, Candidates, FinitePool, Query, RankingQuery, RatingQuery,
                               first_unique_rows)
from torchpref.strategies import UCBC, Selector
from torchpref.version import __version__

__all__ = [
    "FORMAT_VERSION",
    "PreferenceSession",
    "SessionAnswer",
    "SessionFileCorrupt",
    "SessionFileError",
    "SessionMismatchError",
    "SessionRepairWarning",
    "SessionVersionError",
    "default_session_model",
    "read_session_file",
    "step_generator",
]

FORMAT_VERSION = 1
"""The newest session-file format this version reads and the one it writes."""

ANSWER_KINDS = ("rating", "choice", "no_preference")


class SessionFileError(ValueError):
    """A session file that cannot be used as it is."""


class SessionFileCorrupt(SessionFileError):
    """A line of a session file is incomplete or not a valid record.

    Attributes:
        path: the file.
        line_number: the 1-based number of the bad line.
        reason: what is wrong with it.
        repairable: whether ``repair=True`` can fix it (only a bad *last* line: a crash
            mid-write; a bad line followed by good ones is never dropped).
        partial: the bad line's bytes.
        offset: the byte offset where the bad line starts.
    """

    def __init__(self, path, line_number: int, reason: str, repairable: bool, partial: bytes, offset: int):
        self.path, self.line_number, self.reason = str(path), line_number, reason
        self.repairable, self.partial, self.offset = repairable, partial, offset
        fix = (
            "It looks like a crash in the middle of writing the last answer. To recover, open it with "
            "repair=True (PreferenceSession(..., repair=True) or PreferenceSession.load(path, repair=True)): "
            f"the partial line is moved to {self.path}.dropped, the file is truncated to its last complete "
            "record, and that answer is asked again."
            if repairable
            else "The lines after it are valid, so this is not an interrupted write; the file was edited or "
            "damaged and must be fixed by hand."
        )
        super().__init__(f"session file {self.path}, line {line_number}: {reason}. {fix}")


class SessionVersionError(SessionFileError):
    """The file was written by a newer format version than this library reads."""


class SessionMismatchError(SessionFileError):
    """The file was written for other items, dimensions or settings than those given."""


class SessionRepairWarning(UserWarning):
    """A partial last line was removed from a session file (``repair=True``)."""


@dataclass(frozen=True)
class SessionAnswer:
    """One answer in force (not undone).

    Attributes:
        seq: its sequence number in the file.
        kind: ``"rating"``, ``"choice"`` or ``"no_preference"``.
        items: ``m x d`` the items' coordinates as shown (``1 x d`` for a rating).
        answer: the answer as given: a Likert level (or a rating in ``[0, 1]`` when the session
            has no levels) for a rating, the index of the chosen row of ``items`` for a choice,
            ``None`` for no preference.
        value: the rating in ``[0, 1]`` the model uses (ratings only).
        step: the query number it answered, or ``None`` if given out of turn.
        pool_indices: the items' rows in the candidate pool, where known.
        time: ISO 8601 timestamp.
    """

    seq: int
    kind: str
    items: Tensor
    answer: Any
    value: float | None
    step: int | None
    pool_indices: tuple[int, ...] | None
    time: str


def step_generator(seed: int, step: int) -> torch.Generator:
    """The generator for query ``step`` of a session seeded ``seed``: a fresh stream per step, so a
    restarted session proposes what the uninterrupted one would have."""
    digest = hashlib.sha256(f"torchpref-session:{int(seed)}:{int(step)}".encode()).digest()
    return torch.Generator().manual_seed(int.from_bytes(digest[:8], "little") & ((1 << 63) - 1))


def default_session_model(train_X: Tensor) -> PreferenceGP:
    r"""The default model of a session: :class:`~torchpref.PreferenceGP` on inputs normalised to the
    unit cube, an RBF kernel with lengthscale 0.2 and outputscale ``sigma_f^2 = 1`` (eq. 1), and the
    model's default likelihood settings (``sigma_R = 0.1``, ``sigma_B = 1``, ``nu = 80``), all fixed."""
    kernel = default_covar_module(train_X.shape[-1]).to(train_X)
    kernel.base_kernel.lengthscale = 0.2
    kernel.outputscale = 1.0
    return PreferenceGP(train_X, covar_module=kernel)


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def _write_all(fd: int, data: bytes) -> None:
    """Write all of ``data`` to ``fd`` (``os.write`` may write less than asked)."""
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def _encode(record: dict) -> bytes:
    return (json.dumps(record, allow_nan=False, separators=(",", ":")) + "\n").encode()


def read_session_file(path) -> tuple[dict | None, list[dict], int]:
    """Parse a session file without changing it.

    Returns:
        ``(header, records, size)``: the header (``None`` for an empty file), the records after
        it in order, and the file's size in bytes.

    Raises:
        SessionFileCorrupt: a line is incomplete or invalid (with its line number).
        SessionVersionError: a record is of a newer format version.
        SessionFileError: the records are inconsistent (sequence numbers, undo targets).
    """
    path = Path(path)
    data = path.read_bytes()
    if not data:
        return None, [], 0
    lines = data.split(b"\n")
    complete = lines[:-1]  # the text after the last newline is "" for a well-formed file
    tail = lines[-1]
    parsed: list[dict] = []
    offset = 0
    for i, line in enumerate(complete):
        is_last = i == len(complete) - 1 and not tail
        try:
            rec = json.loads(line.decode())
            if not isinstance(rec, dict) or "type" not in rec:
                raise ValueError("not a JSON object with a 'type'")
        except (UnicodeDecodeError, ValueError) as exc:
            raise SessionFileCorrupt(path, i + 1, f"not a valid record ({exc})", is_last, line, offset) from None
        parsed.append(rec)
        offset += len(line) + 1
    if tail:
        raise SessionFileCorrupt(path, len(lines), "the last line is incomplete (no newline at its end)", True, tail,
                                 offset)
    header, records = parsed[0], parsed[1:]
    if header.get("type") != "header":
        raise SessionFileError(f"session file {path}, line 1: the first record must be the header, got {header!r:.200}.")
    version = header.get("version")
    if not isinstance(version, int) or version < 1:
        raise SessionFileError(f"session file {path}: the header has no valid version ({version!r}).")
    if version > FORMAT_VERSION:
        raise SessionVersionError(
            f"session file {path} has format version {version}, newer than this torchpref {__version__} reads "
            f"(up to {FORMAT_VERSION}); upgrade torchpref to open it."
        )
    last_seq = 0
    active: set[int] = set()
    for i, rec in enumerate(records, start=2):
        v = rec.get("v", 1)
        if not isinstance(v, int) or v > FORMAT_VERSION:
            raise SessionVersionError(
                f"session file {path}, line {i}: record format version {v!r} is newer than {FORMAT_VERSION}; "
                "upgrade torchpref to open it."
            )
        seq = rec.get("seq")
        if not isinstance(seq, int) or seq <= last_seq:
            raise SessionFileError(f"session file {path}, line {i}: sequence number {seq!r} does not follow {last_seq}.")
        last_seq = seq
        if rec["type"] == "answer":
            if rec.get("kind") not in ANSWER_KINDS:
                raise SessionFileError(f"session file {path}, line {i}: unknown answer kind {rec.get('kind')!r}.")
            active.add(seq)
        elif rec["type"] == "undo":
            if rec.get("undoes") not in active:
                raise SessionFileError(f"session file {path}, line {i}: undo of {rec.get('undoes')!r}, not an answer in force.")
            active.discard(rec["undoes"])
        else:
            raise SessionFileError(f"session file {path}, line {i}: unknown record type {rec['type']!r}.")
    return header, records, len(data)


def _repair(path: Path, err: SessionFileCorrupt) -> None:
    """Move a partial last line to ``path.dropped`` and truncate ``path`` before it (reported)."""
    dropped = Path(str(path) + ".dropped")
    with open(dropped, "ab") as f:
        f.write(f"# {_now()} line {err.line_number} of {path.name}: {err.reason}\n".encode() + err.partial + b"\n")
        f.flush()
        os.fsync(f.fileno())
    fd = os.open(path, os.O_WRONLY)
    try:
        os.ftruncate(fd, err.offset)
        os.fsync(fd)
    finally:
        os.close(fd)
    warnings.warn(
        f"session file {path}: removed the incomplete line {err.line_number} ({len(err.partial)} bytes, kept in "
        f"{dropped}); its answer, if any, will be asked again.",
        SessionRepairWarning,
        stacklevel=3,
    )


def _as_items(X, dim: int, name: str) -> Tensor:
    try:
        t = torch.as_tensor(X, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"{name} must be numbers, got {X!r}.") from None
    if t.dim() == 1:
        t = t.unsqueeze(0)
    if t.dim() != 2 or t.shape[-1] != dim:
        raise ValueError(f"{name} must be m x {dim}, got shape {tuple(t.shape)}.")
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} must be finite, got {t.tolist()}.")
    return t


def _same(a, b) -> bool:
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


class PreferenceSession:
    r"""Ask queries, take answers, keep the model current; optionally persisted to a file.

    Args:
        candidates: the items queries are built from: an ``N x d`` tensor (a finite pool), a
            :class:`~torchpref.FinitePool` or a :class:`~torchpref.BoxCandidates`.
        selector: picks each query (default :class:`~torchpref.UCBC` with ``m = min(5, N)``).
        model_factory: ``train_X -> PreferenceGP``, called with one ``1 x d`` unobserved anchor
            item (normalised); default :func:`default_session_model`. Its hyperparameters stay as
            built (refitting would make the model depend on more than the answers).
        session_file: a JSON Lines file; created if missing or empty, resumed otherwise.
        seed: seeds query ``k``'s random choices through :func:`step_generator`.
        num_queries: the planned number of queries (``T`` of the selector; see :attr:`done`).
        num_levels: ratings are Likert levels ``1..num_levels``, mapped to ``[0, 1]`` by
            :func:`~torchpref.likert_to_unit` (bin centres); ``None``: ratings in ``[0, 1]``.
        bounds: ``2 x d`` lower and upper bounds used to normalise items to the unit cube for the
            model (default: the pool's range, or the box).
        names: the objectives' names (stored in the header).
        repair: if the file ends in a partial line, report it, move it to ``FILE.dropped`` and
            continue; by default that raises :class:`SessionFileCorrupt`.
        metadata: JSON-serialisable extra settings stored in a new file's header.

    Raises:
        SessionFileCorrupt, SessionVersionError, SessionMismatchError: see :meth:`load`.

    Example:
        >>> s = PreferenceSession(X_pool, session_file="me.jsonl")
        >>> q = s.ask()
        >>> s.tell(q, 4 if q.kind == "rating" else 0)
    """

    def __init__(
        self,
        candidates: Tensor | Candidates,
        *,
        selector: Selector | None = None,
        model_factory: Callable[[Tensor], PreferenceGP] | None = None,
        session_file: str | os.PathLike | None = None,
        seed: int = 0,
        num_queries: int = 14,
        num_levels: int | None = 5,
        bounds: Tensor | None = None,
        names: Sequence[str] | None = None,
        repair: bool = False,
        metadata: dict | None = None,
    ) -> None:
        if isinstance(candidates, Tensor):
            candidates = FinitePool(_as_items(candidates, candidates.shape[-1], "candidates"))
        if isinstance(candidates, FinitePool):
            pool = candidates.X.to(torch.float64)
            candidates = FinitePool(pool)
            spec = {"kind": "pool", "items": pool.tolist()}
            lo, hi = pool.min(0).values, pool.max(0).values
        elif isinstance(candidates, BoxCandidates):
            b = candidates.bounds.to(torch.float64)
            candidates = BoxCandidates(b, candidates.num)
            spec = {"kind": "box", "bounds": b.tolist(), "num": candidates.num}
            lo, hi = b[0], b[1]
        else:
            raise TypeError(f"candidates must be a tensor, FinitePool or BoxCandidates, got {type(candidates).__name__}.")
        self._candidates = candidates
        self._spec = spec
        self.dim = int(lo.shape[0])
        if bounds is None:
            width = hi - lo
            hi = torch.where(width > 0, hi, lo + 1.0)
            bounds = torch.stack([lo, hi])
        bounds = torch.as_tensor(bounds, dtype=torch.float64)
        if bounds.shape != (2, self.dim) or not torch.isfinite(bounds).all() or not (bounds[1] > bounds[0]).all():
            raise ValueError(f"bounds must be 2 x {self.dim} finite with lower < upper, got {bounds.tolist()}.")
        self.bounds = bounds
        if num_levels is not None and (int(num_levels) != num_levels or num_levels < 2):
            raise ValueError(f"num_levels must be an integer >= 2 or None, got {num_levels!r}.")
        if int(num_queries) != num_queries or num_queries < 1:
            raise ValueError(f"num_queries must be a positive integer, got {num_queries!r}.")
        if names is not None and len(names) != self.dim:
            raise ValueError(f"names must give {self.dim} names, got {list(names)}.")
        self.num_levels = None if num_levels is None else int(num_levels)
        self.num_queries = int(num_queries)
        self.seed = int(seed)
        self.names = None if names is None else [str(n) for n in names]
        n_pool = first_unique_rows(self._pool).numel() if self._pool is not None else None
        self.selector = selector if selector is not None else UCBC(m=min(5, n_pool) if n_pool else 5)
        self.model_factory = model_factory if model_factory is not None else default_session_model
        self._anchor = self.transform(self._pool[:1] if self._pool is not None else bounds.mean(0, keepdim=True))
        self._records: list[dict] = []
        self._active: list[dict] = []
        self._next_seq = 1
        self._pending: Query | None = None
        self._pending_step: int | None = None
        self._fd: int | None = None
        self.path = None if session_file is None else Path(session_file)
        if self.path is not None:
            self._open(repair, metadata)
        self._model = self._replay(self._active)

    # ------------------------------------------------------------------ file
    @property
    def _pool(self) -> Tensor | None:
        return self._candidates.X if isinstance(self._candidates, FinitePool) else None

    def _header(self, metadata: dict | None) -> dict:
        return {
            "type": "header",
            "version": FORMAT_VERSION,
            "dim": self.dim,
            "created": _now(),
            "torchpref": __version__,
            "seed": self.seed,
            "num_queries": self.num_queries,
            "num_levels": self.num_levels,
            "bounds": self.bounds.tolist(),
            "names": self.names,
            "candidates": self._spec,
            "metadata": metadata or {},
        }

    def _open(self, repair: bool, metadata: dict | None) -> None:
        path = self.path
        if path.exists():
            try:
                header, records, _ = read_session_file(path)
            except SessionFileCorrupt as err:
                if not (repair and err.repairable):
                    raise
                _repair(path, err)
                header, records, _ = read_session_file(path)
        else:
            header, records = None, []
        if header is not None:
            self._check_header(header)
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            self._lock(fd)
            if header is None:
                _write_all(fd, _encode(self._header(metadata)))
                os.fsync(fd)
                _fsync_dir(path)
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd
        self._records = records
        for rec in records:
            self._next_seq = rec["seq"] + 1
            if rec["type"] == "answer":
                self._active.append(rec)
            else:
                self._active = [r for r in self._active if r["seq"] != rec["undoes"]]
        for rec in self._active:
            self._check_record_items(rec)

    def _lock(self, fd: int) -> None:
        try:
            import fcntl
        except ImportError:  # not POSIX: no advisory lock
            return
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise SessionFileError(f"session file {self.path} is in use by another process.") from None

    def _check_header(self, h: dict) -> None:
        p = self.path
        if h.get("dim") != self.dim:
            raise SessionMismatchError(
                f"session file {p} was written for {h.get('dim')}-dimensional items, but these items have "
                f"{self.dim} dimensions."
            )
        for key, mine in (("candidates", self._spec), ("bounds", self.bounds.tolist()), ("seed", self.seed),
                          ("num_levels", self.num_levels)):
            if not _same(h.get(key), mine):
                theirs = h.get(key)
                if key == "candidates":
                    theirs, mine = _describe(theirs), _describe(mine)
                raise SessionMismatchError(
                    f"session file {p} was written with {key} {theirs}, but this session has {key} {mine}; "
                    f"open it with PreferenceSession.load({str(p)!r}) to use the file's settings."
                )

    def _check_record_items(self, rec: dict) -> None:
        items = torch.tensor(rec["items"], dtype=torch.float64)
        if items.dim() != 2 or items.shape[-1] != self.dim:
            raise SessionMismatchError(f"session file {self.path}: record {rec['seq']} has items of shape "
                                       f"{tuple(items.shape)}, not m x {self.dim}.")

    @classmethod
    def load(cls, path: str | os.PathLike, candidates: Tensor | Candidates | None = None, **kwargs: Any) -> "PreferenceSession":
        """Resume the session in ``path`` with the settings in its header (seed, levels, bounds,
        candidates, names); ``selector``, ``model_factory``, ``repair`` and ``num_queries`` may be given.

        Raises:
            FileNotFoundError: no such file.
            SessionFileCorrupt: a line is incomplete or invalid (``repair=True`` fixes a bad last line).
            SessionVersionError: the file is of a newer format version.
            SessionMismatchError: ``candidates`` given that differ from the file's.
        """
        path = Path(path)
        try:
            header, _, _ = read_session_file(path)
        except SessionFileCorrupt as err:
            if not (kwargs.get("repair") and err.repairable):
                raise
            _repair(path, err)
            header, _, _ = read_session_file(path)
        if header is None:
            raise SessionFileError(f"session file {path} is empty: create the session with PreferenceSession(...).")
        if candidates is None:
            spec = header["candidates"]
            if spec["kind"] == "pool":
                candidates = torch.tensor(spec["items"], dtype=torch.float64)
            else:
                candidates = BoxCandidates(torch.tensor(spec["bounds"], dtype=torch.float64), spec["num"])
        kwargs.setdefault("num_queries", header["num_queries"])
        kwargs.setdefault("num_levels", header["num_levels"])
        kwargs.setdefault("names", header.get("names"))
        return cls(candidates, session_file=path, seed=header["seed"],
                   bounds=torch.tensor(header["bounds"], dtype=torch.float64), **kwargs)

    def close(self) -> None:
        """Release the file (every answer is already on disk)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> "PreferenceSession":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass

    def _append(self, record: dict) -> None:
        """Append ``record`` and fsync; on any failure the file is truncated back as it was."""
        if self.path is None:
            return
        if self._fd is None:
            raise SessionFileError(f"session file {self.path} is closed.")
        data = _encode(record)
        size = os.fstat(self._fd).st_size
        try:
            _write_all(self._fd, data)
            os.fsync(self._fd)
        except BaseException:
            os.ftruncate(self._fd, size)
            os.fsync(self._fd)
            raise

    # ----------------------------------------------------------------- model
    def transform(self, X: Tensor) -> Tensor:
        """Items (``... x d``) normalised by :attr:`bounds` to the unit cube, as the model sees them."""
        lo, hi = self.bounds
        return (X.to(torch.float64) - lo) / (hi - lo)

    def _apply(self, model: PreferenceGP, rec: dict) -> None:
        """Add one answer record to ``model``, in the same way on every path (live and replay)."""
        if rec["kind"] == "no_preference":
            return
        items = self.transform(torch.tensor(rec["items"], dtype=torch.float64))
        model.mode  # the mode for the current data first (as ask() leaves it): identical warm starts
        if rec["kind"] == "rating":
            model.add_observations(items, ratings=[rec["value"]], rating_index=[0])
        else:
            model.add_observations(items, comparisons=best_of_m(rec["answer"], list(range(items.shape[0]))))

    def _replay(self, records: list[dict]) -> PreferenceGP:
        model = self.model_factory(self._anchor.clone())
        for rec in records:
            self._apply(model, rec)
        return model

    @property
    def model(self) -> PreferenceGP:
        """The current model (inputs normalised: use :meth:`transform`, or :meth:`predict`)."""
        return self._model

    def predict(self, X: Tensor) -> tuple[Tensor, Tensor]:
        """Posterior mean and standard deviation of the utility at the rows of ``X`` (``N x d``)."""
        X = _as_items(X, self.dim, "X")
        with torch.no_grad():
            post = self._model.posterior(self.transform(X).unsqueeze(-2))
        return post.mean.reshape(-1), post.variance.reshape(-1).clamp_min(0).sqrt()

    def expected_rating(self, X: Tensor) -> Tensor:
        """Expected rating in ``[0, 1]`` at the rows of ``X`` (``N x d``) (eq. 11)."""
        X = _as_items(X, self.dim, "X")
        with torch.no_grad():
            return self._model.expected_rating(self.transform(X))

    def best_item(self) -> tuple[int | None, Tensor]:
        """The item of largest posterior mean: ``(pool index, item)`` over the pool, or
        ``(None, item)`` over the items answered about when candidates are a box."""
        if self._pool is not None:
            X = self._pool
        else:
            seen = [torch.tensor(r["items"], dtype=torch.float64) for r in self._active if r["kind"] != "no_preference"]
            if not seen:
                raise ValueError("no items rated or compared yet: best_item needs a pool or some answers.")
            X = torch.cat(seen).unique(dim=0)
        i = int(self.predict(X)[0].argmax())
        return (i if self._pool is not None else None), X[i]

    # ---------------------------------------------------------------- ask/tell
    @property
    def step(self) -> int:
        """The number of answers in force: the next query's number."""
        return len(self._active)

    @property
    def done(self) -> bool:
        """Whether ``num_queries`` answers are in force (asking more is allowed)."""
        return self.step >= self.num_queries

    @property
    def history(self) -> list[SessionAnswer]:
        """The answers in force, oldest first."""
        out = []
        for r in self._active:
            q = r.get("query") or {}
            out.append(SessionAnswer(r["seq"], r["kind"], torch.tensor(r["items"], dtype=torch.float64),
                                     r.get("answer"), r.get("value"), q.get("step"),
                                     None if q.get("pool_indices") is None else tuple(q["pool_indices"]), r["time"]))
        return out

    @property
    def records(self) -> list[dict]:
        """Every record written (answers, including undone ones, and undos), as in the file."""
        return list(self._records)

    def ask(self) -> Query:
        """The next query (the same one until it is answered or the session changes). Its items
        are in the caller's coordinates; ``index`` / ``indices`` are pool rows (or ``None``)."""
        if self._pending is not None:
            return self._pending
        step = self.step
        gen = step_generator(self.seed, step)
        X, idx = self._candidates.draw(gen)
        rows = torch.arange(X.shape[0])  # a pool draws each distinct item once (FinitePool)
        q = self.selector.select(self._model, self.transform(X), rows, step, self.num_queries, gen)
        if isinstance(q, RatingQuery):
            r = int(q.index)
            query: Query = RatingQuery(X[r], None if idx is None else int(idx[r]))
        else:
            rr = list(q.indices)
            query = RankingQuery(X[rr], None if idx is None else tuple(int(idx[r]) for r in rr))
        self._pending, self._pending_step = query, step
        return query

    def tell(self, query: Query, answer: int | float | None) -> None:
        """Record ``answer`` to ``query``: a Likert level (or a ``[0, 1]`` rating if the session has
        no levels) for a :class:`~torchpref.RatingQuery`; the index of the chosen row of
        ``query.items`` for a :class:`~torchpref.RankingQuery`, or ``None`` for no preference.

        Raises:
            ValueError: an invalid answer (naming it); the session and the file are unchanged.
        """
        info: dict[str, Any] = {"kind": getattr(query, "kind", None)}
        if query is self._pending:
            info["step"] = self._pending_step
        if isinstance(query, RatingQuery):
            info["pool_indices"] = None if query.index is None else [int(query.index)]
            self._tell_rating(query.item, answer, info)
        elif isinstance(query, RankingQuery):
            info["pool_indices"] = None if query.indices is None else [int(i) for i in query.indices]
            if answer is None:
                self._tell(self._body("no_preference", query.items, None, None, info))
            elif isinstance(answer, bool):
                raise ValueError(f"a ranking answer must be an item index in 0..{query.m - 1}, got {answer!r}.")
            else:
                self._tell_choice(query.items, query.validate_answer(answer), info)
        else:
            raise TypeError(f"query must be a RatingQuery or RankingQuery, got {type(query).__name__}.")

    def tell_rating(self, x: Tensor, rating: int | float) -> None:
        """A rating of any item ``x`` (``d``), given out of turn: a Likert level (or ``[0, 1]``)."""
        self._tell_rating(x, rating, None)

    def tell_choice(self, X_shown: Tensor, chosen: int) -> None:
        """A choice of row ``chosen`` among any shown items ``X_shown`` (``m x d``, ``m >= 2``)."""
        X = _as_items(X_shown, self.dim, "X_shown")
        if isinstance(chosen, (bool, str)):
            raise ValueError(f"chosen must be a row index in 0..{X.shape[0] - 1}, got {chosen!r}.")
        self._tell_choice(X, RankingQuery(X).validate_answer(chosen), None)

    def tell_no_preference(self, X_shown: Tensor) -> None:
        """The person saw ``X_shown`` (``m x d``) and had no preference: recorded in the file and
        the history, not used by the model (it has no tie likelihood)."""
        X = _as_items(X_shown, self.dim, "X_shown")
        if X.shape[0] < 2:
            raise ValueError(f"no preference needs at least 2 items shown, got {X.shape[0]}.")
        self._tell(self._body("no_preference", X, None, None, None))

    def _tell_rating(self, x, answer, info) -> None:
        x = _as_items(x, self.dim, "x")
        if x.shape[0] != 1:
            raise ValueError(f"a rating is of one item, got {x.shape[0]}.")
        if isinstance(answer, bool) or isinstance(answer, str):
            raise ValueError(f"a rating must be a number, got {answer!r}.")
        if self.num_levels is not None:
            try:
                level = float(answer)
                value = float(likert_to_unit(level, self.num_levels))
            except (TypeError, ValueError):
                raise ValueError(f"a rating must be a Likert level in 1..{self.num_levels}, got {answer!r}.") from None
            answer = int(level)
        else:
            value = RatingQuery(x[0]).validate_answer(answer)
            answer = value
        self._tell(self._body("rating", x, answer, value, info))

    def _tell_choice(self, X: Tensor, chosen: int, info) -> None:
        if X.shape[0] < 2:
            raise ValueError(f"a choice needs at least 2 items shown, got {X.shape[0]}.")
        self._tell(self._body("choice", X, int(chosen), None, info))

    def _body(self, kind: str, X: Tensor, answer, value, info) -> dict:
        body = {"type": "answer", "v": FORMAT_VERSION, "kind": kind, "items": X.tolist(), "answer": answer}
        if value is not None:
            body["value"] = value
        body["query"] = info
        return body

    def _tell(self, body: dict) -> None:
        rec = {"type": "answer", "v": FORMAT_VERSION, "seq": self._next_seq, "time": _now(), **body}
        self._apply(self._model, rec)  # validated and solved first; unchanged on error
        try:
            self._append(rec)
        except BaseException:
            self._model = self._replay(self._active)
            raise
        self._records.append(rec)
        self._active.append(rec)
        self._next_seq += 1
        self._pending = self._pending_step = None

    def undo(self) -> SessionAnswer:
        """Withdraw the last answer in force (an ``undo`` record is appended; the model is rebuilt
        from the remaining answers) and return it.

        Raises:
            ValueError: nothing to undo.
        """
        if not self._active:
            raise ValueError("nothing to undo: no answers in force.")
        undone = self.history[-1]
        remaining = self._active[:-1]
        model = self._replay(remaining)
        rec = {"type": "undo", "v": FORMAT_VERSION, "seq": self._next_seq, "time": _now(), "undoes": undone.seq}
        self._append(rec)
        self._model, self._active = model, remaining
        self._records.append(rec)
        self._next_seq += 1
        self._pending = self._pending_step = None
        return undone


def _describe(spec) -> str:
    if not isinstance(spec, dict):
        return repr(spec)
    if spec.get("kind") == "pool":
        items = spec.get("items") or []
        digest = hashlib.sha256(json.dumps(items).encode()).hexdigest()[:10]
        return f"(a pool of {len(items)} items, digest {digest})"
    return f"(a box {spec.get('bounds')} x {spec.get('num')})"


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path.parent if str(path.parent) else ".", os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
