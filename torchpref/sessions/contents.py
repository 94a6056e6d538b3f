r"""A session file read whole, for whoever analyses it (a study's refit, export, report and page;
the replays): :func:`read_session` gives its typed header, its records, the answers in force, the
data its model sees and the model it records.

This is the one place outside :class:`~torchpref.PreferenceSession` that turns a file into data,
and it does so with the session's own functions (the unit cube of the header's bounds, the same
anchor, :func:`~torchpref.sessions.model_state.build_data` with the recorded model's
``rating_eps`` and ``rating_levels``), so a change to a session's normalisation or answer encoding
changes both. Reading takes no lock: a server may hold the file open.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchpref.data.preference_data import PreferenceData
from torchpref.models.preference_gp import PreferenceGP
from torchpref.sessions.errors import SessionFileError
from torchpref.sessions.journal import read_header, read_session_file
from torchpref.sessions.model_state import build_data
from torchpref.sessions.recorded import (
    describe_model,
    legacy_model_description,
    recorded_model_factory,
    same_description,
    settings_error,
)
from torchpref.sessions.records import (
    AnswerRecord,
    Record,
    SessionHeader,
    UndoRecord,
    parse_record,
    records_in_force,
)
from torchpref.sessions.settings import to_unit_cube

if TYPE_CHECKING:
    from torchpref.population.model import Population

__all__ = ["SESSION_SUFFIX", "SessionContents", "read_session", "read_session_header", "session_id"]

SESSION_SUFFIX = ".session.jsonl"
"""The ending of a session file's name whose id is the part before it (``SID.session.jsonl``)."""


def session_id(path: str | os.PathLike) -> str:
    """The session id a file's name carries (``SID`` of ``SID.session.jsonl``; else its stem)."""
    name = Path(path).name
    return name[: -len(SESSION_SUFFIX)] if name.endswith(SESSION_SUFFIX) else Path(name).stem


@dataclass(frozen=True, eq=False)
class SessionContents:
    """A session file's contents (:func:`read_session`).

    Attributes:
        path: the file.
        header: its typed header.
        records: every record after the header, typed, in order (answers and undos).
        in_force: the answers not undone, oldest first.
    """

    path: Path
    header: SessionHeader
    records: tuple[Record, ...]
    in_force: tuple[AnswerRecord, ...]

    @property
    def sid(self) -> str:
        """The session's id (its file's name before ``.session.jsonl``)."""
        return session_id(self.path)

    @property
    def answers(self) -> tuple[AnswerRecord, ...]:
        """Every answer record, undone ones included, in order."""
        return tuple(r for r in self.records if isinstance(r, AnswerRecord))

    @cached_property
    def undone(self) -> frozenset[int]:
        """The sequence numbers of the answers withdrawn."""
        return frozenset(r.undoes for r in self.records if isinstance(r, UndoRecord))

    @property
    def finished(self) -> bool:
        """Whether every planned question has an answer in force."""
        return len(self.in_force) >= self.header.num_queries

    def transform(self, X: Tensor) -> Tensor:
        """Items (``... x d``) in the unit cube of the header's bounds, as the session's model sees them."""
        return to_unit_cube(X, self.header.bounds_tensor)

    @cached_property
    def pool(self) -> Tensor | None:
        """The pool's items as recorded (``N x d``, raw units), or ``None`` for a box."""
        pool = self.header.pool
        return None if pool is None else torch.tensor(pool, dtype=torch.float64)

    @property
    def anchor(self) -> Tensor:
        """The item the session's model is built on (``1 x d``, unit cube): the pool's first, or the box's centre."""
        first = self.header.first_item
        if first is None:
            return self.transform(self.header.bounds_tensor.mean(0, keepdim=True))
        return self.transform(torch.tensor([first], dtype=torch.float64))

    @cached_property
    def model_description(self) -> dict:
        """The model the session started with, as its header records it (torchpref 0.1.0's
        default for a file that records none)."""
        return self.header.model or legacy_model_description(self.header.dim)

    def item_rows(self, record: AnswerRecord) -> list[int | None]:
        """The pool rows of an answer's items (``None`` for an item not in the pool, or a box)."""
        if record.pool_indices is not None:
            return list(record.pool_indices)
        pool = self.header.pool or []
        index = {tuple(row): i for i, row in reversed(list(enumerate(pool)))}
        return [index.get(tuple(x)) for x in record.items]

    @cached_property
    def data(self) -> PreferenceData:
        """The data of the answers in force, as the session's model sees it (unit cube, the recorded
        model's ``rating_eps`` and ``rating_levels``)."""
        s = self.model_description.get("settings", {})
        data, _ = build_data(
            self.anchor, list(self.in_force), self.transform, float(s["rating_eps"]), s.get("rating_levels")
        )
        return data

    def model(self, population: Population | None = None) -> PreferenceGP:
        """The session's model of its answers in force: the recorded model (rebuilt from the header;
        with ``population``, that population's person model, which must be the recorded one).

        Raises:
            SessionSettingsError: the model built is not the one the header records (another
                population, or one this version cannot rebuild), naming the difference.
        """
        desc = self.model_description
        if population is not None:
            model = population.person_model(self.anchor)
            if not same_description(describe_model(model), desc):
                raise settings_error(self.path, "model", desc, describe_model(model), "another population was given")
        else:
            factory = recorded_model_factory(desc, self.header.dim)
            if factory is None:
                raise settings_error(
                    self.path, "model", desc, {}, "this version cannot build it without its population"
                )
            model = factory(self.anchor)
        if self.in_force:
            model.replace_data(self.data)
        return model


def read_session(path: str | os.PathLike) -> SessionContents:
    """The contents of the session file ``path``, read and validated without locking it.

    Raises:
        SessionFileError: the file is empty, or a record breaks the format (naming the line);
            see :func:`~torchpref.sessions.journal.read_session_file`.
        OSError: it cannot be read.
    """
    path = Path(path)
    raw_header, raw, _ = read_session_file(path)
    if raw_header is None:
        raise SessionFileError(f"session file {path} is empty.")
    header = SessionHeader.from_json(raw_header, path)
    records = tuple(parse_record(r) for r in raw)
    in_force = tuple(AnswerRecord.from_json(r) for r in records_in_force(raw))
    return SessionContents(path, header, records, in_force)


def read_session_header(path: str | os.PathLike) -> SessionHeader | None:
    """The typed header of the session file ``path`` (its first line only; ``None`` if the file is
    empty or its first line incomplete)."""
    raw = read_header(path)
    return None if raw is None else SessionHeader.from_json(raw, path)
