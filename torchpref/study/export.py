r"""``torchpref study export DIR``: a study's answers, participants and population as tables.

* ``answers.csv``: one row per answer record of every session file (undone ones too, marked):
  participant (the session's id), participant_id (the ``?participant=`` of their link, if any),
  status, seq, question (its step; empty for an answer given out of turn), kind, the items (their
  labels, ``;``-separated), the answer, the chosen item's label, the rating's value, seconds (the
  page's response time), when (the record's time), in force;
* ``participants.csv``: one row per participant: their ids, status (``finished``, ``in progress``,
  or ``abandoned``: unfinished and silent for :data:`ABANDONED_AFTER` seconds), answers in force,
  questions, started, first and last answer, median seconds, the population version they started from;
* ``population_utility.csv``: the current population's mean utility and spread at every item (its
  label and features in the items' own units).

Every cell that a spreadsheet would read as a formula (starting ``=``, ``+``, ``-``, ``@``, a tab
or a carriage return) is written with a leading ``'`` (:func:`csv_cell`), header cells included.
Each table is built in memory (:func:`table_bytes`) and written atomically (a temporary file,
renamed: a reader never sees a part), mode 0600; also as Parquet where pyarrow is installed.
"""

from __future__ import annotations

import calendar
import csv
import io
import os
import statistics
import time
from pathlib import Path
from typing import Any

import torch

from torchpref.sessions.contents import SessionContents, read_session
from torchpref.study.folder import StudyFolder, make_private, private_dir, write_private
from torchpref.study.items import StudySpace, study_space

__all__ = [
    "ABANDONED_AFTER",
    "ANSWER_COLUMNS",
    "PARTICIPANT_COLUMNS",
    "TABLES",
    "answer_rows",
    "csv_cell",
    "export",
    "participant_rows",
    "population_rows",
    "study_sessions",
    "table_bytes",
]

ANSWER_COLUMNS = [
    "participant", "participant_id", "status", "seq", "question", "kind", "items", "answer", "chosen", "value",
    "seconds", "time", "in_force",
]  # fmt: skip
PARTICIPANT_COLUMNS = [
    "participant", "participant_id", "status", "answers", "questions", "started", "first_answer", "last_answer",
    "median_seconds", "population_version",
]  # fmt: skip
TABLES = ("answers.csv", "participants.csv", "population_utility.csv")
ABANDONED_AFTER = 1800.0
"""An unfinished session without an answer (or, with none, since it started) for this many seconds is abandoned."""

_FORMULA = ("=", "+", "-", "@", "\t", "\r")


def csv_cell(value: object) -> object:
    """``value`` as a CSV cell a spreadsheet will not run: text starting ``=``, ``+``, ``-``, ``@``,
    a tab or a carriage return gets a leading ``'``; numbers are kept."""
    if isinstance(value, str) and value.startswith(_FORMULA):
        return "'" + value
    return value


def study_sessions(folder: StudyFolder) -> list[SessionContents]:
    """Every session file of the study that reads (by id); one that does not is left out."""
    out = []
    for f in sorted(folder.sessions.glob("*.session.jsonl")):
        try:
            out.append(read_session(f))
        except (OSError, ValueError):
            continue
    return out


def _seconds_since(stamp: str, now: float) -> float:
    try:
        return now - calendar.timegm(time.strptime(stamp[:19], "%Y-%m-%dT%H:%M:%S"))
    except ValueError:
        return 0.0


def status(s: SessionContents, now: float | None = None) -> str:
    """``"finished"``, ``"abandoned"`` (unfinished and silent for :data:`ABANDONED_AFTER` s) or ``"in progress"``."""
    if s.finished:
        return "finished"
    last = s.records[-1].time if s.records else s.header.created
    silent = _seconds_since(last, time.time() if now is None else now)
    return "abandoned" if silent >= ABANDONED_AFTER else "in progress"


def participant_id(s: SessionContents) -> str:
    """The participant's id from their link (``?participant=``), or empty."""
    pid = s.header.metadata.get("participant")
    return pid if isinstance(pid, str) else ""


def population_version(s: SessionContents) -> int | None:
    """The population version the session started from (``None``: none)."""
    v = s.header.metadata.get("study_population")
    return v if isinstance(v, int) and not isinstance(v, bool) else None


def answer_rows(folder: StudyFolder, space: StudySpace | None = None) -> list[dict[str, Any]]:
    """Every answer record of every session file, as ``ANSWER_COLUMNS`` rows."""
    space = space if space is not None else study_space(folder)
    rows = []
    for s in study_sessions(folder):
        st, pid = status(s), participant_id(s)
        for r in s.answers:
            labels = [space.label(i, x) for i, x in zip(s.item_rows(r), r.items)]
            chosen = labels[int(r.answer)] if r.kind == "choice" and r.answer is not None else ""
            rows.append(
                dict(
                    participant=s.sid,
                    participant_id=pid,
                    status=st,
                    seq=r.seq,
                    question="" if r.step is None else r.step,
                    kind=r.kind,
                    items=";".join(labels),
                    answer="" if r.answer is None else r.answer,
                    chosen=chosen,
                    value="" if r.value is None else r.value,
                    seconds="" if r.response_time is None else round(r.response_time, 3),
                    time=r.time,
                    in_force=int(r.seq not in s.undone),
                )  # fmt: skip
            )
    return rows


def participant_rows(folder: StudyFolder) -> list[dict[str, Any]]:
    """One summary row per participant (``PARTICIPANT_COLUMNS``)."""
    rows = []
    for s in study_sessions(folder):
        answers = s.in_force
        secs = [r.response_time for r in answers if r.response_time is not None]
        version = population_version(s)
        rows.append(
            dict(
                participant=s.sid,
                participant_id=participant_id(s),
                status=status(s),
                answers=len(answers),
                questions=s.header.num_queries,
                started=s.header.created,
                first_answer=answers[0].time if answers else "",
                last_answer=answers[-1].time if answers else "",
                median_seconds=round(statistics.median(secs), 3) if secs else "",
                population_version="" if version is None else version,
            )  # fmt: skip
        )
    return rows


def population_rows(folder: StudyFolder, space: StudySpace | None = None) -> list[dict[str, Any]]:
    """The current population's mean utility and spread (sd) at every item, one row per item (its
    label and features in the items' units); empty before the first population."""
    pointer = folder.current()
    if pointer is None:
        return []
    space = space if space is not None else study_space(folder)
    pop = folder.population(pointer.version, names=space.names)
    assert pop is not None
    X = space.unit
    with torch.no_grad():
        post = pop.person_model(X).posterior(X.unsqueeze(-2))
        mean, sd = post.mean.reshape(-1), post.variance.reshape(-1).clamp_min(0).sqrt()
    return [
        {"item": space.labels[i], **dict(zip(space.names, space.X[i].tolist())), "mean": float(m), "sd": float(s)}
        for i, (m, s) in enumerate(zip(mean.tolist(), sd.tolist()))
    ]


def _csv(rows: list[dict], columns: list[str]) -> bytes:
    buf = io.StringIO(newline="")
    w = csv.writer(buf)
    w.writerow([csv_cell(c) for c in columns])
    for r in rows:
        w.writerow([csv_cell(r.get(c, "")) for c in columns])
    return buf.getvalue().encode()


def _table(folder: StudyFolder, what: str, space: StudySpace) -> tuple[list[dict], list[str]]:
    if what == "answers.csv":
        return answer_rows(folder, space), ANSWER_COLUMNS
    if what == "participants.csv":
        return participant_rows(folder), PARTICIPANT_COLUMNS
    if what == "population_utility.csv":
        return population_rows(folder, space), ["item", *space.names, "mean", "sd"]
    raise ValueError(f"no table {what!r}: one of {', '.join(TABLES)}.")


def table_bytes(folder: StudyFolder, what: str, space: StudySpace | None = None) -> bytes:
    """One table (``"answers.csv"``, ``"participants.csv"`` or ``"population_utility.csv"``) as CSV
    bytes, built in memory (what a download sends: no file is read back).

    Raises:
        ValueError: another name, naming it and the tables.
    """
    rows, columns = _table(folder, what, space if space is not None else study_space(folder))
    return _csv(rows, columns)


def _parquet(rows: list[dict], columns: list[str], path: Path) -> Path | None:
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return None
    table = pa.table({str(csv_cell(c)): [str(csv_cell(r.get(c, ""))) for r in rows] for c in columns})
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    pq.write_table(table, tmp)
    make_private(tmp)
    os.replace(tmp, path)
    return path


def export(folder: StudyFolder, out: Path | None = None) -> list[Path]:
    """Write the three tables (module docstring) to ``out`` (default ``DIR/exports``, mode 0700),
    each atomically; returns the files."""
    if out is None:
        out = private_dir(folder.exports)
    out.mkdir(parents=True, exist_ok=True)
    space = study_space(folder)
    written = []
    for what in TABLES:
        rows, columns = _table(folder, what, space)
        write_private(out / what, _csv(rows, columns))
        written.append(out / what)
        pq = _parquet(rows, columns, (out / what).with_suffix(".parquet"))
        if pq is not None:
            written.append(pq)
    return written
