"""A session file changed by another program while a session has it open (issue #34): shortened
in place (same inode: an editor, ``rsync --inplace``), extended, or rewritten with other bytes of
the same length. The session refuses the next answer by name (:class:`SessionFileChanged`), never
pads the file with zeros, and no acknowledged answer is ever moved to ``FILE.dropped``; a second
session on the same file in the same process names ``close()`` and ``with``."""

from __future__ import annotations

import json
import os
import warnings

import pytest
import torch

from torchpref.sessions.errors import SessionFileChanged, SessionFileError
from torchpref.sessions.session import PreferenceSession


def _pool() -> torch.Tensor:
    g = torch.Generator().manual_seed(3)
    return torch.rand(8, 2, generator=g, dtype=torch.float64)


def _answers(path) -> list[dict]:
    lines = path.read_bytes().split(b"\n")
    return [json.loads(line) for line in lines[1:] if line.strip() and b'"answer"' in line]


def _three_answers(path):
    X = _pool()
    s = PreferenceSession(X, session_file=path, seed=0)
    for k in range(3):
        s.tell_rating(X[k], 2 + k, response_time=1.0 + k)
    return s, X


@pytest.mark.parametrize("keep", [-1, -40])  # cut the newline only, or into the last record
def test_a_file_shortened_in_place_is_refused_by_name_and_nothing_acknowledged_is_dropped(tmp_path, keep):
    path = tmp_path / "me.session.jsonl"
    s, X = _three_answers(path)
    size, inode = path.stat().st_size, path.stat().st_ino
    with open(path, "r+b") as f:  # another program truncates the open file in place
        f.truncate(size + keep)
    assert path.stat().st_ino == inode
    with pytest.raises(SessionFileChanged, match=r"shortened from .* bytes"):
        s.tell_rating(X[4], 5, response_time=9.0)
    with pytest.raises(SessionFileChanged):
        s.undo()
    assert b"\x00" not in path.read_bytes()  # never padded with zeros
    assert path.stat().st_size == size + keep  # nothing written after the change
    assert s.step == 3 and [r["answer"] for r in s.records] == [2, 3, 4]  # the acknowledged answers, in memory
    s.close()
    # reopening with repair (as serve does) cannot move the refused answer: it was never written
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        again = PreferenceSession(_pool(), session_file=path, seed=0, repair=True)
    dropped = path.with_name(path.name + ".dropped")
    assert b'"response_time":9.0' not in (dropped.read_bytes() if dropped.exists() else b"")
    assert all(r["response_time"] != 9.0 for r in _answers(path))
    again.close()


def test_a_file_rewritten_in_place_with_the_same_length_is_refused(tmp_path):
    path = tmp_path / "me.session.jsonl"
    s, X = _three_answers(path)
    data = path.read_bytes()
    changed = data.replace(b'"answer":3', b'"answer":1', 1)
    assert changed != data and len(changed) == len(data)
    with open(path, "r+b") as f:  # same inode, same size, other bytes
        f.write(changed)
    with pytest.raises(SessionFileChanged, match="rewritten in place"):
        s.tell_rating(X[4], 5)
    assert path.read_bytes() == changed
    s.close()


def test_a_file_extended_by_another_program_is_refused_and_kept(tmp_path):
    path = tmp_path / "me.session.jsonl"
    s, X = _three_answers(path)
    with open(path, "ab") as f:
        f.write(b'{"type":"note"}\n')
    before = path.read_bytes()
    with pytest.raises(SessionFileChanged, match="extended"):
        s.tell_rating(X[4], 5)
    assert path.read_bytes() == before  # their bytes are not cut away either
    s.close()


def test_a_file_only_touched_goes_on(tmp_path):
    path = tmp_path / "me.session.jsonl"
    s, X = _three_answers(path)
    os.utime(path, ns=(1, 1))  # times changed, bytes not
    os.chmod(path, 0o644)
    s.tell_rating(X[4], 5, response_time=4.0)
    assert [r["response_time"] for r in _answers(path)] == [1.0, 2.0, 3.0, 4.0]
    s.close()


def test_the_same_file_opened_twice_in_one_process_names_close(tmp_path):
    path = tmp_path / "me.session.jsonl"
    first = PreferenceSession(_pool(), session_file=path)
    with pytest.raises(SessionFileError, match=r"already open in this process.*close\(\).*with PreferenceSession"):
        PreferenceSession(_pool(), session_file=path)
    first.close()
    with PreferenceSession(_pool(), session_file=path) as second:  # once closed, it opens
        assert second.step == 0
