r"""A study's sessions: :class:`StudyStore` (each new participant starts from the current
population, a reopened session from the version its header recorded, a finished one starts a
refit) and the experimenter's key (:func:`experimenter_key`)."""

from __future__ import annotations

import os
import secrets
import threading
from collections.abc import Callable

from torchpref.frontends.serve.items import ServeItems
from torchpref.frontends.serve.pool import PoolLimits
from torchpref.frontends.serve.store import AnswerRefused, NewSessions, SessionStore
from torchpref.population.model import Population
from torchpref.sessions.contents import read_session_header
from torchpref.study.export import study_sessions
from torchpref.study.folder import PRIVATE_FILE, StudyFolder, make_private
from torchpref.study.refit import MIN_PEOPLE, RefitRunner

__all__ = ["StudyStore", "experimenter_key"]


class StudyStore(SessionStore):
    """The sessions of a study (module docstring).

    Args:
        say: called with one line for the server's terminal per finished participant.
    """

    def __init__(
        self,
        folder: StudyFolder,
        items: ServeItems,
        new: NewSessions,
        limits: PoolLimits,
        refits: RefitRunner,
        say: Callable[[str], None] | None = None,
    ):
        super().__init__(items, folder.sessions, new=new, limits=limits)
        self.folder, self.refits = folder, refits
        self.say = say or (lambda line: None)
        settings = folder.settings()
        self.completion_code = settings.get("completion_code")
        self.redirect_url = settings.get("redirect_url")
        self.selector_name = str(settings.get("selector") or "default")
        self._populations: dict[int, Population] = {}
        self._plock = threading.Lock()
        # participants finished before this start (a restart, a kill): refitted now if the current
        # population does not have them all
        self._finished: set[str] = {s.sid for s in study_sessions(folder) if s.finished}
        pointer = folder.current()
        fitted = set(pointer.participants) if pointer is not None else set()
        if len(self._finished) >= MIN_PEOPLE and not self._finished <= fitted:
            folder.log("refit requested", why="finished participants not in the current population at start")
            refits.request()
        else:
            refits.start()  # ready before the second participant finishes: the first refit starts at once

    def _population(self, version: int | None) -> Population | None:
        if version is None:
            return None
        with self._plock:
            if version not in self._populations:
                pop = self.folder.population(version, names=self.items.names)
                assert pop is not None
                self._populations[version] = pop
            return self._populations[version]

    def session_settings(self, sid: str) -> dict:
        """A new session starts from the current population; a reopened one from its header's."""
        path = self.path(sid)
        header = read_session_header(path) if path.is_file() and path.stat().st_size else None
        if header is not None:
            version = header.metadata.get("study_population")
        else:
            pointer = self.folder.current()
            version = None if pointer is None else pointer.version
        base = super().session_settings(sid)
        metadata = dict(base["metadata"], study_population=version)
        try:
            population = self._population(version)
        except (OSError, ValueError) as err:  # a session's own population gone or damaged: said, not a 500
            self.folder.log("session population unusable", participant=sid, version=version, why=str(err)[:300])
            raise AnswerRefused(
                f"session {sid} started from population v{version}, which cannot be loaded now ({str(err)[:200]}); "
                "the experimenter has been told (the study's log).",
                503,
            ) from None
        return dict(base, population=population, metadata=metadata)

    def create(self, participant: str | None = None) -> str:
        """A new participant's session (its file mode 0600)."""
        sid = super().create(participant)
        make_private(self.path(sid))
        return sid

    def completion(self) -> dict | None:
        """What a participant who has answered every question is shown: the completion code and
        the address to go on to, as the study's settings give them (``None``: neither)."""
        if self.completion_code is None and self.redirect_url is None:
            return None
        return {"code": self.completion_code, "redirect": self.redirect_url}

    def first_population_pending(self) -> bool:
        """Whether the first population is being fitted (enough have finished, none is current yet)."""
        return len(self._finished) >= MIN_PEOPLE and self.folder.current() is None

    def on_finished(self, sid: str) -> None:
        """A participant answered their last question: logged, said, and the population refitted."""
        with self._plock:
            if sid in self._finished:
                return
            self._finished.add(sid)
            count = len(self._finished)
        self.folder.log("finished", participant=sid)
        self.refits.request()
        header = read_session_header(self.path(sid))
        link_id = None if header is None else header.metadata.get("participant")
        who = sid if not isinstance(link_id, str) else f"{sid} ({link_id!r})"
        then = (
            "the population is being refitted"
            if count >= MIN_PEOPLE
            else f"a population is fitted once {MIN_PEOPLE} have"
        )
        self.say(f"torchpref study: participant {who} finished ({count} finished); {then}")


def experimenter_key(folder: StudyFolder) -> str:
    """The study's experimenter key, made once and kept in ``DIR/.experimenter-key`` (mode 0600)."""
    f = folder.path / ".experimenter-key"
    try:
        key = f.read_text().strip()
        if len(key) >= 16:
            make_private(f)
            return key
    except OSError:
        pass
    key = secrets.token_urlsafe(24)
    fd = os.open(f, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, PRIVATE_FILE)
    with os.fdopen(fd, "w") as fh:
        fh.write(key + "\n")
    return key
