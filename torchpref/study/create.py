r"""Creating a study's folder (``torchpref study serve DIR`` the first time), or opening an existing
one with the settings it was created with.

Everything given is checked before anything is written (the items CSV read whole, the settings in
range), so a mistake is not frozen into the folder; serving an existing study with a setting other
than its own is refused, naming both and the way out.
"""

from __future__ import annotations

import os
import shutil
import urllib.parse
from collections.abc import Callable
from pathlib import Path

from torchpref.selection.defaults import SELECTOR_NAMES
from torchpref.study.folder import FORMAT, VERSION, StudyFolder, make_private, now, private_dir, write_json_atomically

__all__ = ["DEFAULTS", "check_settings", "create_study", "way_out"]

DEFAULTS: dict[str, object] = {
    "num_queries": 14,
    "num_levels": 5,
    "ties": True,
    "seed": 0,
    "selector": "default",
    "completion_code": None,
    "redirect_url": None,
}
"""A new study's settings where not given (and an older study's where its study.json has none)."""

_SKELETON = {"sessions", "population", "exports", "log.jsonl", "refit.log", ".experimenter-key", ".server.lock"}


def _whole(name: str, value: object, lo: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < lo:
        raise ValueError(f"{name} must be a whole number >= {lo}, got {value!r:.80}.")
    return value


def check_settings(settings: dict[str, object]) -> dict[str, object]:
    """The study settings ``settings`` (keys of :data:`DEFAULTS`), checked.

    Raises:
        ValueError: an unknown setting or a value out of range, naming it and the value.
    """
    unknown = sorted(set(settings) - set(DEFAULTS))
    if unknown:
        raise ValueError(f"unknown study setting(s) {', '.join(unknown)}; the settings are {', '.join(DEFAULTS)}.")
    s = {**DEFAULTS, **settings}
    _whole("num_queries", s["num_queries"], 1)
    if s["num_levels"] is not None:
        _whole("num_levels", s["num_levels"], 2)
    if not isinstance(s["seed"], int) or isinstance(s["seed"], bool):
        raise ValueError(f"seed must be a whole number, got {s['seed']!r:.80}.")
    if not isinstance(s["ties"], bool):
        raise ValueError(f"ties must be True or False, got {s['ties']!r:.80}.")
    if s["selector"] not in SELECTOR_NAMES:
        raise ValueError(f"unknown selector {s['selector']!r:.80}: one of {', '.join(SELECTOR_NAMES)}.")
    code = s["completion_code"]
    if code is not None and not (
        isinstance(code, str) and 0 < len(code) <= 64 and code.isprintable() and code.strip() == code
    ):
        raise ValueError(f"completion_code must be 1-64 printable characters, got {code!r:.80}.")
    url = s["redirect_url"]
    if url is not None:
        parts = urllib.parse.urlsplit(url) if isinstance(url, str) and url.isprintable() else None
        if parts is None or parts.scheme not in ("http", "https") or not parts.netloc:
            raise ValueError(f"redirect_url must be an http:// or https:// address, got {url!r:.120}.")
    return s


def way_out(folder: StudyFolder) -> str:
    """What a researcher can do about a study that does not serve as asked: serve it as it is, or
    (without participants yet) delete it and create it again."""
    has_people = folder.sessions.is_dir() and any(folder.sessions.glob("*.session.jsonl"))
    keep = f"Serve it as it is with 'torchpref study serve {folder.path}' (its own items and settings)"
    if has_people:
        return f"{keep}, or create a new study in another folder."
    return f"{keep}; it has no participants yet, so you may also delete the folder {folder.path} and create it again."


def _check_same(folder: StudyFolder, settings: dict, given: dict[str, object], items: dict[str, object]) -> None:
    for key, value in {**given, **items}.items():
        if value is None and key in items:
            continue
        mine = settings.get(key, DEFAULTS.get(key))
        if value != mine:
            raise ValueError(
                f"{folder.path} is a study created with {key}={mine!r}, and this serve gives {key}={value!r}: "
                f"a study's settings do not change once created. {way_out(folder)}"
            )


def create_study(
    path: str | os.PathLike,
    *,
    items: str | os.PathLike | None,
    world: str | None = None,
    id_column: str | None = None,
    image_column: str | None = None,
    image_dir: str | os.PathLike | None = None,
    check: Callable[[], object] | None = None,
    **given: object,
) -> StudyFolder:
    """A new study folder at ``path``, or the existing study there: ``items`` a features CSV (copied
    into the folder; its images stay where they are, ``image_dir`` or the CSV's folder) or
    ``world="lake"``; ``given``: settings of :data:`DEFAULTS` (``num_queries=10``, ...).

    For a new study, everything is checked before the folder is written: the settings
    (:func:`check_settings`) and ``check()`` (the server reads the items with it). An existing
    study must be given the same items and settings (those not given are its own).

    Raises:
        ValueError: neither or both of ``items`` and ``world``; a setting out of range; a folder
            that holds something else; an existing study of other items or settings (naming the
            way out); what ``check`` raises.
    """
    folder = StudyFolder(Path(path))
    if (items is None) == (world is None):
        raise ValueError("give the items (a features CSV) or a world (lake), not both or neither.")
    check_settings(given)
    if (folder.path / "study.json").exists():
        settings = folder.settings()
        theirs = settings.get("world")
        if world is not None and theirs != world:
            raise ValueError(
                f"{folder.path} is a study of {theirs or 'a CSV of items'}, not of {world}. {way_out(folder)}"
            )
        if items is not None and theirs is not None:
            raise ValueError(f"{folder.path} is a study of the {theirs}, not of {items}. {way_out(folder)}")
        if items is not None and Path(items).resolve() != (folder.path / "items.csv").resolve():
            if Path(items).read_bytes() != (folder.path / "items.csv").read_bytes():
                raise ValueError(
                    f"{folder.path} is a study of other items than {items} (its items.csv differs). {way_out(folder)}"
                )
        _check_same(folder, settings, given, {"id_column": id_column, "image_column": image_column})
        folder.secure()
        return folder
    if folder.path.exists() and not folder.path.is_dir():
        raise ValueError(f"{folder.path} is a file, not a folder: give a new or empty folder for the study.")
    if folder.path.is_dir():
        left = sorted(p.name for p in folder.path.iterdir() if not _leftover(p))
        if left:
            shown = ", ".join(left[:5]) + (", ..." if len(left) > 5 else "")
            raise ValueError(f"{folder.path} exists and is not a study (it holds {shown}): give a new or empty folder.")
    if items is not None and not Path(items).is_file():
        raise ValueError(f"the items file {items} does not exist (or is not a file): check the --features path.")
    settings_in = check_settings(given)
    if check is not None:
        check()  # the items read whole before anything is written
    for d in (folder.path, folder.sessions, folder.populations, folder.exports):
        private_dir(d)
    new: dict[str, object] = {"format": FORMAT, "version": VERSION, "created": now(), "world": world}
    if items is not None:
        shutil.copyfile(items, folder.path / "items.csv")
        make_private(folder.path / "items.csv")
        src = Path(items).resolve()
        new.update(
            id_column=id_column,
            image_column=image_column,
            image_dir=str(Path(image_dir).resolve()) if image_dir is not None else str(src.parent),
        )
    new.update(settings_in)
    write_json_atomically(folder.path / "study.json", new)
    folder.log("created", items=str(items) if items is not None else world)
    return folder


def _leftover(p: Path) -> bool:
    """Whether ``p`` is what an earlier, failed creation may have left: an empty folder of the
    study's, or its log."""
    if p.name not in _SKELETON:
        return False
    if p.is_dir() and not p.is_symlink():
        return not any(p.iterdir())
    return p.name in ("log.jsonl", "refit.log")
