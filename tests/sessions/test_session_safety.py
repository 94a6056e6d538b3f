"""Sessions under threads, forks, vanished files, failed rollbacks and odd paths (issue #22)."""

import errno
import os
import signal
import threading
import time
import warnings

import pytest
import torch

import torchpref.sessions.journal as journal
from torchpref.sessions.errors import (
    SessionFileError,
    SessionFileGone,
    SessionForkError,
    SessionReadOnlyError,
    SessionRepairWarning,
)
from torchpref.sessions.session import PreferenceSession, read_session_file

SCALE = torch.tensor([100.0, 5.0], dtype=torch.float64)


def pool(n: int = 8, seed: int = 4) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 2, generator=g, dtype=torch.float64) * SCALE


def check_file(path, acknowledged: list[float]) -> list[dict]:
    """The file opens, its sequence numbers are 1, 2, ... and every acknowledged answer (named by
    its response time) is in it exactly once."""
    _, records, _ = read_session_file(path)
    assert [r["seq"] for r in records] == list(range(1, len(records) + 1))
    stamps = sorted(r["response_time"] for r in records if r["type"] == "answer")
    assert stamps == sorted(acknowledged)
    return records


@pytest.mark.parametrize("per_thread", [25, pytest.param(200, marks=pytest.mark.slow)])
def test_eight_threads_answering_one_session_lose_and_duplicate_nothing(tmp_path, per_thread):
    X = pool()
    path = tmp_path / "s.jsonl"
    s = PreferenceSession(X, session_file=path, seed=1)
    acked, errors = [], []

    def worker(t: int) -> None:
        g = torch.Generator().manual_seed(t)
        try:
            for i in range(per_thread):
                stamp = float(t * 1000 + i)
                if i % 3:
                    s.tell_rating(X[int(torch.randint(8, (1,), generator=g))], 1 + i % 5, response_time=stamp)
                else:
                    rows = torch.randperm(8, generator=g)[:3]
                    s.tell_choice(X[rows], i % 3, response_time=stamp)
                acked.append(stamp)
        except BaseException as err:  # pragma: no cover - reported below
            errors.append(err)

    threads = [threading.Thread(target=worker, args=(t,)) for t in range(8)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(timeout=600)
    assert not errors and not any(th.is_alive() for th in threads)
    assert len(acked) == 8 * per_thread == s.step
    live = s.predict(X)
    s.close()
    check_file(path, acked)
    with PreferenceSession.load(path) as r:  # the model held every answer: the file's posterior
        torch.testing.assert_close(r.predict(X), live, rtol=0, atol=1e-10)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")
def test_a_forked_child_cannot_write_to_its_parents_session(tmp_path):
    X = pool()
    path = tmp_path / "s.jsonl"
    s = PreferenceSession(X, session_file=path, seed=1)
    s.tell_rating(X[0], 3, response_time=1.0)
    read_fd, write_fd = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: answer, undo, open the file again; report what happened
        code = 0
        try:
            for attempt in (lambda: s.tell_rating(X[1], 4, response_time=2.0), s.undo):
                try:
                    attempt()
                    code |= 1
                except SessionForkError:
                    pass
            # (no torch work in the child: an OpenMP thread pool inherited through fork can hang it)
        except BaseException:
            code |= 8
        os.write(write_fd, bytes([code]))
        os._exit(0)
    os.close(write_fd)
    deadline = time.monotonic() + 120
    while os.waitpid(pid, os.WNOHANG) == (0, 0):
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            pytest.fail("the forked child did not finish")
        time.sleep(0.05)
    code = os.read(read_fd, 1)
    os.close(read_fd)
    assert code == b"\x00"  # refused both writes by name, and the file is still the parent's
    s.tell_rating(X[2], 5, response_time=3.0)  # the parent goes on
    s.close()
    check_file(path, [1.0, 3.0])


@pytest.mark.parametrize("how", ["deleted", "moved", "replaced"])
def test_a_file_gone_from_under_the_session_is_detected_before_acknowledging(tmp_path, how):
    X = pool()
    path = tmp_path / "s.jsonl"
    s = PreferenceSession(X, session_file=path, seed=1)
    s.tell_rating(X[0], 3)
    before = s.predict(X)
    if how == "deleted":
        path.unlink()
    elif how == "moved":
        path.rename(tmp_path / "elsewhere.jsonl")
    else:
        other = tmp_path / "other.jsonl"
        other.write_bytes(b"")
        os.replace(other, path)
    with pytest.raises(SessionFileGone, match="was not saved"):
        s.tell_rating(X[1], 4)
    with pytest.raises(SessionFileGone):
        s.undo()
    assert s.step == 1
    torch.testing.assert_close(s.predict(X), before, rtol=0, atol=0)
    s.close()


def test_a_failed_rollback_then_more_answers_leaves_a_file_that_opens(tmp_path, monkeypatch):
    X = pool()
    path = tmp_path / "s.jsonl"
    s = PreferenceSession(X, session_file=path, seed=1)
    s.tell_rating(X[0], 3, response_time=1.0)
    real_write, real_truncate = journal._write_all, journal.os.ftruncate
    failures = {"truncate": 2}

    def half_then_fail(fd, data):
        real_write(fd, data[: len(data) // 2])
        raise OSError(errno.EIO, "Input/output error")

    def flaky_truncate(fd, size):
        if failures["truncate"] > 0:
            failures["truncate"] -= 1
            raise (KeyboardInterrupt() if failures["truncate"] else OSError(errno.EIO, "Input/output error"))
        real_truncate(fd, size)

    monkeypatch.setattr(journal, "_write_all", half_then_fail)
    monkeypatch.setattr(journal.os, "ftruncate", flaky_truncate)
    with pytest.raises(OSError):
        s.tell_rating(X[1], 4, response_time=2.0)  # the write fails, and so does its rollback (Ctrl-C, then EIO)
    assert not path.read_bytes().endswith(b"\n")  # half a record left behind
    monkeypatch.setattr(journal, "_write_all", real_write)
    s.tell_rating(X[2], 5, response_time=3.0)  # healed first: the half record is cut, then this one appended
    s.close()
    check_file(path, [1.0, 3.0])


def test_a_failed_header_write_leaves_no_half_header(tmp_path, monkeypatch):
    X = pool()
    path = tmp_path / "s.jsonl"
    real_write = journal._write_all

    def disk_full(fd, data):
        real_write(fd, data[:40])
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(journal, "_write_all", disk_full)
    with pytest.raises(OSError, match="No space"):
        PreferenceSession(X, session_file=path)
    assert path.read_bytes() == b""  # rolled back
    monkeypatch.undo()
    path.write_bytes(b'{"type":"header","version":1,"dim":2,"cre')  # a half header (rollback failed too)
    with pytest.warns(SessionRepairWarning, match="incomplete header"):
        s = PreferenceSession(X, session_file=path)
    s.tell_rating(X[0], 2)
    s.close()
    assert len(read_session_file(path)[1]) == 1


def test_devices_fifos_and_huge_files_are_refused_without_reading(tmp_path, monkeypatch):
    X = pool()
    with pytest.raises(SessionFileError, match="character device"):
        PreferenceSession(X, session_file="/dev/zero")
    with pytest.raises(SessionFileError, match="character device"):
        PreferenceSession.load("/dev/zero")
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    with pytest.raises(SessionFileError, match="FIFO"):  # without blocking on the open
        PreferenceSession(X, session_file=fifo)
    big = tmp_path / "big.jsonl"
    PreferenceSession(X, session_file=big).close()
    monkeypatch.setattr(journal, "MAX_FILE_BYTES", 100)
    with pytest.raises(SessionFileError, match="more than a session file may be"):
        PreferenceSession.load(big)


def test_long_and_non_utf8_file_names_work_or_are_named(tmp_path):
    X = pool()
    with pytest.raises(SessionFileError, match="too long"):
        PreferenceSession(X, session_file=tmp_path / ("a" * 250 + ".jsonl"))
    for name in ("b" * 249 + ".jsonl", os.fsdecode(b"caf\xe9-\xff.jsonl")):  # 255 bytes; not UTF-8
        path = tmp_path / name
        try:
            s = PreferenceSession(X, session_file=path)
        except OSError as err:  # a file system that refuses such names: nothing to test here
            pytest.skip(f"the file system refuses {name!r}: {err}")
        s.tell_rating(X[0], 3)
        s.tell_rating(X[1], 4)
        s.close()
        path.write_bytes(path.read_bytes()[:-20])  # a torn last answer
        with pytest.warns(SessionRepairWarning, match="incomplete line 3"):
            r = PreferenceSession.load(path, repair=True)
        assert r.step == 1
        r.tell_rating(X[2], 5)
        r.close()


def test_a_file_this_process_may_not_write_opens_read_only(tmp_path, monkeypatch):
    X = pool()
    path = tmp_path / "s.jsonl"
    with PreferenceSession(X, session_file=path) as s:
        s.tell_rating(X[0], 3)
        live = s.predict(X)
    real_open = journal._open

    def denied(p, flags):  # as a read-only directory and file (root would not see it)
        if flags & os.O_RDWR:
            raise PermissionError(errno.EACCES, "Permission denied", str(p))
        return real_open(p, flags)

    monkeypatch.setattr(journal, "_open", denied)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = PreferenceSession.load(path)
    assert r.read_only and r.step == 1
    torch.testing.assert_close(r.predict(X), live, rtol=0, atol=1e-12)
    with pytest.raises(SessionReadOnlyError, match="read-only"):
        r.tell_rating(X[1], 4)
    with pytest.raises(SessionReadOnlyError):
        r.undo()
    assert r.step == 1
    r.close()
