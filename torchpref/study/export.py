r"""``torchpref study export DIR``: a study's answers, participants and population as tables.

* ``answers.csv``: one row per answer record of every session file (undone ones too, marked):
  participant, seq, question (its step; empty for an answer given out of turn), kind, the items'
  labels (rows of the study's items, ``;``-separated), the answer, the chosen item, the rating's
  value, seconds (the page's response time), when (the record's time), in force;
* ``participants.csv``: one row per participant: answers in force, questions, finished, first and
  last answer, median seconds, the population version they started from;
* ``population_utility.csv``: the current population's mean utility and spread at every item.

Each is also written as Parquet where pyarrow is installed.
"""

from __future__ import annotations

import csv
import json
import statistics
from pathlib import Path
from typing import Any

import torch

from torchpref.sessions.journal import read_session_file
from torchpref.sessions.records import AnswerRecord, UndoRecord, parse_record
from torchpref.sessions.settings import pool_digest
from torchpref.study.folder import StudyFolder

__all__ = ["ANSWER_COLUMNS", "answer_rows", "export", "participant_rows", "population_rows"]

ANSWER_COLUMNS = [
    "participant", "seq", "question", "kind", "items", "answer", "chosen", "value", "seconds", "time", "in_force",
]  # fmt: skip


def _sessions(folder: StudyFolder) -> list[tuple[str, dict, list]]:
    out = []
    for f in sorted(folder.sessions.glob("*.session.jsonl")):
        try:
            header, raw, _ = read_session_file(f)
        except (OSError, ValueError):
            continue
        if header is not None:
            out.append((f.name.split(".")[0], header, [parse_record(r) for r in raw]))
    return out


def _rows_of(pool: list, items: tuple) -> list[int | None]:
    index = {tuple(row): i for i, row in enumerate(pool)}
    return [index.get(tuple(x)) for x in items]


def answer_rows(folder: StudyFolder) -> list[dict[str, Any]]:
    """Every answer record of every session file, as ``ANSWER_COLUMNS`` rows."""
    rows = []
    for sid, header, records in _sessions(folder):
        undone = {r.undoes for r in records if isinstance(r, UndoRecord)}
        pool = header["candidates"].get("items", [])
        for r in records:
            if not isinstance(r, AnswerRecord):
                continue
            idx = r.pool_indices or _rows_of(pool, r.items)
            labels = [f"#{i + 1}" if i is not None else json.dumps(list(x)) for i, x in zip(idx, r.items)]
            chosen = labels[int(r.answer)] if r.kind == "choice" and r.answer is not None else ""
            rows.append(
                dict(
                    participant=sid,
                    seq=r.seq,
                    question="" if r.step is None else r.step,
                    kind=r.kind,
                    items=";".join(labels),
                    answer="" if r.answer is None else r.answer,
                    chosen=chosen,
                    value="" if r.value is None else r.value,
                    seconds="" if r.response_time is None else round(r.response_time, 3),
                    time=r.time,
                    in_force=int(r.seq not in undone),
                )  # fmt: skip
            )
    return rows


def participant_rows(folder: StudyFolder) -> list[dict[str, Any]]:
    """One summary row per participant."""
    rows = []
    for sid, header, records in _sessions(folder):
        undone = {r.undoes for r in records if isinstance(r, UndoRecord)}
        answers = [r for r in records if isinstance(r, AnswerRecord) and r.seq not in undone]
        secs = [r.response_time for r in answers if r.response_time is not None]
        rows.append(
            dict(
                participant=sid,
                answers=len(answers),
                questions=header["num_queries"],
                finished=int(len(answers) >= header["num_queries"]),
                first_answer=answers[0].time if answers else "",
                last_answer=answers[-1].time if answers else "",
                median_seconds=round(statistics.median(secs), 3) if secs else "",
                population_version=(header.get("metadata") or {}).get("study_population") or "",
            )  # fmt: skip
        )
    return rows


def population_rows(folder: StudyFolder, X: torch.Tensor, names: list[str]) -> list[dict[str, Any]]:
    """The current population's mean utility and spread (sd) at the items ``X`` (``N x d``, in the
    unit cube the models see), one row per item; empty before the first population."""
    pointer = folder.current()
    if pointer is None:
        return []
    pop = folder.population(pointer["version"], names=names)
    assert pop is not None
    with torch.no_grad():
        post = pop.person_model(X).posterior(X.unsqueeze(-2))
        mean, sd = post.mean.reshape(-1), post.variance.reshape(-1).clamp_min(0).sqrt()
    return [
        {"item": f"#{i + 1}", **{n: float(v) for n, v in zip(names, X[i].tolist())}, "mean": float(m), "sd": float(s)}
        for i, (m, s) in enumerate(zip(mean.tolist(), sd.tolist()))
    ]


def _write(rows: list[dict], path: Path, columns: list[str] | None = None) -> list[Path]:
    columns = columns or (list(rows[0]) if rows else [])
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=columns)
        w.writeheader()
        w.writerows(rows)
    out = [path]
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return out
    table = pa.table({c: [str(r.get(c, "")) for r in rows] for c in columns})
    pq.write_table(table, path.with_suffix(".parquet"))
    return out + [path.with_suffix(".parquet")]


def _pool(folder: StudyFolder, spec: dict) -> torch.Tensor:
    """A header's pool: its items, or for a pool recorded by reference (a large one) the study's
    items, checked against the recorded digest."""
    if "items" in spec:
        return torch.tensor(spec["items"], dtype=torch.float64)
    from torchpref.frontends.serve.items import items_from_csv

    settings = folder.settings()  # a pool by reference is large: a features CSV's, never the lake's
    csv_path = folder.path / "items.csv"
    X = items_from_csv(csv_path, settings.get("id_column"), settings.get("image_column"), settings.get("image_dir")).X
    if X.shape[0] != spec.get("num_items") or pool_digest(X) != spec.get("sha256"):
        raise ValueError(f"the study {folder.path}'s items are not the pool its session files record (digest differs).")
    return X


def study_items(folder: StudyFolder) -> tuple[torch.Tensor, list[str]]:
    """The study's items in the unit cube its models see, and the features' names (from a session
    file's header; the pool's range otherwise)."""
    for _, header, _ in _sessions(folder):
        pool = _pool(folder, header["candidates"])
        lo, hi = torch.tensor(header["bounds"], dtype=torch.float64)
        return (pool - lo) / (hi - lo), list(header.get("names") or [f"x{k + 1}" for k in range(pool.shape[1])])
    raise ValueError(f"the study {folder.path} has no participants yet: nothing to export.")


def export(folder: StudyFolder, out: Path | None = None) -> list[Path]:
    """Write the three tables (module docstring) to ``out`` (default ``DIR/exports``); returns the files."""
    out = out or folder.exports
    out.mkdir(parents=True, exist_ok=True)
    X, names = study_items(folder)
    written = _write(answer_rows(folder), out / "answers.csv", ANSWER_COLUMNS)
    written += _write(participant_rows(folder), out / "participants.csv")
    written += _write(population_rows(folder, X, names), out / "population_utility.csv", ["item", *names, "mean", "sd"])
    return written
