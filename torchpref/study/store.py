r"""A study's sessions: :class:`StudyStore` (each new participant starts from the current
population, a reopened session from the version its header recorded, a finished one starts a
refit) and the experimenter's key (:func:`experimenter_key`)."""

from __future__ import annotations

import os
import secrets
import threading

from torchpref.frontends.serve.items import ServeItems
from torchpref.frontends.serve.pool import PoolLimits
from torchpref.frontends.serve.store import NewSessions, SessionStore
from torchpref.population.model import Population
from torchpref.sessions.journal import read_header
from torchpref.study.export import participant_rows
from torchpref.study.folder import StudyFolder
from torchpref.study.refit import MIN_PEOPLE, RefitRunner

__all__ = ["StudyStore", "experimenter_key"]


class StudyStore(SessionStore):
    """The sessions of a study (module docstring)."""

    def __init__(
        self, folder: StudyFolder, items: ServeItems, new: NewSessions, limits: PoolLimits, refits: RefitRunner
    ):
        super().__init__(items, folder.sessions, new=new, limits=limits)
        self.folder, self.refits = folder, refits
        self._populations: dict[int, Population] = {}
        self._plock = threading.Lock()
        # participants finished before this start (a restart, a kill): refitted now if the current
        # population does not have them all
        self._finished: set[str] = {str(r["participant"]) for r in participant_rows(folder) if r["finished"]}
        pointer = folder.current()
        fitted = set(pointer["participants"]) if pointer is not None else set()
        if len(self._finished) >= MIN_PEOPLE and not self._finished <= fitted:
            folder.log("refit requested", why="finished participants not in the current population at start")
            refits.request()

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
        header = read_header(path) if path.is_file() and path.stat().st_size else None
        if header is not None:
            version = (header.get("metadata") or {}).get("study_population")
        else:
            pointer = self.folder.current()
            version = None if pointer is None else int(pointer["version"])
        base = super().session_settings(sid)
        metadata = dict(base["metadata"], study_population=version)
        return dict(base, population=self._population(version), metadata=metadata)

    def on_finished(self, sid: str) -> None:
        """A participant answered their last question: logged, and the population refitted."""
        with self._plock:
            if sid in self._finished:
                return
            self._finished.add(sid)
        self.folder.log("finished", participant=sid)
        self.refits.request()


def experimenter_key(folder: StudyFolder) -> str:
    """The study's experimenter key, made once and kept in ``DIR/.experimenter-key`` (mode 0600)."""
    f = folder.path / ".experimenter-key"
    try:
        key = f.read_text().strip()
        if len(key) >= 16:
            return key
    except OSError:
        pass
    key = secrets.token_urlsafe(24)
    fd = os.open(f, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(key + "\n")
    return key
