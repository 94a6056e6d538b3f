r"""An ask/tell elicitation session that keeps every answer in an append-only file.

:class:`PreferenceSession` proposes the next query (:meth:`~PreferenceSession.ask`), takes the
answer (:meth:`~PreferenceSession.tell`), and keeps a :class:`~torchpref.PreferenceGP` current.
It also takes answers given out of turn (:meth:`~PreferenceSession.tell_rating`,
:meth:`~PreferenceSession.tell_choice`, :meth:`~PreferenceSession.tell_no_preference`) and
undoes the last answer (:meth:`~PreferenceSession.undo`).

With a ``session_file`` every answer is appended to a :class:`~torchpref.sessions.journal.Journal` (one
JSON line, fsynced) before ``tell`` returns. The model is a function of the answers in the file:
a live answer goes through :func:`~torchpref.data.queries.record_answer` (a warm-started update,
no replay); an undo takes the model back to its data before that answer
(:func:`~torchpref.sessions.model_state.truncate`); a resume builds the data of every answer in
force in one pass (:func:`~torchpref.sessions.model_state.build_data`) and solves the mode once.
All three give the posterior of replaying the answers one by one to Newton's tolerance, and the
same next query (the selector's random numbers for query ``k`` come from ``(seed, k)``, not from
a stream that a restart would lose).

One lock (an ``RLock``) covers each call: taking the next sequence number, the model's update, the
append and its ``fsync`` happen as one, so a session may be shared by threads. A forked child
cannot write to its parent's file (:class:`~torchpref.sessions.errors.SessionForkError`).

The model is a cache of the file's answers in force: an interrupted or failed update is undone
exactly (:meth:`~torchpref.PreferenceGP.rollback`), and a model that may not match is rebuilt,
so a ``KeyboardInterrupt`` anywhere in :meth:`~PreferenceSession.tell` leaves the model, the file
and the history agreeing.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict

import torch
from torch import Tensor

from torchpref.data.queries import (
    Candidates,
    FinitePool,
    InvalidAnswer,
    Query,
    RankingQuery,
    RatingQuery,
    record_answer,
)
from torchpref.models.preference_gp import PreferenceGP
from torchpref.population.model import Population
from torchpref.selection.choosing import query_items
from torchpref.selection.defaults import default_selector
from torchpref.selection.shortlist import for_pool
from torchpref.selection.strategies import Selector
from torchpref.sessions.errors import (  # noqa: F401  (the errors stay importable from here, as before)
    SessionFileChanged,
    SessionFileCorrupt,
    SessionFileError,
    SessionFileGone,
    SessionForkError,
    SessionMismatchError,
    SessionReadOnlyError,
    SessionRepairWarning,
    SessionSettingsError,
    SessionVersionError,
)
from torchpref.sessions.journal import (
    Journal,
    MemoryJournal,
    existing_header,
    now,
    read_session_file,
)
from torchpref.sessions.model_state import (
    MODE_MEMORY,
    REPLAY_LIMIT,
    Sizes,
    build_data,
    header_digest,
    mode,
    read_snapshot,
    sizes,
    truncate,
    write_snapshot,
)
from torchpref.sessions.query_list import QuerySpec, check_pool_rows, pool_rows_of, queries_of_spec, resumed_queries
from torchpref.sessions.recorded import (
    describe_model,
    describe_selector,
    resume_settings,
)
from torchpref.sessions.records import FORMAT_VERSION, AnswerRecord, Record, SessionHeader, UndoRecord
from torchpref.sessions.settings import (
    MAX_REDRAWS,
    SessionAnswer,
    SessionSettings,
    as_items,
    as_seconds,
    as_time,
    candidates_from_header,
    check_callables,
    default_ranking_size,
    default_session_model,
    population_factory,
    step_generator,
    to_unit_cube,
    unrated_rows,
)

if TYPE_CHECKING:
    from typing_extensions import Unpack

__all__ = [
    "FORMAT_VERSION",
    "PreferenceSession",
    "SessionAnswer",
    "default_ranking_size",
    "default_session_model",
    "read_session_file",
    "step_generator",
]


PREDICT_CHUNK = 65536
"""Rows per chunk of :meth:`PreferenceSession.predict`."""


class ResumeOptions(TypedDict, total=False):
    """What :meth:`PreferenceSession.load` may be given besides the file and its candidates: the
    constructor's other keywords (the file's header gives the seed and bounds, and by default the
    number of queries, the levels and the names)."""

    queries: Sequence[Query] | None
    selector: Selector | None
    model_factory: Callable[[Tensor], PreferenceGP] | None
    num_queries: int
    num_levels: int | None
    names: Sequence[str] | None
    repair: bool
    metadata: dict | None
    migrate: bool
    population: Population | None


class PreferenceSession:
    r"""Ask queries, take answers, keep the model current; optionally persisted to a file.

    Args:
        candidates: the items queries are built from: an ``N x d`` tensor (a finite pool), a
            :class:`~torchpref.FinitePool` or a :class:`~torchpref.BoxCandidates`.
        selector: picks each query (default :func:`~torchpref.default_selector`, with ``m = min(5, N - 1)``; a
            resumed file's recorded selector).
        model_factory: ``train_X -> PreferenceGP``, called with one ``1 x d`` unobserved anchor
            item (normalised); default :func:`default_session_model` (a resumed file's recorded
            model). Its hyperparameters stay as built (refitting would make the model depend on
            more than the answers).
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
        population: a :class:`~torchpref.Population` a new person starts from (docs/population.md).
        migrate: resume a file under a model or selector other than the one its header records
            (given, or this version's default where the recorded one cannot be rebuilt); by
            default that raises :class:`SessionSettingsError`.

    Raises:
        SessionFileCorrupt, SessionVersionError, SessionMismatchError, SessionSettingsError: see
            :meth:`load`.

    Example:
        >>> s = PreferenceSession(X_pool, session_file="me.jsonl")
        >>> q = s.ask()
        >>> s.tell(q, 4 if q.kind == "rating" else 0)
    """

    _journal: Journal | MemoryJournal  # set by _open_journal; absent only if opening failed

    def __init__(
        self,
        candidates: Tensor | Candidates | None = None,
        *,
        queries: Sequence[Query] | None = None,
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
        migrate: bool = False,
        population: Population | None = None,
    ) -> None:
        if candidates is None:
            if queries is None:
                raise ValueError("give the candidates (items), the queries, or both.")
            candidates = query_items(queries).X  # the queries' distinct items are the pool
        settings = SessionSettings.validated(candidates, bounds, seed, num_queries, num_levels, names)
        self._settings, self._candidates = settings, settings.candidates
        self.dim, self.bounds, self.seed = settings.dim, settings.bounds, settings.seed
        self.num_queries, self.num_levels, self.names = settings.num_queries, settings.num_levels, settings.names
        pool = self._candidates
        self._n_pool = pool.draw(torch.Generator())[1].numel() if isinstance(pool, FinitePool) else None  # found once
        model_factory = population_factory(population, model_factory, settings.dim, settings.names)
        check_callables(selector, model_factory)
        self._lock, self._pid = threading.RLock(), os.getpid()
        self._anchor = self.transform(self._pool[:1] if self._pool is not None else self.bounds.mean(0, keepdim=True))
        self._pending: tuple[int, Query] | None = None  # (step, query) until answered
        self._answered: tuple[int, Query] | None = None  # (seq, query) of the last query told
        self._model: PreferenceGP | None = None
        self._model_version, self._version = -1, 0  # the model holds the answers iff the two are equal
        # an answer in force -> the model's data sizes before it, and its mode then (kept for the
        # latest answers, MODE_MEMORY floats in all): what undo takes the model back to
        self._sizes: dict[int, Sizes] = {}
        self._modes: dict[int, Tensor] = {}
        self._mode_floats = 0
        self.selector = selector if selector is not None else default_selector(self._n_pool, self.num_levels)
        self._queries = self._query_list(queries, selector)
        self.model_factory = model_factory if model_factory is not None else default_session_model
        self.path = None if session_file is None else Path(session_file)
        try:
            self._open_journal(metadata, repair, queries is not None, selector, model_factory, migrate)
            self.model  # noqa: B018  (builds the model of the file's answers now: errors surface at opening)
        except BaseException:
            self.close()
            raise

    def _open_journal(self, metadata, repair: bool, gave_queries: bool, selector, model_factory, migrate: bool) -> None:
        """A new journal (in memory, or a new file with this session's header) or the file's, whose
        header must then match this session's settings; a resumed file's queries, model and
        selector are its own (``resume_settings``)."""
        header = self._new_header(metadata)  # before the file is made: bad metadata leaves no file
        created: list[dict] = []

        def new_header() -> dict:
            created.append(header)
            return header

        if self.path is None:
            self._journal = MemoryJournal(header)
            return
        self._journal = Journal(self.path, new_header, repair=repair)
        file_header = self._journal.header
        if file_header is None:  # new_header() was called: not reached
            raise SessionFileError(f"session file {self.path} has no header.")
        self._digest = header_digest(file_header)
        if not created:  # resumed: the file's settings must be this session's
            typed = SessionHeader.from_json(file_header, self.path)
            self._settings.check_header(typed, self.path)
            self._check_pool_records(typed)
            self._queries = resumed_queries(typed, gave_queries, self._queries, self.path)
            self.selector, self.model_factory = resume_settings(
                typed,
                path=self.path,
                dim=self.dim,
                num_pool_items=self._n_pool,
                current=(self.selector, self.model_factory),
                given=(selector, model_factory),
                new_model=self._new_model,
                migrate=migrate,
            )

    def _check_pool_records(self, header: SessionHeader) -> None:
        """A file whose header records its pool by reference: each answer's items are its pool rows
        (what the file's format checks where the header holds the items)."""
        if "items" in header.candidates or self._pool is None:
            return
        for rec in self._journal.records:
            if isinstance(rec, AnswerRecord) and rec.pool_indices:
                rows = rec.pool_indices
                items = torch.tensor(rec.items, dtype=torch.float64)
                if max(rows) >= self._pool.shape[0] or not torch.equal(self._pool[list(rows)], items):
                    raise SessionFileError(
                        f"session file {self.path}, answer {rec.seq}: the items are not the pool's rows {list(rows)}."
                    )

    def _new_header(self, metadata: dict | None) -> dict:
        """A new file's header: the settings, and the model and selector the session starts with."""
        return self._settings.header(
            metadata, describe_model(self._new_model()), describe_selector(self.selector), self._queries
        )

    def _query_list(self, queries: Sequence[Query] | None, selector: Selector | None) -> QuerySpec | None:
        """The queries as ``[kind, pool rows...]`` (:mod:`torchpref.sessions.query_list`), checked."""
        if queries is None:
            return None
        if self._pool is None:
            raise ValueError("queries need a finite pool of candidates (an N x d tensor or a FinitePool), not a box.")
        if not callable(getattr(self.selector, "choose", None)):
            raise TypeError(f"with queries, the selector needs choose(model, queries, ...): {self.selector!r:.80}.")
        return pool_rows_of(queries, self._pool)

    def _new_model(self) -> PreferenceGP:
        model = self.model_factory(self._anchor.clone())
        if not isinstance(model, PreferenceGP):
            raise TypeError(f"model_factory must return a PreferenceGP, got {type(model).__name__}.")
        return model

    # ------------------------------------------------------------------ file
    @property
    def _pool(self) -> Tensor | None:
        return self._candidates.X if isinstance(self._candidates, FinitePool) else None

    @classmethod
    def load(
        cls, path: str | os.PathLike, candidates: Tensor | Candidates | None = None, **kwargs: Unpack[ResumeOptions]
    ) -> PreferenceSession:
        """Resume the session in ``path`` with the settings in its header (seed, levels, bounds,
        candidates, names, and the recorded model and selector); ``selector``, ``model_factory``,
        ``repair``, ``migrate`` and ``num_queries`` may be given.

        Raises:
            FileNotFoundError: no such file.
            SessionFileCorrupt: a line is incomplete or invalid (``repair=True`` fixes a bad last line).
            SessionVersionError: the file is of a newer format version.
            SessionFileError: a record breaks the format (naming the file and line); the path is a
                directory, device or FIFO, or the file is too large.
            SessionMismatchError: ``candidates`` given that differ from the file's.
            SessionSettingsError: the recorded model or selector is not the one given, or cannot be
                built by this version (``migrate=True`` resumes anyway).
        """
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"no session file {path}")
        header = SessionHeader.from_json(existing_header(path, repair=bool(kwargs.get("repair"))), path)
        if candidates is None:
            candidates = candidates_from_header(header)
        kwargs.setdefault("num_queries", header.num_queries)
        kwargs.setdefault("num_levels", header.num_levels)
        kwargs.setdefault("names", None if header.names is None else list(header.names))
        return cls(candidates, session_file=path, seed=header.seed, bounds=header.bounds_tensor, **kwargs)

    def close(self) -> None:
        """Release the file (every answer is already on disk); waits for a call in another thread."""
        journal = getattr(self, "_journal", None)
        if journal is not None:
            with self._guarded():
                journal.close()

    def __enter__(self) -> PreferenceSession:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass

    @contextlib.contextmanager
    def _guarded(self) -> Iterator[None]:
        """Hold the session's lock (a fresh one in a forked child: the parent's may have been held
        by one of its threads at the fork)."""
        if os.getpid() != self._pid:
            self._lock, self._pid = threading.RLock(), os.getpid()
        with self._lock:
            yield

    @property
    def candidates(self) -> Candidates:
        """The session's candidates (a :class:`~torchpref.FinitePool` or a
        :class:`~torchpref.BoxCandidates`); a pool's queries name its rows."""
        return self._candidates

    def reference_model(self) -> PreferenceGP:
        """A new model told the answers in force one by one through
        :func:`~torchpref.data.queries.record_answer`: the reference that :attr:`model` (built
        in one pass, from the mode snapshot, or updated answer by answer) equals to Newton's tolerance."""
        with self._guarded():
            return self._replay(self._active())

    def _active(self) -> list[AnswerRecord]:
        """The answer records in force, oldest first."""
        return list(self._journal.in_force.values())

    def _last_in_force(self) -> AnswerRecord | None:
        force = self._journal.in_force
        return force[next(reversed(force))] if force else None

    # ----------------------------------------------------------------- model
    def transform(self, X: Tensor) -> Tensor:
        """Items (``... x d``) normalised by :attr:`bounds` to the unit cube, as the model sees them."""
        return to_unit_cube(X, self.bounds)

    @property
    def model(self) -> PreferenceGP:
        """The current model (inputs normalised: use :meth:`transform`, or :meth:`predict`),
        rebuilt from the answers in force if an update was interrupted."""
        with self._guarded():
            if self._model is None or self._model_version != self._version:
                self._model_version = -1
                self._model = self._build()
                self._model_version = self._version
            return self._model

    def predict(self, X: Tensor) -> tuple[Tensor, Tensor]:
        """Posterior mean and standard deviation of the utility at the rows of ``X`` (``N x d``)."""
        X = as_items(X, self.dim, "X")
        with self._guarded(), torch.no_grad():
            Xt = self.transform(X)  # the marginals, a chunk of rows at a time (a large pool's too)
            parts = [self.model.marginals(Xt[s : s + PREDICT_CHUNK]) for s in range(0, max(1, len(Xt)), PREDICT_CHUNK)]
        mean, var = (torch.cat(t) for t in zip(*parts))
        return mean, var.clamp_min(0).sqrt()

    def expected_rating(self, X: Tensor) -> Tensor:
        """Expected rating in ``[0, 1]`` at the rows of ``X`` (``N x d``) (eq. 11)."""
        X = as_items(X, self.dim, "X")
        with self._guarded(), torch.no_grad():
            return self.model.expected_rating(self.transform(X))

    def best_item(self) -> tuple[int | None, Tensor]:
        """The item of largest posterior mean: ``(pool index, item)`` over the pool, or
        ``(None, item)`` over the items answered about when candidates are a box."""
        with self._guarded():
            if self._pool is not None:
                X = self._pool
            else:
                seen = [torch.tensor(r.items, dtype=torch.float64) for r in self._active() if r.kind != "no_preference"]
                if not seen:
                    raise ValueError("no items rated or compared yet: best_item needs a pool or some answers.")
                X = torch.cat(seen).unique(dim=0)
            i = int(self.predict(X)[0].argmax())
        return (i if self._pool is not None else None), X[i]

    # ---------------------------------------------------------------- ask/tell
    @property
    def step(self) -> int:
        """The number of answers in force: the next query's number."""
        return len(self._journal.in_force)

    @property
    def done(self) -> bool:
        """Whether ``num_queries`` answers are in force (asking more is allowed)."""
        return self.step >= self.num_queries

    @property
    def history(self) -> list[SessionAnswer]:
        """The answers in force, oldest first."""
        with self._guarded():
            return [SessionAnswer.from_record(r) for r in self._active()]

    @property
    def records(self) -> list[dict]:
        """Every record written (answers, including undone ones, and undos), as the file's JSON
        objects (:meth:`typed_records` for the typed ones)."""
        with self._guarded():
            return [r.to_json() for r in self._journal.records]

    @property
    def typed_records(self) -> list[Record]:
        """Every record written, typed (:class:`~torchpref.sessions.records.AnswerRecord` /
        :class:`~torchpref.sessions.records.UndoRecord`), oldest first."""
        with self._guarded():
            return list(self._journal.records)

    @property
    def in_force_seqs(self) -> frozenset[int]:
        """The sequence numbers of the answers in force (not undone)."""
        with self._guarded():
            return frozenset(self._journal.in_force)

    @property
    def read_only(self) -> bool:
        """Whether the file was opened read-only (answers raise :class:`SessionReadOnlyError`)."""
        return self._journal.read_only

    def ask(self) -> Query:
        """The next query (the same one until it is answered or the session changes). Its items
        are in the caller's coordinates; ``index`` / ``indices`` are pool rows (or ``None``)."""
        with self._guarded():
            step = self.step
            if self._pending is not None and self._pending[0] == step:
                return self._pending[1]
            last_rec = self._last_in_force()
            last = sorted(last_rec.items) if last_rec is not None else None
            for attempt in range(MAX_REDRAWS + 1):  # not the items just answered about again (small pools)
                query = self._select(step, attempt)
                if sorted(query.items.tolist()) != last:
                    break
            self._pending = (step, query)
            return query

    def _select(self, step: int, attempt: int) -> Query:
        """The selector's query ``step`` (its ``attempt``-th draw), in the caller's coordinates."""
        gen = step_generator(self.seed, step, attempt)
        if self._queries is not None:
            return self._choose_from_list(self._queries, step, gen)
        X, idx = self._candidates.draw(gen)
        rows = torch.arange(X.shape[0])  # a pool draws each distinct item once (FinitePool)
        selector = for_pool(self.selector, X.shape[0])  # many candidates: a shortlist (docs/selection.md)
        q = selector.select(self.model, self.transform(X), rows, step, self.num_queries, gen)
        if isinstance(q, RatingQuery) and idx is not None:  # never a second rating while unrated items are left
            keep = unrated_rows(idx, self._journal.in_force.values(), _row(q), getattr(self.selector, "m", 2))
            if keep is not None:
                X, idx = X[keep], idx[keep]
                q = selector.select(self.model, self.transform(X), rows[: len(keep)], step, self.num_queries, gen)
        if isinstance(q, RatingQuery):
            r = _row(q)
            return RatingQuery(X[r], None if idx is None else int(idx[r]))
        rr = _rows(q)
        return RankingQuery(X[rr], None if idx is None else tuple(int(idx[r]) for r in rr))

    def tell(
        self,
        query: Query,
        answer: int | float | None,
        *,
        response_time: float | None = None,
        shown_at: str | None = None,
        answered_at: str | None = None,
    ) -> None:
        """Record ``answer`` to ``query``: a Likert level (or a ``[0, 1]`` rating if the session has
        no levels) for a :class:`~torchpref.RatingQuery`; the index of the chosen row of
        ``query.items`` for a :class:`~torchpref.RankingQuery`, or ``None`` for no preference
        (see :func:`~torchpref.data.queries.record_answer`). ``response_time``: seconds from the
        question being shown to the answer, if the front end measured it (kept in the record);
        ``shown_at`` and ``answered_at``: when the question was on screen and when it was answered
        (ISO 8601 times from the front end, e.g. the page's clock), kept in the record too.

        Raises:
            ValueError: an invalid answer (naming it), a query already answered (a second click),
                a ``response_time`` that is not a finite number of seconds >= 0,
                or one whose pool rows are not this session's (another session's query); the
                session and the file are unchanged.
            SessionForkError, SessionReadOnlyError, SessionFileGone: the answer cannot be saved
                (a forked child, a read-only file, a file deleted or replaced); nothing changes.
        """
        if not isinstance(query, (RatingQuery, RankingQuery)):
            raise TypeError(f"query must be a RatingQuery or RankingQuery, got {type(query).__name__}.")
        with self._guarded():
            last = self._answered
            if last is not None and last[1] is query and last[0] in self._journal.in_force:
                raise ValueError(
                    f"this query is already answered (answer {last[0]}); ask() gives the next one. Another "
                    "answer about the same items: tell_rating, tell_choice or tell_no_preference."
                )
            pending = self._pending is not None and self._pending[1] is query and self._pending[0] == self.step
            if isinstance(query, RatingQuery):
                pool_rows = None if query.index is None else [int(query.index)]
            else:
                pool_rows = None if query.indices is None else [int(i) for i in query.indices]
            if pool_rows is not None:
                check_pool_rows(self._pool, as_items(query.items, self.dim, "the query's items"), pool_rows)
            info = {"kind": query.kind, "step": self.step if pending else None, "pool_indices": pool_rows}
            times = {"shown_at": shown_at, "answered_at": answered_at}
            seq = self._tell(query, answer, info, response_time, {k: v for k, v in times.items() if v is not None})
            self._answered = (seq, query)

    def tell_rating(self, x: Tensor, rating: int | float, *, response_time: float | None = None) -> None:
        """A rating of any item ``x`` (``d``), given out of turn: a Likert level (or ``[0, 1]``);
        ``response_time`` as in :meth:`tell`."""
        x = as_items(x, self.dim, "x")
        if x.shape[0] != 1:
            raise ValueError(f"a rating is of one item, got {x.shape[0]}.")
        with self._guarded():
            self._tell(RatingQuery(x[0]), rating, None, response_time)

    def tell_choice(self, X_shown: Tensor, chosen: int, *, response_time: float | None = None) -> None:
        """A choice of row ``chosen`` among any shown items ``X_shown`` (``m x d``, ``m >= 2``);
        ``response_time`` as in :meth:`tell`."""
        X = as_items(X_shown, self.dim, "X_shown")
        RankingQuery(X).validate_answer(chosen)  # None is not a choice here
        with self._guarded():
            self._tell(RankingQuery(X), chosen, None, response_time)

    def tell_no_preference(self, X_shown: Tensor, *, response_time: float | None = None) -> None:
        """The person saw ``X_shown`` (``m x d``) and had no preference: a tie between every two of
        the items shown (:func:`~torchpref.data.queries.no_preference_observations`);
        ``response_time`` as in :meth:`tell`."""
        X = as_items(X_shown, self.dim, "X_shown")
        with self._guarded():
            self._tell(RankingQuery(X), None, None, response_time)

    def _tell(self, query: Query, answer, info: dict | None, response_time=None, times: dict | None = None) -> int:
        """Validate and add the answer to the model (:func:`~torchpref.data.queries.record_answer`,
        a warm-started update), then append its record; on any failure the model is put back
        exactly. Called under the lock; returns the record's sequence number."""
        self._journal.check_writable()  # a forked child or a read-only file: refused before anything changes
        items = as_items(query.items, self.dim, "the query's items")
        response_time = as_seconds(response_time)
        times = {k: as_time(v, k) for k, v in (times or {}).items()}
        if isinstance(answer, (list, tuple)):
            raise InvalidAnswer(
                f"a session records one chosen item (or None for no preference), not several equally best "
                f"ones; got {answer!r:.80}."
            )
        if isinstance(query, RankingQuery) and items.shape[0] < 2:
            raise ValueError(f"a choice needs at least 2 items shown, got {items.shape[0]}.")
        model = self.model
        before, f_before = sizes(model), mode(model)
        self._model_version = -1  # in flux: rebuilt from the file if this neither completes nor rolls back
        try:
            with model.rollback():  # on any failure the model is put back exactly
                value = record_answer(model, self._model_query(query.kind, items), answer, num_levels=self.num_levels)
                assert not isinstance(value, list)  # one chosen item: several equally best were refused above
                rating = query.kind == "rating"
                rec = AnswerRecord(
                    seq=self._journal.last_seq + 1,
                    time=now(),
                    kind="rating" if rating else ("choice" if value is not None else "no_preference"),
                    items=tuple(tuple(row) for row in items.tolist()),
                    answer=int(answer) if rating and self.num_levels is not None else value,
                    value=value if rating else None,
                    query=info,
                    response_time=response_time,
                    shown_at=times.get("shown_at"),
                    answered_at=times.get("answered_at"),
                )
                self._journal.append(rec)
        except BaseException:
            self._model_version = self._version
            raise
        self._sizes[rec.seq] = before
        self._keep_mode(rec.seq, f_before)
        self._version += 1
        self._model_version = self._version
        self._snapshot()
        return rec.seq

    def undo(self) -> SessionAnswer:
        """Withdraw the last answer in force (an ``undo`` record is appended; the model goes back
        to its data before that answer, no replay) and return it.

        Raises:
            ValueError: nothing to undo.
            SessionForkError, SessionReadOnlyError, SessionFileGone: the undo cannot be saved.
        """
        with self._guarded():
            self._journal.check_writable()
            last = self._last_in_force()
            if last is None:
                raise ValueError("nothing to undo: no answers in force.")
            undone = SessionAnswer.from_record(last)
            model = self.model
            before = self._sizes.get(last.seq)
            self._model_version = -1
            try:
                with model.rollback():
                    if before is not None:
                        truncate(model, before, self._modes.get(last.seq))
                    self._journal.append(UndoRecord(self._journal.last_seq + 1, now(), undone.seq))
            except BaseException:
                self._model_version = self._version
                raise
            self._sizes.pop(last.seq, None)
            f = self._modes.pop(last.seq, None)
            self._mode_floats -= 0 if f is None else f.numel()
            self._version += 1
            if before is not None:
                self._model_version = self._version  # else rebuilt at its next use
                self._snapshot()
            return undone

    def _choose_from_list(self, spec: QuerySpec, step: int, gen: torch.Generator) -> Query:
        """The selector's choice among the listed queries ``spec`` not yet answered (all of them
        once every one is), in the caller's coordinates with pool rows."""
        pool = self._pool
        assert pool is not None  # a query list needs a finite pool (checked when it was given)
        asked = {(r.query_kind, tuple(sorted(r.pool_indices))) for r in self._active() if r.pool_indices is not None}
        offered = queries_of_spec([q for q in spec if (q[0], tuple(sorted(q[1:]))) not in asked] or spec, pool)
        mine: list[Query] = [self._model_query(q.kind, torch.as_tensor(q.items)) for q in offered]
        i = self.selector.choose(self.model, mine, step=step, num_steps=self.num_queries, generator=gen)
        return offered[i]

    # ------------------------------------------------------------ model cache
    # The model is a cache of the answers in force (module docstring): built from the file's mode
    # snapshot where there is one, with the earlier modes kept for exact undos.
    def _model_query(self, kind: str, items: Tensor) -> Query:
        """A query of ``kind`` (``"rating"`` or not) on ``items`` (``m x d``), in the model's coordinates."""
        Z = self.transform(items)
        return RatingQuery(Z[0]) if kind == "rating" else RankingQuery(Z)

    def _replay(self, records: list[AnswerRecord]) -> PreferenceGP:
        """The reference: a new model told ``records`` one by one through ``record_answer``."""
        model = self._new_model()
        for rec in records:
            query = self._model_query(rec.kind, torch.tensor(rec.items, dtype=torch.float64))
            record_answer(model, query, rec.answer, num_levels=self.num_levels)
        return model

    def _build(self) -> PreferenceGP:
        """A new model of the answers in force: the data of those the file's mode snapshot covers
        built in one pass, Newton started from the snapshot's mode, and the few answers after it
        replayed through the live path; without a usable snapshot, every answer's data in one pass
        and the mode solved once (the same data as :meth:`_replay`'s; the mode to Newton's tolerance)."""
        model = self._new_model()
        records = self._active()
        d = model.data
        self._sizes, self._modes, self._mode_floats = {}, {}, 0
        if not records or not (d.n == 1 and d.num_observations == 0 and model.batch_shape == torch.Size([])):
            return self._replay(records) if records else model
        k, f = self._snapshot_start(records)
        data, before = build_data(self._anchor, records[:k], self.transform, model.rating_eps, model.rating_levels)
        model.replace_data(data, f if f is not None and f.numel() == data.n else None)
        self._sizes = {r.seq: b for r, b in zip(records[:k], before, strict=True)}
        for rec in records[k:]:  # after the snapshot: the live path, as told
            b, fb = sizes(model), mode(model)
            query = self._model_query(rec.kind, torch.tensor(rec.items, dtype=torch.float64))
            record_answer(model, query, rec.answer, num_levels=self.num_levels)
            self._sizes[rec.seq] = b
            self._keep_mode(rec.seq, fb)
        return model

    def _snapshot_start(self, records: list[AnswerRecord]) -> tuple[int, Tensor | None]:
        """``(k, f)``: the file's mode snapshot covers the first ``k`` answers in force, with mode
        ``f``; ``(len(records), None)`` where there is no usable snapshot."""
        none = (len(records), None)
        snap = read_snapshot(self.path) if self.path is not None else None
        if snap is None or snap[0].get("header") != self._digest:
            return none
        meta, f = snap
        later, all_records = 0, self._journal.records
        for rec in reversed(all_records):  # the records after the snapshot: answers only, a few
            if rec.seq <= meta.get("seq", -1):
                break
            if not isinstance(rec, AnswerRecord) or later == REPLAY_LIMIT:
                return none
            later += 1
        at = len(all_records) - later - 1
        stamp = all_records[at].time if at >= 0 else None
        k = len(records) - later
        if meta.get("in_force") != k or meta.get("time") != stamp or (at < 0 and meta.get("seq") != 0):
            return none
        return k, f

    def _snapshot(self) -> None:
        """Keep the current mode beside the file (a resume starts there)."""
        if self.path is not None and not self._journal.read_only and self._model is not None:
            last = self._journal.records[-1] if self._journal.records else None
            meta = {
                "seq": last.seq if last else 0,
                "time": last.time if last else None,
                "in_force": len(self._journal.in_force),
                "header": self._digest,
            }
            write_snapshot(self.path, meta, mode(self._model))

    def _keep_mode(self, seq: int, f: Tensor) -> None:
        """Keep the mode before answer ``seq`` for its undo, forgetting the oldest beyond MODE_MEMORY floats."""
        self._modes[seq] = f
        self._mode_floats += f.numel()
        while self._mode_floats > MODE_MEMORY and len(self._modes) > 1:
            oldest = next(iter(self._modes))
            self._mode_floats -= self._modes.pop(oldest).numel()


def _row(query: RatingQuery) -> int:
    """The candidate row a selector's rating query names (selectors always name it)."""
    if query.index is None:
        raise ValueError(f"the selector returned a rating query without its candidate row: {query!r:.80}.")
    return int(query.index)


def _rows(query: RankingQuery) -> list[int]:
    """The candidate rows a selector's ranking query names (selectors always name them)."""
    if query.indices is None:
        raise ValueError(f"the selector returned a ranking query without its candidate rows: {query!r:.80}.")
    return [int(i) for i in query.indices]
