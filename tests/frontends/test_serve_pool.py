"""``torchpref serve``'s sessions as a bounded cache over their files
(:mod:`torchpref.frontends.serve.pool`): closed when idle, finished or over the limit, reopened
with the same answers, next question and posterior; a new participant refused with 503 and
``Retry-After`` (one log line) when descriptors or memory run out, and accepted again after."""

from __future__ import annotations

import errno
import logging
import os
import warnings
from pathlib import Path

import pytest
import torch

pytest.importorskip("starlette", reason="the serve extra (starlette) is not installed")
pytest.importorskip("httpx", reason="starlette's test client needs httpx")

with warnings.catch_warnings():
    warnings.simplefilter("ignore")

from torchpref.frontends.serve.pool import (
    FD_MARGIN,
    MAX_OPEN_CAP,
    PoolLimits,
    ServerBusy,
    default_max_open,
    quiet_resource_errors,
    resource_error,
)
from torchpref.frontends.serve.store import SessionStore
from torchpref.testing.serve import random_items
from torchpref.testing.serve import serve_client as _client


def _items(n=30, d=3, seed=0):
    return random_items(n, d, seed)


class Clock:
    def __init__(self):
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def _answer(c, sid, k):
    st = c.get(f"/s/{sid}/state").json()
    q = st["question"]
    a = 1 + (3 * k) % 5 if q["kind"] == "rating" else k % len(q["options"])
    r = c.post(f"/s/{sid}/answer", json={"qid": st["qid"], "answer": a, "response_time": 0.5})
    assert r.status_code == 200, r.text
    return r.json()


def _journal_fds(path: Path) -> int:
    """How many of this process's descriptors name the file ``path``."""
    n = 0
    for fd in os.listdir("/proc/self/fd"):
        try:
            n += os.readlink(f"/proc/self/fd/{fd}") == str(path)
        except OSError:
            pass
    return n


def _snapshot(store, sid):
    entry = store.entry(sid)
    with entry.lock:
        s = entry.session
        mean, sd = s.predict(store.items.X)
        return store.state(entry), s.records, mean, sd


linux = pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="counts descriptors in /proc/self/fd")


@linux
def test_over_the_limit_the_least_recently_used_closes_and_reopens_the_same(tmp_path):
    store = SessionStore(_items(), tmp_path, num_queries=12, limits=PoolLimits(max_open=2))
    c = _client(store)
    sids = [c.post("/api/new", json={}).json()["sid"] for _ in range(3)]
    for k in range(5):  # three sessions answered in turn through a pool of two
        for sid in sids:
            _answer(c, sid, k)
            assert len(store.sids) <= 2
    assert store.pool.closed >= 10
    first = sids[0]
    assert first not in store.sids and _journal_fds(store.path(first)) == 0  # file released, model dropped
    state, records, mean, sd = _snapshot(store, first)  # reopened from its file and mode snapshot
    for sid in sids[1:]:  # it is closed again
        _snapshot(store, sid)
    assert first not in store.sids
    state2, records2, mean2, sd2 = _snapshot(store, first)
    assert state2 == state and records2 == records
    assert torch.allclose(mean2, mean, rtol=0, atol=1e-9) and torch.allclose(sd2, sd, rtol=0, atol=1e-9)
    # and against a session that was never closed: the same answers told to one that stays open
    ref = SessionStore(_items(), tmp_path / "ref", num_queries=12)
    rc = _client(ref)
    rsid = rc.post("/api/new", json={}).json()["sid"]
    for k in range(5):
        _answer(rc, rsid, k)
    rstate, rrecords, rmean, _ = _snapshot(ref, rsid)
    assert rstate["question"] == state["question"] and [r["answer"] for r in rrecords] == [r["answer"] for r in records]
    assert torch.allclose(rmean, mean, rtol=0, atol=1e-9)
    store.close()
    ref.close()


def test_idle_and_finished_sessions_close_after_their_times(tmp_path):
    store = SessionStore(_items(), tmp_path, num_queries=3, limits=PoolLimits(idle_close=100, finished_close=10))
    clock = store.pool.clock = Clock()
    c = _client(store)
    busy, done = (c.post("/api/new", json={}).json()["sid"] for _ in range(2))
    _answer(c, busy, 0)
    for k in range(3):
        last = _answer(c, done, k)
    assert last["done"] and sorted(store.sids) == sorted([busy, done])
    assert store.plots.summary.wait_idle(300)  # its summary plot, started by the last answer, is drawn
    before = _snapshot(store, busy)
    clock.now += 11
    assert store.pool.sweep() == 1 and store.sids == [busy]  # the finished one, after finished_close
    clock.now += 90
    assert store.pool.sweep() == 1 and store.sids == []  # the idle one, after idle_close
    after = _snapshot(store, busy)  # reopens on the next request: same question, same posterior
    assert after[0] == before[0] and after[1] == before[1]
    assert torch.allclose(after[2], before[2], rtol=0, atol=1e-9)
    assert c.get(f"/s/{done}/state").json()["done"]
    store.close()


def test_a_session_in_a_request_is_never_closed(tmp_path):
    store = SessionStore(_items(), tmp_path, limits=PoolLimits(max_open=1, idle_close=0, finished_close=0))
    sid = store.create()
    entry = store.entry(sid)
    with entry.lock:
        assert store.pool.sweep() == 0 and store.pool.make_room() == 0
        assert entry.is_open
    assert store.pool.sweep() == 1 and not entry.is_open
    with entry.lock:  # a request that still holds the entry reopens it (one session object per file)
        assert entry.session.step == 0 and store.entry(sid) is entry
    store.close()


def test_a_deleted_file_is_not_reopened_as_a_new_session(tmp_path):
    store = SessionStore(_items(), tmp_path, limits=PoolLimits(idle_close=0, finished_close=0))
    c = _client(store)
    sid = c.post("/api/new", json={}).json()["sid"]
    _answer(c, sid, 0)
    store.pool.sweep()
    store.path(sid).unlink()
    assert c.get(f"/s/{sid}/state").status_code == 404 and not store.path(sid).exists()
    store.close()


def test_default_limit_follows_the_descriptor_limit():
    import resource

    assert default_max_open(1024) == (1024 - FD_MARGIN) // 2
    assert default_max_open(100) == (100 - FD_MARGIN) // 2 and default_max_open(20) == 4
    assert default_max_open(10**6) == MAX_OPEN_CAP
    soft = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    expected = MAX_OPEN_CAP if soft == resource.RLIM_INFINITY else default_max_open(soft)
    assert PoolLimits().open_limit() == expected and PoolLimits(max_open=7).open_limit() == 7
    for bad in (dict(max_open=0), dict(max_open=True), dict(idle_close=-1), dict(finished_close=float("nan"))):
        with pytest.raises(ValueError, match=next(iter(bad))):
            PoolLimits(**bad)


def test_out_of_descriptors_a_new_participant_gets_503_and_one_log_line(tmp_path, monkeypatch):
    store = SessionStore(_items(), tmp_path, limits=PoolLimits(retry_after=7))
    lines: list[str] = []
    store.pool._log = lines.append
    c = _client(store)
    old = c.post("/api/new", json={}).json()["sid"]
    monkeypatch.setattr(store.pool, "_shortage", lambda: "file descriptors (1019 of 1024 open)")
    for _ in range(50):
        r = c.post("/api/new", json={})
        assert r.status_code == 503 and r.headers["retry-after"] == "7"
        assert "try again in 7 seconds" in r.json()["error"]
    assert len(lines) == 1 and "out of file descriptors" in lines[0] and "503" in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir() if p.suffix == ".jsonl") == [f"{old}.session.jsonl"]
    _answer(c, old, 0)  # a participant already in goes on
    monkeypatch.undo()
    assert c.post("/api/new", json={}).status_code == 200
    assert len(lines) == 2 and "available again" in lines[1]
    store.close()


def test_a_failed_open_for_want_of_descriptors_is_503_and_leaves_no_file(tmp_path, monkeypatch):
    store = SessionStore(_items(), tmp_path, limits=PoolLimits(idle_close=0, finished_close=0))
    store.pool._log = lambda line: None
    c = _client(store)
    old = c.post("/api/new", json={}).json()["sid"]
    store.pool.sweep()
    real = store._open

    def no_descriptors(sid):
        raise OSError(errno.EMFILE, "Too many open files")

    monkeypatch.setattr(store, "_open", no_descriptors)
    r = c.post("/api/new", json={})
    assert r.status_code == 503 and "retry-after" in r.headers
    assert [p.name for p in tmp_path.glob("*.jsonl")] == [f"{old}.session.jsonl"]
    r = c.get(f"/s/{old}/state")  # reopening a closed session: 503 too (the page retries), not a 500
    assert r.status_code == 503 and "retry-after" in r.headers
    monkeypatch.setattr(store, "_open", real)
    assert c.get(f"/s/{old}/state").status_code == 200 and c.post("/api/new", json={}).status_code == 200
    store.close()


@pytest.mark.parametrize(
    "exc",
    [MemoryError(), RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried to allocate 8 bytes")],
    ids=["MemoryError", "torch"],
)
def test_out_of_memory_in_an_answer_is_503_and_nothing_recorded(tmp_path, monkeypatch, exc):
    store = SessionStore(_items(), tmp_path)
    lines: list[str] = []
    store.pool._log = lines.append
    c = _client(store)
    sid = c.post("/api/new", json={}).json()["sid"]
    st = c.get(f"/s/{sid}/state").json()
    monkeypatch.setattr(type(store.entry(sid).session), "tell", lambda *a, **k: (_ for _ in ()).throw(exc))
    body = {"qid": st["qid"], "answer": 1 if st["question"]["kind"] != "rating" else 3}
    for _ in range(3):
        r = c.post(f"/s/{sid}/answer", json=body)
        assert r.status_code == 503 and "retry-after" in r.headers and "nothing was recorded" in r.json()["error"]
    assert len(lines) == 1 and store.entry(sid).session.step == 0
    monkeypatch.undo()
    assert c.post(f"/s/{sid}/answer", json=body).status_code == 200  # the page's retry goes through
    assert store.entry(sid).session.step == 1
    store.close()


def test_resource_errors_are_recognised_through_their_chain():
    assert resource_error(OSError(errno.EMFILE, "x")) and resource_error(MemoryError())
    try:
        try:
            raise OSError(errno.ENFILE, "table full")
        except OSError:
            raise ValueError("cannot be opened") from None
    except ValueError as wrapped:
        assert resource_error(wrapped)
    assert not resource_error(OSError(errno.ENOENT, "x")) and not resource_error(ValueError("x"))
    assert ServerBusy("busy", 3).status == 503


def test_accept_errors_become_one_log_line(caplog):
    log = logging.getLogger("asyncio")
    with quiet_resource_errors() as flt, caplog.at_level(logging.ERROR, logger="asyncio"):
        for _ in range(1000):
            try:
                raise OSError(errno.EMFILE, "Too many open files")
            except OSError:
                log.error("socket.accept() out of system resource", exc_info=True)
        log.error("something else")
    lines = [r for r in caplog.records if r.name == "asyncio"]
    assert len(lines) == 2 and flt.dropped == 999
    assert "Too many open files" in lines[0].getMessage() and lines[0].exc_info is None
    assert not any(f is flt for f in log.filters)  # removed afterwards


def test_participants_in_parallel_through_a_pool_of_two(tmp_path):
    """Four participants at once, sessions closed after every request (idle 0 s, two open at most)
    and reopened by the next: every answer acknowledged is in its file, in order, nothing twice."""
    import threading

    from torchpref.testing.serve import acknowledged_in_file, records

    store = SessionStore(_items(), tmp_path, num_queries=6, limits=PoolLimits(max_open=2, idle_close=0))
    c = _client(store)
    sids = [c.post("/api/new", json={}).json()["sid"] for _ in range(4)]
    acked: dict[str, list] = {sid: [] for sid in sids}
    errors: list = []

    def participant(sid):
        try:
            for k in range(6):
                st = c.get(f"/s/{sid}/state").json()
                q = st["question"]
                a = 1 + (3 * k) % 5 if q["kind"] == "rating" else k % len(q["options"])
                r = c.post(f"/s/{sid}/answer", json={"qid": st["qid"], "answer": a})
                assert r.status_code == 200, r.text
                acked[sid].append((st["qid"], a))
                store.pool.sweep()
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=participant, args=(sid,)) for sid in sids]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    assert store.pool.closed > 8 and len(store.sids) <= 2 + 4  # closed and reopened many times
    for sid in sids:
        recs = records(store.path(sid))
        assert len(recs) == 6 and acknowledged_in_file(acked[sid], recs) == []
        assert c.get(f"/s/{sid}/state").json()["done"]
    store.close()


def test_the_limit_passed_while_sessions_are_busy_is_restored_by_the_sweep(tmp_path):
    store = SessionStore(_items(), tmp_path, limits=PoolLimits(max_open=1))
    sids = [store.create() for _ in range(3)]
    entries = [store.entry(sid) for sid in sids]
    assert store.sids == [sids[-1]]  # one open: the others were closed to make room
    for e in entries:
        e.lock.acquire()  # three requests at once: none may be closed under them
    closed = store.pool.closed
    for e in entries:
        assert e.session.step == 0  # each (re)opened: the limit of one is passed, all are busy
    assert len(store.sids) == 3 and store.pool.closed == closed
    for e in entries:
        e.lock.release()
    assert store.pool.sweep() == 2 and store.sids == [sids[1]]  # back to the limit: the last reopened kept
    store.close()
