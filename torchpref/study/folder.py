r"""A study's folder: its settings, items, session files, population versions and log.

::

    DIR/study.json          the settings (format, items, session settings, created)
    DIR/items.csv           the items (a copy of the features CSV; absent for the lake)
    DIR/sessions/           one session file per participant (SID.session.jsonl)
    DIR/population/         vNNNN.pt, one file per fitted population, and current.json (which
                            one new participants start from), each replaced atomically
    DIR/log.jsonl           what happened: the server's starts, finished participants, refits
    DIR/exports/            what ``torchpref study export`` and ``report`` write

A participant's session header records the population version it started from
(``metadata.study_population``), so a session reopened later (after a restart, or after it was
closed for being idle) is rebuilt from the same population, whatever the current one is.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from torchpref.data.files import read_regular_text
from torchpref.models.checkpoint import CheckpointError
from torchpref.population.io import load_population
from torchpref.population.model import Population

__all__ = ["FORMAT", "Pointer", "StudyFolder", "write_json_atomically", "write_private"]

FORMAT = "torchpref-study"
VERSION = 1


PRIVATE_FILE = 0o600
"""The mode of every file the study writes: what the experimenter's key guards is nobody else's."""
PRIVATE_DIR = 0o700
"""The mode of the study's folders."""
KEEP_LOADED = 3
"""How many loaded population versions a :class:`StudyFolder` keeps (the newest)."""


def write_private(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` (mode 0600) through a temporary file, fsynced, renamed: a reader
    (or a kill at any moment) sees the old file or the new one, never a part or an empty one."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_CLOEXEC", 0), PRIVATE_FILE)
    try:
        with os.fdopen(fd, "wb") as fh:
            os.fchmod(fh.fileno(), PRIVATE_FILE)  # whatever the umask
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def write_json_atomically(path: Path, obj: object) -> None:
    """Write ``obj`` as JSON to ``path`` atomically, mode 0600 (:func:`write_private`)."""
    write_private(path, json.dumps(obj, indent=1).encode())


def private_dir(path: Path) -> Path:
    """``path`` made (with its parents) if missing, and mode 0700; returns it."""
    path.mkdir(parents=True, exist_ok=True, mode=PRIVATE_DIR)
    os.chmod(path, PRIVATE_DIR)
    return path


def make_private(path: Path) -> None:
    """Mode 0600 for a file the study wrote (0700 for a folder), whoever made it and whatever the umask."""
    with contextlib.suppress(FileNotFoundError):
        os.chmod(path, PRIVATE_DIR if path.is_dir() and not path.is_symlink() else PRIVATE_FILE)


def now() -> str:
    """The current UTC time, ISO 8601 (the log's and the pointer's)."""
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


@dataclass(frozen=True)
class Pointer:
    """Which population new participants start from (``population/current.json``, validated).

    Attributes:
        version: the population's version (its file ``population/vNNNN.pt``).
        participants: the participants it was fitted on (empty where unknown: a fallback).
        seconds: how long its fit took (``None`` where unknown).
        fitted_at: when it was made current (ISO 8601; empty where unknown).
        fallback: why ``current.json`` was not used as written (``None``: it was).
    """

    version: int
    participants: tuple[str, ...]
    seconds: float | None = None
    fitted_at: str = ""
    fallback: str | None = None


def _pointer_problem(obj: object, folder: StudyFolder) -> str | None:
    """What is wrong with a parsed ``current.json`` (``None``: nothing)."""
    if not isinstance(obj, dict):
        return f"it is not a JSON object ({type(obj).__name__})"
    v = obj.get("version")
    if not isinstance(v, int) or isinstance(v, bool) or v < 1:
        return f"its version {v!r:.40} is not a whole number >= 1"
    if not folder.version_path(v).is_file():
        return f"the population version {v} it names is missing ({folder.version_path(v).name})"
    people = obj.get("participants")
    if not isinstance(people, list) or not all(isinstance(p, str) for p in people):
        return f"its participants {people!r:.60} are not a list of participant ids"
    return None


@dataclass(frozen=True)
class StudyFolder:
    """A study's folder (module docstring); :func:`create_study` makes one, ``StudyFolder(path)``
    opens one (:meth:`settings` checks it is a study)."""

    path: Path
    _cache: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", Path(self.path))

    # ------------------------------------------------------------------ places
    @property
    def sessions(self) -> Path:
        """``DIR/sessions``: one session file per participant."""
        return self.path / "sessions"

    @property
    def populations(self) -> Path:
        """``DIR/population``: the fitted populations and ``current.json``."""
        return self.path / "population"

    @property
    def exports(self) -> Path:
        """``DIR/exports``: what ``export`` and ``report`` write."""
        return self.path / "exports"

    @property
    def log_path(self) -> Path:
        """``DIR/log.jsonl``: the study's events."""
        return self.path / "log.jsonl"

    def settings(self) -> dict:
        """The study's settings (``study.json``).

        Raises:
            ValueError: the folder is not a study (naming what is missing or wrong).
        """
        f = self.path / "study.json"
        if not f.is_file():
            raise ValueError(
                f"{self.path} is not a torchpref study (no study.json): create it with 'torchpref study serve'."
            )
        try:
            settings = json.loads(read_regular_text(f, "study settings", 2**20))
        except ValueError as err:
            raise ValueError(f"{f} is not a torchpref study's settings (not JSON: {err}).") from None
        if not isinstance(settings, dict) or settings.get("format") != FORMAT:
            raise ValueError(f"{f} is not a torchpref study's settings.")
        if settings.get("version", 0) > VERSION:
            raise ValueError(f"{f} is of a newer study format ({settings.get('version')}); upgrade torchpref.")
        return settings

    def secure(self) -> None:
        """The folders 0700 and the files 0600, a study made by an older version included (the
        session files name participants; everything here is what the experimenter's key guards)."""
        for d in (self.path, self.sessions, self.populations, self.exports):
            if d.is_dir():
                os.chmod(d, PRIVATE_DIR)
                for f in d.iterdir():
                    if f.is_file() and not f.is_symlink():
                        make_private(f)

    # ------------------------------------------------------------------- log
    def log(self, event: str, **fields: object) -> None:
        """Append one event to ``log.jsonl`` (one JSON line, fsynced; the file mode 0600)."""
        line = json.dumps({"time": now(), "event": event, **fields}) + "\n"
        fd = os.open(self.log_path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), PRIVATE_FILE)
        with os.fdopen(fd, "a") as fh:
            fh.write(line)
            fh.flush()
            os.fsync(fh.fileno())

    def events(self) -> list[dict]:
        """Every event logged so far (a torn last line, from a kill, is skipped)."""
        if not self.log_path.is_file():
            return []
        out = []
        for line in self.log_path.read_text().splitlines():
            try:
                event = json.loads(line)
            except ValueError:
                continue
            if isinstance(event, dict):
                out.append(event)
        return out

    # -------------------------------------------------------------- population
    def current(self) -> Pointer | None:
        """The population new participants start from (``None``: none yet).

        ``current.json`` is validated (a JSON object naming a version whose file loads, and its
        participants); where it is missing, damaged or names a population that is missing or does
        not load, the newest version that loads is used instead and a line saying why is logged
        (and printed) once."""
        f = self.populations / "current.json"
        problem: str | None = None
        try:
            text: str | None = f.read_text()
        except FileNotFoundError:
            text = None
        except (OSError, UnicodeDecodeError) as err:
            text, problem = None, f"it cannot be read ({err})"
        if text is not None:
            try:
                obj = json.loads(text)
            except ValueError as err:
                obj, problem = None, f"it is not JSON ({err})"
            problem = problem or _pointer_problem(obj, self)
            if problem is None:
                assert isinstance(obj, dict)
                problem = self._load_problem(int(obj["version"]))
            if problem is None:
                secs = obj.get("seconds")
                seconds = float(secs) if isinstance(secs, (int, float)) and not isinstance(secs, bool) else None
                return Pointer(int(obj["version"]), tuple(obj["participants"]), seconds, str(obj.get("fitted_at", "")))
        versions = self.versions()
        if text is None and problem is None and not versions:
            return None  # no population yet
        why = problem or "it is missing"
        for v in reversed(versions):
            if self._load_problem(v) is None:
                people = _participants_of(self._cache.get(("pop", v)) or load_population(self.version_path(v)))
                self._report(f"population/current.json is not usable ({why}): using v{v:04d}, the newest that loads.")
                return Pointer(v, people, fallback=why)
        self._report(f"population/current.json is not usable ({why}) and no population version loads: none is used.")
        return None

    def _report(self, line: str) -> None:
        """Log (and print) ``line`` once per server."""
        if line not in self._cache.setdefault("reported", set()):
            self._cache["reported"].add(line)
            print(f"torchpref study: {line}", file=sys.stderr, flush=True)
            self.log("population pointer", why=line)

    def _load_problem(self, version: int) -> str | None:
        """Why population ``version`` does not load (``None``: it does; the loaded one is kept)."""
        f = self.version_path(version)
        try:
            st = f.stat()
        except OSError:
            return f"the population version {version} is missing ({f.name})"
        key = ("pop", version)
        sig = (st.st_mtime_ns, st.st_size)
        if self._cache.get(("sig", version)) == sig:
            return self._cache.get(("problem", version))
        try:
            pop, problem = load_population(f), None
        except (OSError, ValueError) as err:
            pop, problem = (
                None,
                f"the population version {version} does not load ({type(err).__name__}: {str(err)[:160]})",
            )
        self._cache[("sig", version)], self._cache[("problem", version)], self._cache[key] = sig, problem, pop
        loaded = sorted(k[1] for k, v in self._cache.items() if k[0] == "pop" and v is not None)
        for old in loaded[:-KEEP_LOADED]:  # a long-lived worker or server keeps a few, not every version
            self._cache[("pop", old)] = None
        return problem

    def versions(self) -> list[int]:
        """The population versions with a file, oldest first."""
        return sorted(int(p.stem[1:]) for p in self.populations.glob("v*.pt") if p.stem[1:].isdigit())

    def version_path(self, version: int) -> Path:
        """The file of population ``version`` (``population/vNNNN.pt``)."""
        return self.populations / f"v{version:04d}.pt"

    def next_version(self) -> int:
        """One more than the newest population file's version."""
        return max(self.versions(), default=0) + 1

    def population(self, version: int | None, names: list[str] | None = None) -> Population | None:
        """The population of ``version`` (``None``: no population).

        Raises:
            CheckpointError: its file is missing or damaged, or of another objective space.
        """
        if version is None:
            return None
        f = self.version_path(int(version))
        if not f.is_file():
            raise CheckpointError(f"population version {version} of the study {self.path} is missing ({f}).")
        problem = self._load_problem(int(version))
        pop = self._cache.get(("pop", int(version)))
        if problem is not None or pop is None:
            return load_population(f, names=names)  # raises, naming the fault
        try:
            pop.check_space(names=names)
        except ValueError as err:
            raise CheckpointError(f"{f}: {err}") from None
        return pop

    def set_current(self, version: int, participants: list[str], seconds: float) -> None:
        """Make ``version`` the population new participants start from (atomically)."""
        pointer = {"version": version, "file": self.version_path(version).name, "participants": participants}
        write_json_atomically(self.populations / "current.json", dict(pointer, fitted_at=now(), seconds=seconds))


def _participants_of(pop: Population | None) -> tuple[str, ...]:
    """The participants a study's population file says it was fitted on (empty where it does not say)."""
    raw = None if pop is None else pop.stats.get("study_participants")
    try:
        people = json.loads(raw) if isinstance(raw, str) else []
    except ValueError:
        people = []
    return tuple(str(p) for p in people) if isinstance(people, list) else ()
