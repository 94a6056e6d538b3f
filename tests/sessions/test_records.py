"""Typed session records: AnswerRecord / UndoRecord read every committed journal line and write it back
unchanged, check what the file reader checks, and an invalid answer is one InvalidAnswer."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

import torchpref
from torchpref.data.queries import InvalidAnswer, RankingQuery, RatingQuery
from torchpref.sessions import PreferenceSession
from torchpref.sessions.errors import SessionFileError
from torchpref.sessions.records import AnswerRecord, UndoRecord, parse_record

FIXTURE = Path(__file__).parents[1] / "fixtures" / "session_v1_defaults.jsonl"


def _lines() -> tuple[dict, list[dict]]:
    header, *records = [json.loads(line) for line in FIXTURE.read_text().splitlines()]
    return header, records


def test_every_record_of_a_journal_of_the_previous_release_reads_and_round_trips():
    header, records = _lines()
    assert records
    for i, rec in enumerate(records, start=2):
        typed = (
            AnswerRecord.from_json(rec, header, f"line {i}")
            if rec["type"] == "answer"
            else UndoRecord.from_json(rec, f"line {i}")
        )
        # written before response_time existed: read as None, and written back with the key
        filled = {**rec, "response_time": rec.get("response_time")} if rec["type"] == "answer" else rec
        assert typed.to_json() == filled
        assert parse_record(typed.to_json()) == typed == parse_record(rec)


def test_a_session_writes_what_the_typed_records_write(tmp_path):
    X = torch.rand(8, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    s = PreferenceSession(X, session_file=tmp_path / "s.jsonl", seed=1, num_queries=4, num_levels=5)
    s.tell(RatingQuery(X[0]), 4, response_time=1.5)
    s.tell(RankingQuery(X[1:4]), 2)
    s.tell(RankingQuery(X[4:6]), None)
    s.undo()
    lines = [json.loads(line) for line in (tmp_path / "s.jsonl").read_text().splitlines()]
    header, records = lines[0], lines[1:]
    kinds = [(r["type"], r.get("kind")) for r in records]
    assert kinds == [("answer", "rating"), ("answer", "choice"), ("answer", "no_preference"), ("undo", None)]
    rating = AnswerRecord.from_json(records[0], header)
    expected = float(torchpref.likert_to_unit(torch.tensor(4), 5))
    assert (rating.answer, rating.value, rating.response_time) == (4, expected, 1.5)
    assert AnswerRecord.from_json(records[1], header).answer == 2
    assert UndoRecord.from_json(records[3]).undoes == records[2]["seq"]
    for rec in records:
        assert parse_record(rec).to_json() == rec


@pytest.mark.parametrize(
    "field, value, words",
    [
        ("answer", 6, "'answer' must be an integer in 1..5"),
        ("kind", "vote", "unknown answer kind"),
        ("time", 3, "'time'"),
    ],
)
def test_from_json_checks_as_the_file_reader_does(field, value, words):
    header, records = _lines()
    rating = next(r for r in records if r["type"] == "answer" and r["kind"] == "rating")
    with pytest.raises(SessionFileError, match=words):
        AnswerRecord.from_json({**rating, field: value}, header, "line 9")


def test_an_undo_needs_its_target_and_a_time():
    with pytest.raises(SessionFileError, match="'undoes'"):
        UndoRecord.from_json({"type": "undo", "seq": 3, "time": "t"})
    with pytest.raises(SessionFileError, match="not an undo record"):
        UndoRecord.from_json({"type": "answer", "seq": 3})


def test_invalid_answers_are_one_error_and_record_nothing():
    X = torch.rand(6, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    s = PreferenceSession(X, seed=0, num_queries=3)
    for query, answer in (
        (RatingQuery(X[0]), 1.5),
        (RatingQuery(X[0]), "0.5"),
        (RatingQuery(X[0]), True),
        (RankingQuery(X[:3]), 3),
        (RankingQuery(X[:3]), 1.0),
        (RankingQuery(X[:3]), [0, 1]),  # "equally best" is not a session answer
    ):
        with pytest.raises(InvalidAnswer) as err:
            s.tell(query, answer)
        assert isinstance(err.value, ValueError) and repr(answer)[:3] in str(err.value)
    assert s.records == [] and s.model.data.num_observations == 0
    assert torchpref.InvalidAnswer is InvalidAnswer


def test_the_session_errors_stay_importable_from_their_old_modules():
    import torchpref.sessions as package
    from torchpref.sessions import errors, journal, recorded, records, session

    for name in errors.__all__:
        assert getattr(package, name) is getattr(errors, name)
        assert getattr(session, name) is getattr(errors, name)  # every error, as before
    for module, names in (
        (records, ("SessionFileError", "SessionFileCorrupt", "SessionVersionError", "SessionMismatchError")),
        (journal, ("SessionFileGone", "SessionFileChanged", "SessionForkError", "SessionReadOnlyError")),
        (recorded, ("SessionSettingsError",)),
    ):
        for name in names:
            assert getattr(module, name) is getattr(errors, name)
