r"""The sessions behind a ``torchpref serve`` page: one :class:`~torchpref.PreferenceSession` per
participant, each in its own file of one directory, and every browser request checked against it.

A participant's session id (``sid``) names the file ``DIR/SID.session.jsonl``; it is random
(:func:`secrets.token_urlsafe`), so the link is the key to the session. Each question shown has a
question id ``qid = "P.H"``: ``P`` the number of records in the file when it was asked and ``H`` a
hash of the session id, ``P`` and the items, so an answer names the question it answers:

* to the current question: validated (:meth:`SessionStore.answer`), told to the session with its
  response time, fsynced, and only then acknowledged (the reply holds the next question);
* to the question just answered, with the same answer (a retry after a lost reply, a server
  killed after the fsync): acknowledged again, nothing recorded twice;
* to an older question, one answered differently, or another session's question: refused
  (HTTP 409) with the current question.

Every request to a session holds that session's lock, so two tabs of one participant cannot
interleave; sessions of different participants run in parallel.
"""

from __future__ import annotations

import csv
import datetime as _dt
import errno
import hashlib
import io
import json
import re
import secrets
import threading
import warnings
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypedDict, TypeGuard

import torch

from torchpref.data.queries import InvalidAnswer, Query, RankingQuery, RatingQuery
from torchpref.frontends.serve.errors import AnswerRefused
from torchpref.frontends.serve.items import ServeItems
from torchpref.population.model import Population
from torchpref.selection.strategies import Selector
from torchpref.sessions.errors import SessionFileError
from torchpref.sessions.records import AnswerRecord
from torchpref.sessions.session import PreferenceSession

if TYPE_CHECKING:
    from typing_extensions import Unpack

    from torchpref.frontends.serve.pool import PoolEntry as _Entry
    from torchpref.frontends.serve.pool import PoolLimits

__all__ = ["AnswerRefused", "MAX_RESPONSE_TIME", "SID_PATTERN", "SessionStore", "make_qid"]

SID_PATTERN = re.compile(r"[A-Za-z0-9_-]{1,64}")
"""What a session id may be (it names a file: no dots, no slashes)."""

MAX_RESPONSE_TIME = 7 * 24 * 3600.0
"""The longest response time accepted, in seconds (a week: a page left open and come back to)."""

ANSWER_FIELDS = {"qid", "answer", "response_time", "shown_at", "answered_at"}
"""What an answer request may hold: ``shown_at`` and ``answered_at`` are the page's clock in
milliseconds since 1970 (JavaScript's ``Date.now()``) when the question was on screen with its
pictures decoded and when it was answered."""

LEVEL_WORDS = {1: "unacceptable", 2: "poor", 3: "fair", 4: "good", 5: "excellent"}


class NewSessionKeywords(TypedDict, total=False):
    """:class:`NewSessions`' fields as keywords (``SessionStore(items, folder, num_queries=6)``)."""

    num_queries: int
    seed: int
    num_levels: int | None
    ties: bool
    population: Population | None
    queries: tuple[Query, ...] | None
    selector: Selector | None


@dataclass(frozen=True)
class NewSessions:
    """The settings of each new participant's session (:class:`SessionStore`, :func:`~torchpref.serve`).

    Attributes:
        num_queries: the questions each participant is asked.
        seed: the sessions' seed (each session's queries draw from it and its number).
        num_levels: ratings on a ``1..K`` scale (``None``: ``[0, 1]``).
        ties: offer "no preference" in the best-of-m questions.
        population: a :class:`~torchpref.Population` each new session starts from (docs/population.md).
        queries: a fixed list of questions (rows of the items) the selector chooses among
            (``--question-list``: :func:`~torchpref.sessions.query_list.read_question_list`).
        selector: the selector of every new session (``None``: :func:`~torchpref.default_selector`;
            a resumed session keeps the one its file records).
    """

    num_queries: int = 14
    seed: int = 0
    num_levels: int | None = 5
    ties: bool = True
    population: Population | None = None
    queries: tuple[Query, ...] | None = None
    selector: Selector | None = None

    @classmethod
    def of(cls, given: NewSessions | None, keywords: NewSessionKeywords, where: str) -> NewSessions:
        """``given`` (default: the defaults) with ``keywords`` (this class's fields) overriding it.

        Raises:
            TypeError: a keyword that is not a field, naming ``where`` and the fields.
        """
        names = [f.name for f in fields(cls)]
        unknown = sorted(set(keywords) - set(names))
        if unknown:
            raise TypeError(f"{where} got unexpected keyword argument(s) {', '.join(unknown)}; "
                            f"each new session's settings are {', '.join(names)} (NewSessions).")  # fmt: skip
        return replace(given if given is not None else cls(), **keywords)


def make_qid(sid: str, position: int, items: list | None) -> str:
    """The id of the question asked in session ``sid`` after ``position`` records, on ``items``."""
    digest = hashlib.sha256(json.dumps([sid, position, items]).encode()).hexdigest()[:16]
    return f"{position}.{digest}"


class SessionStore:
    """The participants' sessions over one pool of items.

    Args:
        items: the pool and its pictures (:class:`~torchpref.frontends.serve.items.ServeItems`).
        directory: where the session files are (created if missing); ``None`` with ``session``.
        session: serve only this session (built in Python), under the id ``sid``; no new ones.
        sid: the id of ``session`` (default: its file's name before ``.session.jsonl``, or ``session``).
        new: each new session's settings (:class:`NewSessions`); its fields are also accepted as
            keywords (``num_queries=6``), overriding it.
        limits: how many sessions stay open and for how long
            (:class:`~torchpref.frontends.serve.pool.PoolLimits`; closed ones reopen from their files).
    """

    def __init__(
        self,
        items: ServeItems,
        directory: str | Path | None = None,
        *,
        session: PreferenceSession | None = None,
        sid: str | None = None,
        new: NewSessions | None = None,
        limits: PoolLimits | None = None,
        **new_settings: Unpack[NewSessionKeywords],
    ) -> None:
        from torchpref.frontends.serve.plots import Plots
        from torchpref.frontends.serve.pool import SessionPool

        new = NewSessions.of(new, new_settings, "SessionStore")
        self.items, self.ties, self.new = items, bool(new.ties), new
        self.pool = SessionPool(self._open_checked, limits)
        self.plots = Plots(items)
        self._lock, self._new_metadata = threading.Lock(), dict[str, dict]()  # metadata: for _open's new file
        self.fixed = session is not None
        if session is not None:
            if sid is None:
                sid = session.path.name.split(".")[0] if session.path is not None else "session"
            if not SID_PATTERN.fullmatch(sid):
                raise ValueError(f"session id {sid!r:.80} must be 1-64 letters, digits, '-' or '_'.")
            self.pool.add(sid, session, pinned=True)
            self.directory = None if session.path is None else session.path.parent
            self.num_levels = session.num_levels
        else:
            if directory is None:
                raise ValueError("give a directory for the session files (or one session).")
            self.directory = Path(directory)
            self.directory.mkdir(parents=True, exist_ok=True)
            self.num_levels = new.num_levels
        self._kwargs = dict(
            seed=new.seed,
            num_queries=new.num_queries,
            num_levels=new.num_levels,
            names=items.names,
            metadata={**items.metadata, "front_end": "serve"},
            population=new.population,
            queries=None if new.queries is None else list(new.queries),
        )
        if new.selector is not None:
            self._kwargs["selector"] = new.selector

    # ------------------------------------------------------------ sessions
    def path(self, sid: str) -> Path:
        """The session file of ``sid``."""
        return self.directory / f"{sid}.session.jsonl"

    def create(self, participant: str | None = None) -> str:
        """A new participant's session (its file written now); returns its id. ``participant``: their
        id from a recruitment platform (``?participant=`` of their link, 1-128 printable characters,
        else a 400), recorded in the header's metadata."""
        if self.fixed:
            raise AnswerRefused("this server serves one session only; no new sessions.", 403)
        if participant is not None and not (isinstance(participant, str) and 0 < len(participant) <= 128 and participant.isprintable()):  # fmt: skip
            raise AnswerRefused(f"a participant id must be 1-128 printable characters, got {participant!r:.80}.", 400)
        self.pool.check_room()  # 503 before anything is made when descriptors or memory run short
        with self._lock:
            for _ in range(100):
                sid = secrets.token_urlsafe(12)
                if sid[0] != "-" and not self.path(sid).exists():
                    break
            else:  # pragma: no cover - 2^-96 per try
                raise RuntimeError("could not draw a new session id")
            try:
                self._new_metadata[sid] = {} if participant is None else {"participant": participant}
                session = self._open(sid)
            except BaseException as exc:
                self._new_metadata.pop(sid, None)
                self._discard(sid)  # no empty session file left behind
                if isinstance(exc, Exception) and _resource_error(exc):
                    self.pool.refuse("file descriptors or memory")
                if isinstance(exc, OSError) and not _resource_error(exc):
                    raise _storage_refused(exc, "no session was started") from None
                raise
            self.pool.add(sid, session)
        self.pool.recovered()
        return sid

    def warm_up(self) -> None:
        """Ask and answer one question of a throwaway session kept in memory (no file, no
        participant), so that the process's first fit, selection and compiled-path load are paid
        before the first participant arrives rather than in their first answers (docs/serve.md, the
        soak). A failure here is not reported: the participants' own sessions meet and report it."""
        if self.fixed:
            return
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                session = PreferenceSession(self.items.X, **self._kwargs)
                q = session.ask()
                mid = (self.num_levels + 1) // 2 if self.num_levels is not None else 0.5
                session.tell(q, mid if q.kind == "rating" else 0)
                session.ask()
                session.close()
        except Exception:  # a warm-up only: nothing depends on it
            pass

    def _discard(self, sid: str) -> None:
        """Remove what a failed creation of ``sid`` left (its file holds no answer: it was never given out)."""
        for p in (self.path(sid), self.path(sid).with_name(self.path(sid).name + ".mode")):
            try:
                p.unlink()
            except OSError:
                pass

    def _open_checked(self, sid: str) -> PreferenceSession:
        """Session ``sid`` from its file, for the pool: ``AnswerRefused`` (409) if the file does not
        fit these items, ``ServerBusy`` (503) for want of descriptors or memory, 404 if it is gone,
        507 / 503 if its file cannot be written (a full disk)."""
        if not self.path(sid).is_file():  # never a new, empty session in place of a deleted file
            raise AnswerRefused("no such session.", 404)
        try:
            return self._open(sid)
        except SessionFileError as err:
            if _resource_error(err):
                self.pool.refuse("file descriptors or memory")
            raise AnswerRefused(f"session {sid} cannot be opened: {err}", 409) from None
        except (OSError, MemoryError) as err:
            if _resource_error(err):
                self.pool.refuse("file descriptors or memory")
                raise
            if isinstance(err, OSError):
                raise _storage_refused(err, f"session {sid} cannot be opened") from None
            raise

    def on_finished(self, sid: str) -> None:
        """Called when session ``sid``'s last question is answered (a study refits its population)."""

    def completion(self) -> dict | None:
        """A finished participant's completion ``code`` and ``redirect`` address (``None`` here; a study's own)."""
        return None

    def session_settings(self, sid: str) -> dict:
        """The settings session ``sid`` is opened (or created) with."""
        return dict(self._kwargs)

    def _open(self, sid: str) -> PreferenceSession:
        # the selector: a new session's is the default (torchpref.default_selector), a resumed one's
        # the one its header records; a new session's header gets the metadata create() left
        kwargs = dict(self.session_settings(sid), session_file=self.path(sid), repair=True)
        kwargs["metadata"] = {**kwargs["metadata"], **self._new_metadata.pop(sid, {})}
        with warnings.catch_warnings(record=True) as caught:  # a partial last line: never acknowledged
            warnings.simplefilter("always")
            session = PreferenceSession(self.items.X, **kwargs)
        for w in caught:
            print(f"torchpref serve: {w.category.__name__}: {w.message}", flush=True)
        return session

    def entry(self, sid: str) -> _Entry:
        """The open session ``sid`` (opened from its file on first use).

        Raises:
            AnswerRefused: (404) no such session; (409) its file does not fit these items.
        """
        if not isinstance(sid, str) or not SID_PATTERN.fullmatch(sid):
            raise AnswerRefused("no such session.", 404)
        found = self.pool.get(sid)
        if found is not None:
            return found
        if self.fixed or not self.path(sid).is_file():
            raise AnswerRefused("no such session.", 404)
        return self.pool.entry(sid)

    @property
    def sids(self) -> list[str]:
        """The ids of the sessions open now."""
        return self.pool.open_sids

    def close(self) -> None:
        """Release the session files this store opened (a session given to it stays open) and stop
        the plot worker."""
        self.pool.close()
        self.plots.close()

    # --------------------------------------------------------------- state
    def _option(self, i: int | None, x) -> dict:
        feats = [[n, f"{float(v):.4g}"] for n, v in zip(self.items.names, x.tolist(), strict=False)]
        has = i is not None and self.items.has_pictures
        return {
            "index": i,
            "label": self.items.label(i) if i is not None else "-",
            "features": feats,
            "picture": f"../../picture/{i}" if has else None,
        }

    def _current(self, entry: _Entry) -> tuple[str, Query | None]:
        s = entry.session
        position = len(s.records)
        if s.done:
            return make_qid(entry.sid, position, None), None
        q = s.ask()
        return make_qid(entry.sid, position, q.items.tolist()), q

    def state(self, entry: _Entry) -> dict:
        """What the page shows now: the question (or that all are answered), progress and the
        currently recommended item. Call with ``entry.lock`` held."""
        s = entry.session
        qid, q = self._current(entry)
        out: dict[str, Any] = {
            "sid": entry.sid,
            "qid": qid,
            "answered": s.step,
            "total": s.num_queries,
            "done": q is None,
            "can_undo": s.step > 0,
            "noun": self.items.noun,
            "question": None,
            "recommended": None,
        }
        if q is not None:
            rows = [q.index] if q.kind == "rating" else list(q.indices)
            question = {"kind": q.kind, "options": [self._option(i, x) for i, x in zip(rows, q.items, strict=False)]}
            if q.kind == "rating":
                k = s.num_levels
                question["levels"] = k
                question["words"] = {str(j): LEVEL_WORDS.get(j, "") for j in (1, k)} if k else None
            else:
                question["ties"] = self.ties
            out["question"] = question
        if s.step > 0:
            i, x = s.best_item()
            out["recommended"] = self._option(i, x)
        if q is None and self.completion() is not None:
            out["completion"] = self.completion()
        return out

    # ------------------------------------------------------------- answers
    def answer(self, sid: str, body: object) -> dict:
        """Record a browser's answer ``body = {"qid", "answer", "response_time"}`` (see the
        module); returns the next state (``"duplicate": true`` for a repeated answer).

        Raises:
            AnswerRefused: nothing recorded: a malformed body or answer (400), no such session
                (404), a stale, differently answered or foreign question (409).
        """
        entry = self.entry(sid)
        body = _object(body, ANSWER_FIELDS)
        rt = _response_time(body.get("response_time"))
        times = _times(body)
        with entry.lock:
            qid, q = self._current(entry)
            if body.get("qid") == qid and q is None:
                n = entry.session.num_queries
                raise AnswerRefused(
                    f"all {n} questions are answered; undo to change an answer.", 409, self.state(entry)
                )
            try:
                if body.get("qid") != qid:
                    return self._not_current(entry, body)
                entry.session.tell(q, self._checked_answer(entry, q, body.get("answer")), response_time=rt, **times)
            except AnswerRefused:  # a stale or repeated question (409): refused as it is
                raise
            except OSError as err:  # the disk is full, or another failure to write: nothing recorded
                raise _storage_refused(err, "your answer was not saved; the page tries again") from None
            except SessionFileError as err:  # the file cannot take this answer (changed, gone, read-only)
                raise AnswerRefused(f"answer not recorded: {err}", 503, self.state(entry)) from None
            except ValueError as exc:  # InvalidAnswer (the query's validation), or another bad value
                raise AnswerRefused(f"answer not recorded: {exc}", 400, self.state(entry)) from None
            return self.state(entry)

    def _checked_answer(self, entry: _Entry, q: Query, answer: object) -> int | float | None:
        """The JSON ``answer`` to ``q``, checked only for what JSON adds (raising
        :class:`~torchpref.data.queries.InvalidAnswer`): a level or a chosen option is a JSON
        integer (``3.0`` is not level 3, so a retry sent as ``3.0`` is not taken for the answer
        ``3``), and "no preference" only where it is offered. Its range is the session's to check, once
        (:meth:`~torchpref.PreferenceSession.tell` through the query's own validation)."""
        if isinstance(q, RankingQuery):
            if answer is None:
                if not self.ties:
                    raise InvalidAnswer("'no preference' is not offered here: pick one option.")
                return None
            if _is_int(answer):
                return answer
            raise InvalidAnswer(f"a choice must be the chosen option's number (a JSON integer), got {answer!r:.40}.")
        k = entry.session.num_levels
        if _is_int(answer) or (k is None and isinstance(answer, float)):
            return answer
        want = f"a whole level in 1..{k}" if k is not None else "a number in [0, 1]"
        raise InvalidAnswer(f"a rating must be {want}, got {answer!r:.40}.")

    def _not_current(self, entry: _Entry, body: dict) -> dict:
        """The answer names another question than the current one: a repeat of the last answer
        (acknowledged again), or refused."""
        qid = body.get("qid")
        records = entry.session.typed_records
        try:
            position = int(str(qid).split(".")[0])
        except ValueError:
            position = -1
        if 0 <= position < len(records):
            rec = records[position]
            asked = isinstance(rec, AnswerRecord) and rec.step is not None
            if isinstance(rec, AnswerRecord) and asked and qid == make_qid(entry.sid, position, rec.items):
                in_force = rec.seq in entry.session.in_force_seqs
                if in_force and position == len(records) - 1:
                    # the retry's answer is checked as the first try's was (3.0 or true is not 3 or 1)
                    answer = self._checked_answer(entry, _asked(rec), body.get("answer"))
                    if _same_answer(answer, rec.answer):
                        return dict(self.state(entry), duplicate=True)
                raise AnswerRefused("this question was already answered.", 409, self.state(entry))
        raise AnswerRefused("not the current question of this session (stale, or another's).", 409, self.state(entry))

    def undo(self, sid: str, body: object) -> dict:
        """Withdraw the last answer; ``body = {"qid"}`` names the question on screen (a second
        click on a stale page is refused). Returns the new state."""
        entry = self.entry(sid)
        body = _object(body, {"qid"})
        with entry.lock:
            qid, _ = self._current(entry)
            if body.get("qid") != qid:
                raise AnswerRefused(
                    "the page is not showing the current question: nothing undone.", 409, self.state(entry)
                )
            if entry.session.step == 0:
                raise AnswerRefused("nothing to undo yet.", 400, self.state(entry))
            try:
                entry.session.undo()
            except OSError as err:
                raise _storage_refused(err, "nothing was undone") from None
            except SessionFileError as err:
                raise AnswerRefused(f"nothing undone: {err}", 503, self.state(entry)) from None
            return self.state(entry)

    # ------------------------------------------------------------- exports
    def answers_csv(self, sid: str) -> str:
        """Every answer record as CSV: seq, time, kind, step, items' labels, answer, chosen label,
        rating value, response time (seconds), whether it is in force."""
        entry = self.entry(sid)
        with entry.lock:
            records, active = entry.session.typed_records, entry.session.in_force_seqs
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(["seq", "time", "kind", "step", "items", "answer", "chosen", "value", "response_time", "in_force"])
        for r in records:
            if not isinstance(r, AnswerRecord):
                continue
            rows = r.pool_indices
            labels = [self.items.label(i) for i in rows] if rows else [json.dumps(list(x)) for x in r.items]
            chosen = labels[int(r.answer)] if r.kind == "choice" and r.answer is not None else ""
            rt = r.response_time
            w.writerow(
                [
                    r.seq,
                    r.time,
                    r.kind,
                    "" if r.step is None else r.step,
                    ";".join(_csv_safe(lab) for lab in labels),
                    "" if r.answer is None else r.answer,
                    _csv_safe(chosen),
                    "" if r.value is None else r.value,
                    "" if rt is None else f"{rt:.3f}",
                    int(r.seq in active),
                ]
            )
        return buf.getvalue()

    def checkpoint(self, sid: str) -> bytes:
        """The session's model as a :func:`~torchpref.save_model` file (inputs normalised by the
        session's bounds, as :meth:`~torchpref.PreferenceSession.transform` maps them)."""
        import tempfile

        from torchpref.models.checkpoint import save_model

        entry = self.entry(sid)
        with entry.lock, tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "model.pt"
            save_model(entry.session.model, path)
            return path.read_bytes()

    def session_file(self, sid: str) -> bytes:
        """The session file's bytes (or, for a session without a file, its records as JSON Lines)."""
        entry = self.entry(sid)
        with entry.lock:
            s = entry.session
            if s.path is not None:
                return s.path.read_bytes()
            return "".join(json.dumps(r) + "\n" for r in s.records).encode()


def _asked(rec: AnswerRecord) -> Query:
    """The question an answer record answered (its items; for the answer's checks)."""
    items = torch.tensor(rec.items, dtype=torch.float64)
    return RatingQuery(items[0]) if rec.kind == "rating" else RankingQuery(items)


def _same_answer(a: object, b: object) -> bool:
    """Equal answers of the same JSON type (``1 == 1.0 == True`` in Python, not in an answer)."""
    return a == b and (a is None) == (b is None) and isinstance(a, float) == isinstance(b, float)


def _storage_refused(err: OSError, what: str) -> AnswerRefused:
    """A failure to write a session file as a reply: ``507`` for a full disk or quota, else ``503``."""
    if err.errno in (errno.ENOSPC, errno.EDQUOT):
        return AnswerRefused(f"the server's disk is full: {what}. Tell the study's organiser.", 507)
    return AnswerRefused(f"the server cannot write its session files ({err.strerror or err}): {what}.", 503)


def _times(body: dict) -> dict[str, str]:
    """``shown_at`` / ``answered_at`` of an answer request (the page's clock, ms since 1970) as
    ISO 8601 times; absent ones are left out.

    Raises:
        AnswerRefused: (400) not a number of milliseconds between 2000 and 2200, or answered
            before shown.
    """
    out, ms = {}, {}
    for key in ("shown_at", "answered_at"):
        value = body.get(key)
        if value is None:
            continue
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        if not ok or not 946684800000 <= value <= 7258118400000:
            raise AnswerRefused(f"{key} must be the page's time in milliseconds since 1970, got {value!r:.40}.", 400)
        ms[key] = float(value)
        stamp = _dt.datetime.fromtimestamp(ms[key] / 1000, _dt.timezone.utc)
        out[key] = stamp.isoformat(timespec="milliseconds")
    if len(ms) == 2 and ms["answered_at"] < ms["shown_at"]:
        raise AnswerRefused("answered_at is before shown_at.", 400)
    return out


def _resource_error(exc: BaseException) -> bool:
    from torchpref.frontends.serve.pool import resource_error

    return resource_error(exc)


def _is_int(v: object) -> TypeGuard[int]:
    return isinstance(v, int) and not isinstance(v, bool)


def _object(body: object, allowed: set[str]) -> dict:
    if not isinstance(body, dict):
        raise AnswerRefused(f"the request must be a JSON object, got {type(body).__name__}.", 400)
    extra = set(body) - allowed
    if extra:
        raise AnswerRefused(f"unknown field(s) {', '.join(sorted(map(repr, extra)))[:80]}.", 400)
    if not isinstance(body.get("qid"), str):
        raise AnswerRefused("the request names no question ('qid').", 400)
    return body


def _response_time(value: object) -> float | None:
    if value is None:
        return None
    ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not ok or not 0.0 <= value <= MAX_RESPONSE_TIME:  # a huge integer compares without overflow
        raise AnswerRefused(
            f"response_time must be a number of seconds in 0..{MAX_RESPONSE_TIME:.0f}, got {value!r:.40}.", 400
        )
    return float(value)


def _csv_safe(text: str) -> str:
    """A label that a spreadsheet will not run as a formula."""
    return "'" + text if text[:1] in ("=", "+", "-", "@", "\t", "\r") else text
