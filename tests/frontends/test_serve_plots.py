"""Pictures off the answer path (:mod:`torchpref.frontends.serve.plots`): an answer is
acknowledged while a slow summary plot or item picture is being drawn; summary plots are drawn in
a worker process (the same PNG as drawn here), cached and started when the last question is
answered; a question's pictures are started before the browser asks for them."""

from __future__ import annotations

import threading
import warnings

import pytest

pytest.importorskip("starlette", reason="the serve extra (starlette) is not installed")
pytest.importorskip("httpx", reason="starlette's test client needs httpx")
pytest.importorskip("matplotlib", reason="the plots need matplotlib")

with warnings.catch_warnings():
    warnings.simplefilter("ignore")

from torchpref.frontends.serve.plot_worker import draw_utility
from torchpref.frontends.serve.plots import ProcessDrawer
from torchpref.frontends.serve.store import SessionStore
from torchpref.frontends.serve.summary import utility_data
from torchpref.testing.serve import random_items as _items
from torchpref.testing.serve import serve_client as _client

PNG = b"\x89PNG\r\n\x1a\n" + b"\x00" * 32
WAIT = 300  # seconds: a bound on a deadlock, never reached when the code is right


def _answer(c, sid, k=1):
    st = c.get(f"/s/{sid}/state").json()
    a = 3 if st["question"]["kind"] == "rating" else k % len(st["question"]["options"])
    return c.post(f"/s/{sid}/answer", json={"qid": st["qid"], "answer": a, "response_time": 1.0})


class Slow:
    """A drawing that waits until released (and says when it has started)."""

    def __init__(self, result=b"png"):
        self.started, self.release, self.calls, self.result = threading.Event(), threading.Event(), 0, result

    def __call__(self, *args):
        self.calls += 1
        self.started.set()
        assert self.release.wait(WAIT)
        return self.result


def _in_thread(fn):
    out: list = []
    t = threading.Thread(target=lambda: out.append(fn()), daemon=True)
    t.start()
    return t, out


def test_an_answer_is_acknowledged_while_its_summary_plot_is_drawn(tmp_path):
    store = SessionStore(_items(), tmp_path, num_queries=10)
    slow = store.plots.drawer = Slow()
    c = _client(store)
    sid = c.post("/api/new", json={}).json()["sid"]
    other = c.post("/api/new", json={}).json()["sid"]
    for k in range(3):
        assert _answer(c, sid, k).status_code == 200
    plot, got = _in_thread(lambda: c.get(f"/s/{sid}/utility.png"))
    assert slow.started.wait(WAIT)
    try:
        for s in (sid, other):  # the same session's answer too: the plot holds no lock of it
            t, out = _in_thread(lambda s=s: _answer(c, s))
            t.join(WAIT)
            assert out and out[0].status_code == 200, "the answer waited for the plot"
            assert not slow.release.is_set() and plot.is_alive()  # still drawing
    finally:
        slow.release.set()
    plot.join(WAIT)
    assert got[0].status_code == 200 and got[0].content == b"png"
    store.close()


def test_an_answer_is_acknowledged_while_an_item_picture_is_drawn(tmp_path):
    slow = Slow(PNG)
    store = SessionStore(_items(render=lambda item, i: slow() if i == 0 else PNG), tmp_path)
    c = _client(store)
    sid = c.post("/api/new", json={}).json()["sid"]
    pic, got = _in_thread(lambda: c.get("/picture/0"))
    assert slow.started.wait(WAIT)
    try:
        for k in range(3):
            t, out = _in_thread(lambda k=k: _answer(c, sid, k))
            t.join(WAIT)
            assert out and out[0].status_code == 200, "the answer waited for a picture"
        assert pic.is_alive()
    finally:
        slow.release.set()
    pic.join(WAIT)
    assert got[0].status_code == 200 and got[0].content == PNG
    store.close()


def test_the_worker_process_draws_the_same_png_and_comes_back_after_a_kill(tmp_path):
    import os
    import signal

    store = SessionStore(_items(), tmp_path, num_queries=4)
    c = _client(store)
    sid = c.post("/api/new", json={}).json()["sid"]
    for k in range(2):
        _answer(c, sid, k)
    entry = store.entry(sid)
    with entry.lock:
        data = utility_data(store.items, entry.session, 0, 2)
    drawer = ProcessDrawer()
    try:
        png = drawer(data)
        assert png == draw_utility(data) and png.startswith(b"\x89PNG")
        os.kill(drawer.pid, signal.SIGKILL)
        assert drawer(data) == png and drawer.starts == 2  # restarted for the next plot
    finally:
        drawer.close()
    assert drawer.pid is None
    store.close()


def test_summary_plots_start_at_the_last_answer_and_are_kept(tmp_path):
    store = SessionStore(_items(), tmp_path, num_queries=3)
    calls = []
    store.plots.drawer = lambda data: calls.append(data["step"]) or b"drawn %d" % data["step"]
    c = _client(store)
    sid = c.post("/api/new", json={}).json()["sid"]
    for k in range(3):
        last = _answer(c, sid, k).json()
    assert last["done"] and store.plots.summary.wait_idle(WAIT)
    assert calls == [3]  # drawn before anyone asked
    for _ in range(3):
        r = c.get(f"/s/{sid}/utility.png")
        assert r.status_code == 200 and r.content == b"drawn 3"
    assert calls == [3]  # from the cache
    assert c.get(f"/s/{sid}/utility.png?x=0&y=2").content == b"drawn 3" and calls == [3, 3]  # other axes
    store.close()


def test_a_questions_pictures_are_drawn_before_they_are_asked_for(tmp_path):
    drawn = []
    store = SessionStore(_items(render=lambda item, i: drawn.append(i) or PNG), tmp_path, num_queries=5)
    c = _client(store)
    sid = c.post("/api/new", json={}).json()["sid"]
    for k in range(3):
        st = _answer(c, sid, k).json()
        assert store.plots.pictures.wait_idle(WAIT)
        shown = [o["index"] for o in st["question"]["options"]] + [st["recommended"]["index"]]
        assert set(shown) <= set(drawn)
    n = len(drawn)
    for i in shown:
        assert c.get(f"/picture/{i}").content == PNG
    assert len(drawn) == n  # served from the cache
    store.close()


def test_without_a_worker_process_the_plot_is_drawn_in_its_thread(tmp_path, monkeypatch):
    import torchpref.frontends.serve.plots as plots

    monkeypatch.setattr(plots, "WORKER_SCRIPT", tmp_path / "missing.py")  # the process starts and ends at once
    store = SessionStore(_items(), tmp_path / "s", num_queries=4)
    c = _client(store)
    sid = c.post("/api/new", json={}).json()["sid"]
    _answer(c, sid)
    r = c.get(f"/s/{sid}/utility.png")
    entry = store.entry(sid)
    with entry.lock:
        expected = draw_utility(utility_data(store.items, entry.session, 0, 1))
    assert r.status_code == 200 and r.content == expected and store.plots.fallbacks == 1
    store.close()
