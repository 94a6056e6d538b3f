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

import json
import os
import shutil
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from torchpref.data.files import read_regular_text
from torchpref.models.checkpoint import CheckpointError
from torchpref.population.io import load_population
from torchpref.population.model import Population

__all__ = ["FORMAT", "StudyFolder", "create_study", "write_json_atomically"]

FORMAT = "torchpref-study"
VERSION = 1


def write_json_atomically(path: Path, obj: object) -> None:
    """Write ``obj`` as JSON to ``path`` through a temporary file, fsynced, renamed: a reader (or a
    kill at any moment) sees the old file or the new one, never a part."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    with open(tmp, "w") as fh:
        json.dump(obj, fh, indent=1)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def now() -> str:
    """The current UTC time, ISO 8601 (the log's and the pointer's)."""
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


@dataclass(frozen=True)
class StudyFolder:
    """A study's folder (module docstring); :func:`create_study` makes one, ``StudyFolder(path)``
    opens one (:meth:`settings` checks it is a study)."""

    path: Path

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
        settings = json.loads(read_regular_text(f, "study settings", 2**20))
        if not isinstance(settings, dict) or settings.get("format") != FORMAT:
            raise ValueError(f"{f} is not a torchpref study's settings.")
        if settings.get("version", 0) > VERSION:
            raise ValueError(f"{f} is of a newer study format ({settings.get('version')}); upgrade torchpref.")
        return settings

    # ------------------------------------------------------------------- log
    def log(self, event: str, **fields: object) -> None:
        """Append one event to ``log.jsonl`` (one JSON line, fsynced)."""
        line = json.dumps({"time": now(), "event": event, **fields}) + "\n"
        with open(self.log_path, "a") as fh:
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
                out.append(json.loads(line))
            except ValueError:
                continue
        return out

    # -------------------------------------------------------------- population
    def current(self) -> dict | None:
        """The pointer to the population new participants start from (``None``: none yet)."""
        f = self.populations / "current.json"
        try:
            return json.loads(f.read_text())
        except (OSError, ValueError):
            return None

    def version_path(self, version: int) -> Path:
        """The file of population ``version`` (``population/vNNNN.pt``)."""
        return self.populations / f"v{version:04d}.pt"

    def next_version(self) -> int:
        """One more than the newest population file's version."""
        versions = [int(p.stem[1:]) for p in self.populations.glob("v*.pt") if p.stem[1:].isdigit()]
        return max(versions, default=0) + 1

    def population(self, version: int | None, names: list[str] | None = None) -> Population | None:
        """The population of ``version`` (``None``: no population).

        Raises:
            CheckpointError: its file is missing or damaged.
        """
        if version is None:
            return None
        f = self.version_path(int(version))
        if not f.is_file():
            raise CheckpointError(f"population version {version} of the study {self.path} is missing ({f}).")
        return load_population(f, names=names)

    def set_current(self, version: int, participants: list[str], seconds: float) -> None:
        """Make ``version`` the population new participants start from (atomically)."""
        pointer = {"version": version, "file": self.version_path(version).name, "participants": participants}
        write_json_atomically(self.populations / "current.json", dict(pointer, fitted_at=now(), seconds=seconds))


def create_study(
    path: str | os.PathLike,
    *,
    items: str | os.PathLike | None,
    world: str | None = None,
    id_column: str | None = None,
    image_column: str | None = None,
    image_dir: str | os.PathLike | None = None,
    num_queries: int = 14,
    num_levels: int | None = 5,
    ties: bool = True,
    seed: int = 0,
) -> StudyFolder:
    """A new study folder at ``path`` (created; an existing study there is opened as it is, and
    must have the same items): ``items`` a features CSV (copied into the folder; its images stay
    where they are, ``image_dir`` or the CSV's folder) or ``world="lake"``.

    Raises:
        ValueError: neither or both of ``items`` and ``world``; a folder that holds something else,
            or a study of other items.
    """
    folder = StudyFolder(Path(path))
    if (items is None) == (world is None):
        raise ValueError("give the items (a features CSV) or a world (lake), not both or neither.")
    if (folder.path / "study.json").exists():
        settings = folder.settings()
        if world is not None and settings.get("world") != world:
            raise ValueError(
                f"{folder.path} is a study of other items ({settings.get('world') or 'a CSV'}), not {world}."
            )
        if items is not None and settings.get("world") is not None:
            raise ValueError(f"{folder.path} is a study of the {settings['world']}, not of {items}.")
        if items is not None and Path(items).read_bytes() != (folder.path / "items.csv").read_bytes():
            raise ValueError(f"{folder.path} is a study of other items than {items} (its items.csv differs).")
        return folder
    if folder.path.exists() and any(folder.path.iterdir()):
        raise ValueError(f"{folder.path} exists and is not a study: give an empty or new folder.")
    for d in (folder.path, folder.sessions, folder.populations, folder.exports):
        d.mkdir(parents=True, exist_ok=True)
    settings = {"format": FORMAT, "version": VERSION, "created": now(), "world": world, "seed": seed}
    if items is not None:
        shutil.copyfile(items, folder.path / "items.csv")
        src = Path(items).resolve()
        settings.update(
            id_column=id_column,
            image_column=image_column,
            image_dir=str(Path(image_dir).resolve()) if image_dir is not None else str(src.parent),
        )
    settings.update(num_queries=num_queries, num_levels=num_levels, ties=ties)
    write_json_atomically(folder.path / "study.json", settings)
    folder.log("created", items=str(items) if items is not None else world)
    return folder
