r"""An ask/tell elicitation session that keeps every answer in an append-only file.

:class:`PreferenceSession` proposes the next query (:meth:`~PreferenceSession.ask`), takes the
answer (:meth:`~PreferenceSession.tell`), and keeps a :class:`~torchpref.PreferenceGP` current.
It also takes answers given out of turn (:meth:`~PreferenceSession.tell_rating`,
:meth:`~PreferenceSession.tell_choice`, :meth:`~PreferenceSession.tell_no_preference`) and
undoes the last answer (:meth:`~PreferenceSession.undo`).

With a ``session_file`` every answer is appended to a :class:`~torchpref.sessions.journal.Journal` (one
JSON line, fsynced) before ``tell`` returns. The model is a pure function of the answers in the
file: each goes through :func:`~torchpref.data.queries.record_answer`, live and on replay, so a
session restarted from its file has bitwise the posterior of the interrupted process, and asks
the query it would have asked (the selector's random numbers for query ``k`` come from
``(seed, k)``, not from a stream that a restart would lose).

The session's state is the journal's records; the model is a cache of them, rebuilt by replay
whenever it may not match (after an interrupted or failed update), so a ``KeyboardInterrupt``
anywhere in :meth:`~PreferenceSession.tell` leaves the model, the file and the history agreeing.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from torchpref.sessions.journal import Journal, now, read_session_file
from torchpref.models.preference_gp import PreferenceGP
from torchpref.data.queries import (
    Candidates,
    FinitePool,
    Query,
    RankingQuery,
    RatingQuery,
    first_unique_rows,
    record_answer,
)
from torchpref.sessions.records import (
    FORMAT_VERSION,
    SessionFileCorrupt,
    SessionFileError,
    SessionMismatchError,
    SessionRepairWarning,
    SessionVersionError,
    check_new_record,
    records_in_force,
)
from torchpref.sessions.settings import (
    MAX_REDRAWS,
    SessionAnswer,
    SessionSettings,
    as_items,
    candidates_from_header,
    default_ranking_size,
    default_session_model,
    step_generator,
)
from torchpref.selection.strategies import UCBC, Selector

__all__ = [
    "FORMAT_VERSION",
    "PreferenceSession",
    "SessionAnswer",
    "SessionFileCorrupt",
    "SessionFileError",
    "SessionMismatchError",
    "SessionRepairWarning",
    "SessionVersionError",
    "default_ranking_size",
    "default_session_model",
    "read_session_file",
    "step_generator",
]


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
        settings = SessionSettings.validated(candidates, bounds, seed, num_queries, num_levels, names)
        self._settings, self._candidates = settings, settings.candidates
        self.dim, self.bounds, self.seed = settings.dim, settings.bounds, settings.seed
        self.num_queries, self.num_levels, self.names = settings.num_queries, settings.num_levels, settings.names
        n_pool = first_unique_rows(self._pool).numel() if self._pool is not None else None
        if selector is not None and not callable(getattr(selector, "select", None)):
            raise TypeError(f"selector must be a Selector (with select(model, candidates, ...)), got {selector!r:.80}.")
        if model_factory is not None and not callable(model_factory):
            raise TypeError(f"model_factory must be callable(X) -> PreferenceGP, got {model_factory!r:.80}.")
        self.selector = selector if selector is not None else UCBC(m=default_ranking_size(n_pool) if n_pool else 5)
        self.model_factory = model_factory if model_factory is not None else default_session_model
        self._anchor = self.transform(self._pool[:1] if self._pool is not None else self.bounds.mean(0, keepdim=True))
        self._pending: tuple[int, Query] | None = None  # (step, query) until answered
        self._answered: tuple[int, Query] | None = None  # (seq, query) of the last query told
        self._journal: Journal | None = None
        self._memory: list[dict] = []  # the records when there is no file
        self._memory_header = settings.header(metadata)
        self._model: PreferenceGP | None = None
        self._model_seqs: tuple[int, ...] | None = None  # the answers the model holds
        self.path = None if session_file is None else Path(session_file)
        if self.path is not None:
            self._journal = Journal(self.path, lambda: self._memory_header, repair=repair)
        try:
            if self._journal is not None:
                settings.check_header(self._journal.header, self.path)
            self.model  # noqa: B018  (replays the file's answers now: errors surface at opening)
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ file
    @property
    def _pool(self) -> Tensor | None:
        return self._candidates.X if isinstance(self._candidates, FinitePool) else None

    @classmethod
    def load(
        cls, path: str | os.PathLike, candidates: Tensor | Candidates | None = None, **kwargs: Any
    ) -> PreferenceSession:
        """Resume the session in ``path`` with the settings in its header (seed, levels, bounds,
        candidates, names); ``selector``, ``model_factory``, ``repair`` and ``num_queries`` may be given.

        Raises:
            FileNotFoundError: no such file.
            SessionFileCorrupt: a line is incomplete or invalid (``repair=True`` fixes a bad last line).
            SessionVersionError: the file is of a newer format version.
            SessionFileError: a record breaks the format (naming the file and line).
            SessionMismatchError: ``candidates`` given that differ from the file's.
        """
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"no session file {path}")
        with Journal(path, lambda: None, repair=bool(kwargs.get("repair"))) as journal:
            header = journal.header
        if header is None:
            raise SessionFileError(f"session file {path} is empty: create the session with PreferenceSession(...).")
        if candidates is None:
            candidates = candidates_from_header(header)
        kwargs.setdefault("num_queries", header["num_queries"])
        kwargs.setdefault("num_levels", header["num_levels"])
        kwargs.setdefault("names", header.get("names"))
        return cls(
            candidates,
            session_file=path,
            seed=header["seed"],
            bounds=torch.tensor(header["bounds"], dtype=torch.float64),
            **kwargs,
        )

    def close(self) -> None:
        """Release the file (every answer is already on disk)."""
        if self._journal is not None:
            self._journal.close()

    def __enter__(self) -> PreferenceSession:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass

    @property
    def _records(self) -> list[dict]:
        return self._journal.records if self._journal is not None else self._memory

    def _append(self, record: dict) -> None:
        """Check ``record`` and append it to the file (or memory): all of it or, on any failure, nothing."""
        if self._journal is not None:
            self._journal.append(record)
        else:
            check_new_record("session (no file)", self._memory_header, self._memory, record)
            self._memory.append(record)

    @property
    def _active(self) -> list[dict]:
        return records_in_force(self._records)

    @property
    def _next_seq(self) -> int:
        return self._records[-1]["seq"] + 1 if self._records else 1

    # ----------------------------------------------------------------- model
    def transform(self, X: Tensor) -> Tensor:
        """Items (``... x d``) normalised by :attr:`bounds` to the unit cube, as the model sees them."""
        lo, hi = self.bounds
        return (X.to(torch.float64) - lo) / (hi - lo)

    def _model_query(self, kind: str, items: Tensor) -> Query:
        """A query of ``kind`` (``"rating"`` or not) on ``items`` (``m x d``), in the model's coordinates."""
        Z = self.transform(items)
        return RatingQuery(Z[0]) if kind == "rating" else RankingQuery(Z)

    def _replay(self, records: list[dict]) -> PreferenceGP:
        model = self.model_factory(self._anchor.clone())
        if not isinstance(model, PreferenceGP):
            raise TypeError(f"model_factory must return a PreferenceGP, got {type(model).__name__}.")
        for rec in records:
            query = self._model_query(rec["kind"], torch.tensor(rec["items"], dtype=torch.float64))
            record_answer(model, query, rec["answer"], num_levels=self.num_levels)
        return model

    @property
    def model(self) -> PreferenceGP:
        """The current model (inputs normalised: use :meth:`transform`, or :meth:`predict`),
        rebuilt from the answers in force if an update was interrupted."""
        active = self._active
        seqs = tuple(r["seq"] for r in active)
        if self._model is None or self._model_seqs != seqs:
            self._model_seqs = None
            self._model = self._replay(active)
            self._model_seqs = seqs
        return self._model

    def predict(self, X: Tensor) -> tuple[Tensor, Tensor]:
        """Posterior mean and standard deviation of the utility at the rows of ``X`` (``N x d``)."""
        X = as_items(X, self.dim, "X")
        with torch.no_grad():
            post = self.model.posterior(self.transform(X).unsqueeze(-2))
        return post.mean.reshape(-1), post.variance.reshape(-1).clamp_min(0).sqrt()

    def expected_rating(self, X: Tensor) -> Tensor:
        """Expected rating in ``[0, 1]`` at the rows of ``X`` (``N x d``) (eq. 11)."""
        X = as_items(X, self.dim, "X")
        with torch.no_grad():
            return self.model.expected_rating(self.transform(X))

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
        return [SessionAnswer.from_record(r) for r in self._active]

    @property
    def records(self) -> list[dict]:
        """Every record written (answers, including undone ones, and undos), as in the file."""
        return list(self._records)

    def ask(self) -> Query:
        """The next query (the same one until it is answered or the session changes). Its items
        are in the caller's coordinates; ``index`` / ``indices`` are pool rows (or ``None``)."""
        step = self.step
        if self._pending is not None and self._pending[0] == step:
            return self._pending[1]
        last = sorted(self._active[-1]["items"]) if self._active else None
        for attempt in range(MAX_REDRAWS + 1):  # not the items just answered about again (small pools)
            query = self._select(step, attempt)
            if sorted(query.items.tolist()) != last:
                break
        self._pending = (step, query)
        return query

    def _select(self, step: int, attempt: int) -> Query:
        """The selector's query ``step`` (its ``attempt``-th draw), in the caller's coordinates."""
        gen = step_generator(self.seed, step, attempt)
        X, idx = self._candidates.draw(gen)
        rows = torch.arange(X.shape[0])  # a pool draws each distinct item once (FinitePool)
        q = self.selector.select(self.model, self.transform(X), rows, step, self.num_queries, gen)
        if isinstance(q, RatingQuery):
            r = int(q.index)
            return RatingQuery(X[r], None if idx is None else int(idx[r]))
        rr = list(q.indices)
        return RankingQuery(X[rr], None if idx is None else tuple(int(idx[r]) for r in rr))

    def tell(self, query: Query, answer: int | float | None, *, response_time: float | None = None) -> None:
        """Record ``answer`` to ``query``: a Likert level (or a ``[0, 1]`` rating if the session has
        no levels) for a :class:`~torchpref.RatingQuery`; the index of the chosen row of
        ``query.items`` for a :class:`~torchpref.RankingQuery`, or ``None`` for no preference
        (see :func:`~torchpref.data.queries.record_answer`). ``response_time``: seconds from the
        question being shown to the answer, if the front end measured it (kept in the record).

        Raises:
            ValueError: an invalid answer (naming it), a query already answered (a second click),
                a ``response_time`` that is not a finite number of seconds >= 0,
                or one whose pool rows are not this session's (another session's query); the
                session and the file are unchanged.
        """
        if not isinstance(query, (RatingQuery, RankingQuery)):
            raise TypeError(f"query must be a RatingQuery or RankingQuery, got {type(query).__name__}.")
        last = self._answered
        if last is not None and last[1] is query and any(r["seq"] == last[0] for r in self._active):
            raise ValueError(
                f"this query is already answered (answer {last[0]}); ask() gives the next one. Another "
                "answer about the same items: tell_rating, tell_choice or tell_no_preference."
            )
        pending = self._pending is not None and self._pending[1] is query and self._pending[0] == self.step
        rows = [query.index] if isinstance(query, RatingQuery) else query.indices
        info = {
            "kind": query.kind,
            "step": self.step if pending else None,
            "pool_indices": None if rows is None or rows[0] is None else [int(i) for i in rows],
        }
        if info["pool_indices"] is not None:
            self._check_pool_rows(query, info["pool_indices"])
        self._tell(query, answer, info, response_time)
        self._answered = (self._records[-1]["seq"], query)

    def _check_pool_rows(self, query: Query, rows: list[int]) -> None:
        """The query's items are this session's pool rows ``rows`` (checked before the model is
        touched; the file's format checks it again)."""
        pool = self._pool
        items = as_items(query.items, self.dim, "the query's items")
        if (
            pool is None
            or not all(0 <= i < pool.shape[0] for i in rows)
            or not torch.equal(pool[rows].to(items), items)
        ):
            raise ValueError(
                f"the query's items are not this session's pool rows {rows}: a query of another "
                "session, or one edited after ask()."
            )

    def tell_rating(self, x: Tensor, rating: int | float, *, response_time: float | None = None) -> None:
        """A rating of any item ``x`` (``d``), given out of turn: a Likert level (or ``[0, 1]``);
        ``response_time`` as in :meth:`tell`."""
        x = as_items(x, self.dim, "x")
        if x.shape[0] != 1:
            raise ValueError(f"a rating is of one item, got {x.shape[0]}.")
        self._tell(RatingQuery(x[0]), rating, None, response_time)

    def tell_choice(self, X_shown: Tensor, chosen: int, *, response_time: float | None = None) -> None:
        """A choice of row ``chosen`` among any shown items ``X_shown`` (``m x d``, ``m >= 2``);
        ``response_time`` as in :meth:`tell`."""
        X = as_items(X_shown, self.dim, "X_shown")
        RankingQuery(X).validate_answer(chosen)  # None is not a choice here
        self._tell(RankingQuery(X), chosen, None, response_time)

    def tell_no_preference(self, X_shown: Tensor, *, response_time: float | None = None) -> None:
        """The person saw ``X_shown`` (``m x d``) and had no preference: a tie between every two of
        the items shown (:func:`~torchpref.data.queries.no_preference_observations`);
        ``response_time`` as in :meth:`tell`."""
        self._tell(RankingQuery(as_items(X_shown, self.dim, "X_shown")), None, None, response_time)

    def _tell(self, query: Query, answer, info: dict | None, response_time=None) -> None:
        """Validate and add the answer to the model (:func:`~torchpref.data.queries.record_answer`),
        then append its record; the model is trusted again only once the record is in."""
        items = as_items(query.items, self.dim, "the query's items")
        response_time = _seconds(response_time)
        if isinstance(query, RankingQuery) and items.shape[0] < 2:
            raise ValueError(f"a choice needs at least 2 items shown, got {items.shape[0]}.")
        model, seqs = self.model, self._model_seqs
        self._model_seqs = None  # in flux: rebuilt from the file if this does not complete
        try:
            value = record_answer(model, self._model_query(query.kind, items), answer, num_levels=self.num_levels)
        except Exception:
            self._model_seqs = seqs  # the model rolls back on error (PreferenceGP.add_observations)
            raise
        rec = {
            "type": "answer",
            "v": FORMAT_VERSION,
            "seq": self._next_seq,
            "time": now(),
            "kind": "rating" if query.kind == "rating" else ("choice" if value is not None else "no_preference"),
            "items": items.tolist(),
        }
        if query.kind == "rating":
            rec.update(answer=int(answer) if self.num_levels is not None else value, value=value)
        else:
            rec["answer"] = value
        rec["query"] = info
        rec["response_time"] = response_time
        self._append(rec)
        self._model_seqs = seqs + (rec["seq"],)

    def undo(self) -> SessionAnswer:
        """Withdraw the last answer in force (an ``undo`` record is appended; the model is rebuilt
        from the remaining answers) and return it.

        Raises:
            ValueError: nothing to undo.
        """
        active = self._active
        if not active:
            raise ValueError("nothing to undo: no answers in force.")
        undone = self.history[-1]
        model = self._replay(active[:-1])
        self._append({"type": "undo", "v": FORMAT_VERSION, "seq": self._next_seq, "time": now(), "undoes": undone.seq})
        self._model, self._model_seqs = model, tuple(r["seq"] for r in active[:-1])
        return undone


def _seconds(value) -> float | None:
    """A response time as float seconds (``None`` stays ``None``).

    Raises:
        ValueError: not a finite real number >= 0 (a bool or text included), naming it.
    """
    if value is None:
        return None
    ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not ok and isinstance(value, Tensor) and value.numel() == 1 and not value.dtype.is_complex:
        value, ok = value.item(), value.dtype != torch.bool
    if not ok or not math.isfinite(float(value)) or float(value) < 0:
        raise ValueError(f"response_time must be None or a finite number of seconds >= 0, got {value!r:.80}.")
    return float(value)
