"""Question lists (round 4 of the field): an edited ``"queries"`` list in a session file's header
is refused when the file is opened, naming the question; a question-list file that is a FIFO is
refused without blocking; the file format is the same for elicit and serve."""

from __future__ import annotations

import json
import os
import threading

import pytest
import torch

from torchpref.data.queries import RankingQuery, RatingQuery
from torchpref.sessions.errors import SessionFileError
from torchpref.sessions.query_list import read_question_list
from torchpref.sessions.session import PreferenceSession


def _pool(n=8):
    return torch.rand(n, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)


def _file_with_queries(tmp_path, edit):
    X = _pool()
    path = tmp_path / "s.jsonl"
    qs = [RankingQuery(X[[0, 1, 2]]), RatingQuery(X[3]), RankingQuery(X[[4, 5]])]
    with PreferenceSession(X, queries=qs, session_file=path, num_queries=3) as s:
        q = s.ask()
        s.tell(q, 0 if q.kind == "ranking" else 3)
    lines = path.read_text().splitlines()
    header = json.loads(lines[0])
    header["queries"] = edit(header["queries"])
    path.write_text("\n".join([json.dumps(header), *lines[1:]]) + "\n")
    return path


@pytest.mark.parametrize(
    "edit",
    [
        lambda q: q + [["ranking", 0, 0]],  # the same item twice: a question no answer could take
        lambda q: q + [["ranking", 0, 99]],  # not a pool row
        lambda q: q + [["rating"]],  # no row
        lambda q: q + [["rating", 1, 2]],  # a rating of two items
        lambda q: q + [["ranking", 1]],  # a best-of-one
        lambda q: q + [["bogus", 1, 2]],
        lambda q: q + [["rating", 1.5]],
        lambda q: q + [["rating", True]],
        lambda q: q + ["rating"],
        lambda q: "not a list",
        lambda q: [],
    ],
)
def test_an_edited_question_list_is_refused_at_open(tmp_path, edit):
    path = _file_with_queries(tmp_path, edit)
    with pytest.raises(SessionFileError, match="queries"):
        PreferenceSession.load(path)


def test_an_unedited_question_list_resumes(tmp_path):
    path = _file_with_queries(tmp_path, lambda q: q)
    with PreferenceSession.load(path) as s:
        assert s.step == 1 and s.ask().kind in ("rating", "ranking")


def test_question_list_file_format(tmp_path):
    X = _pool()
    f = tmp_path / "q.txt"
    f.write_text("# a comment\n0, 1, 2\n\n3\n4;5\n")
    qs = read_question_list(f, X)
    assert [q.kind for q in qs] == ["ranking", "rating", "ranking"]
    assert torch.equal(qs[2].items, X[[4, 5]])
    for bad in ("0, 0\n", "0, 99\n", "a, b\n", "# only a comment\n"):
        f.write_text(bad)
        with pytest.raises(SessionFileError):
            read_question_list(f, X)
    with pytest.raises(FileNotFoundError, match="question list"):
        read_question_list(tmp_path / "none.txt", X)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_a_fifo_question_list_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "q.fifo"
    os.mkfifo(fifo)
    result: list = []
    t = threading.Thread(target=lambda: result.append(_refusal(fifo)), daemon=True)
    t.start()
    t.join(10)
    assert not t.is_alive(), "reading a FIFO question list blocked"
    assert result and "FIFO" in result[0]


def _refusal(path):
    try:
        read_question_list(path, _pool())
    except SessionFileError as err:
        return str(err)
    return "accepted"
