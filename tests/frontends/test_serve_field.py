"""``torchpref serve`` as a new user and an attacker met it (issue #34): every refusal is a 4xx
with a message and no traceback (a token outside ASCII, JSON nested deeply, a huge integer, a
full disk, a file changed under the session, a retry of another JSON type), slow clients are
cut off, the page's shown-at and answered-at times reach the journal, and the command line names
the fix for each slip (a busy port and ``--port 0``, ``--features`` for a CSV, an unknown option)."""

from __future__ import annotations

import errno
import json
import socket
import threading
import time
import warnings

import pytest
import torch

pytest.importorskip("starlette", reason="the serve extra (starlette) is not installed")
pytest.importorskip("uvicorn", reason="the serve extra (uvicorn) is not installed")
pytest.importorskip("httpx", reason="starlette's test client needs httpx")

with warnings.catch_warnings():
    warnings.simplefilter("ignore")

import torchpref.sessions.journal as journal
from torchpref.frontends.serve import app as serve_module
from torchpref.frontends.serve.app import ServeError, create_app, listening_socket
from torchpref.frontends.serve.items import ServeItems
from torchpref.frontends.serve.store import SessionStore
from torchpref.testing.serve import random_items as _items
from torchpref.testing.serve import serve_client as _client

TOKEN = "a-long-enough-token-1234"


def _answers(path):
    return [json.loads(line) for line in path.read_text().splitlines()[1:] if '"answer"' in line]


def _good(q):
    return 4 if q["kind"] == "rating" else 1


def test_a_token_outside_ascii_is_a_403_not_a_500(tmp_path):
    store = SessionStore(_items(), tmp_path, num_queries=3)
    t = _client(store, token=TOKEN, allowed_hosts=["*"])
    t.follow_redirects = False
    assert t.get("/?token=%C3%A9").status_code == 403
    assert t.get("/?token=%FF%FE").status_code == 403
    cookie = [(b"cookie", "torchpref_token=\u00e9t\u00e9".encode())]  # UTF-8 bytes, read by the server as Latin-1
    assert t.get("/", headers=cookie).status_code == 403
    assert t.get("/?token=" + TOKEN).status_code == 303  # the right one still works


def test_json_nested_deeply_under_the_size_limit_is_a_400(served):
    store, c, sid = served
    headers = {"content-type": "application/json"}
    deep = "[" * 2000 + "]" * 2000
    assert len(deep) < serve_module.MAX_BODY
    r = c.post(f"/s/{sid}/answer", content=deep, headers=headers)
    assert r.status_code == 400 and "nested too deeply" in r.json()["error"]
    assert c.post("/api/new", content=deep, headers=headers).status_code == 400
    assert store.entry(sid).session.step == 0


def test_a_huge_integer_response_time_is_a_400(served):
    store, c, sid = served
    st = c.get(f"/s/{sid}/state").json()
    huge = "9" * 400
    body = f'{{"qid": "{st["qid"]}", "answer": {_good(st["question"])}, "response_time": {huge}}}'
    r = c.post(f"/s/{sid}/answer", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 400 and "response_time" in r.json()["error"]
    assert _answers(store.path(sid)) == []


def test_a_retry_of_another_json_type_is_refused_not_acknowledged(served):
    store, c, sid = served
    seen = {}
    while len(seen) < 2:  # a rating and a ranking, each answered and then retried with 3.0 / true
        st = c.get(f"/s/{sid}/state").json()
        q = st["question"]
        a = _good(q)
        assert c.post(f"/s/{sid}/answer", json={"qid": st["qid"], "answer": a}).status_code == 200
        n = len(_answers(store.path(sid)))
        for wrong in (float(a), True, str(a)):
            r = c.post(f"/s/{sid}/answer", json={"qid": st["qid"], "answer": wrong})
            assert r.status_code == 400 and "duplicate" not in r.json(), (q["kind"], wrong, r.text)
        r = c.post(f"/s/{sid}/answer", json={"qid": st["qid"], "answer": a})
        assert r.status_code == 200 and r.json()["duplicate"] is True  # the true retry still is
        assert len(_answers(store.path(sid))) == n
        seen[q["kind"]] = True


def test_shown_at_and_answered_at_reach_the_journal(served):
    store, c, sid = served
    st = c.get(f"/s/{sid}/state").json()
    shown = 1_780_000_000_000  # 2026-05-28T20:26:40Z, in ms as the page's Date.now()
    body = {"qid": st["qid"], "answer": _good(st["question"]), "response_time": 2.5}
    for bad, words in (
        ({"shown_at": "yesterday"}, "shown_at"),
        ({"shown_at": True}, "shown_at"),
        ({"answered_at": 1e30}, "answered_at"),
        ({"shown_at": shown, "answered_at": shown - 1}, "before shown_at"),
    ):
        r = c.post(f"/s/{sid}/answer", json={**body, **bad})
        assert r.status_code == 400 and words in r.json()["error"], bad
    r = c.post(f"/s/{sid}/answer", json={**body, "shown_at": shown, "answered_at": shown + 2500})
    assert r.status_code == 200
    (rec,) = _answers(store.path(sid))
    assert rec["shown_at"] == "2026-05-28T20:26:40.000+00:00"
    assert rec["answered_at"] == "2026-05-28T20:26:42.500+00:00" and rec["response_time"] == 2.5


def _disk_full(monkeypatch):
    def full(fd, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(journal, "_write_all", full)


def test_a_full_disk_is_a_507_and_leaves_no_empty_session(tmp_path, monkeypatch):
    store = SessionStore(_items(), tmp_path / "s", num_queries=4)
    c = _client(store)
    _disk_full(monkeypatch)
    r = c.post("/api/new", json={})
    assert r.status_code == 507 and "disk is full" in r.json()["error"] and "Traceback" not in r.text
    assert list((tmp_path / "s").iterdir()) == [] and store.sids == []
    monkeypatch.undo()
    sid = c.post("/api/new", json={}).json()["sid"]
    st = c.get(f"/s/{sid}/state").json()
    _disk_full(monkeypatch)
    r = c.post(f"/s/{sid}/answer", json={"qid": st["qid"], "answer": _good(st["question"])})
    assert r.status_code == 507 and r.headers["retry-after"]
    assert c.post(f"/s/{sid}/undo", json={"qid": st["qid"]}).status_code == 400  # nothing to undo: not written
    monkeypatch.undo()
    r = c.post(f"/s/{sid}/answer", json={"qid": st["qid"], "answer": _good(st["question"])})  # the page's retry
    assert r.status_code == 200 and len(_answers(store.path(sid))) == 1


def test_a_session_file_shortened_under_the_server_is_a_503_naming_it(served):
    store, c, sid = served
    st = c.get(f"/s/{sid}/state").json()
    c.post(f"/s/{sid}/answer", json={"qid": st["qid"], "answer": _good(st["question"])})
    path = store.path(sid)
    with open(path, "r+b") as f:
        f.truncate(path.stat().st_size - 5)
    st = c.get(f"/s/{sid}/state").json()
    r = c.post(f"/s/{sid}/answer", json={"qid": st["qid"], "answer": _good(st["question"])})
    assert r.status_code == 503 and "shortened" in r.json()["error"]
    assert b"\x00" not in path.read_bytes()


def _serve_in_thread(app):
    sock = listening_socket("127.0.0.1", 0)
    ready = threading.Event()
    server = serve_module.uvicorn_server(app, ready.set)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    assert ready.wait(120)
    return server, thread, sock.getsockname()[1]


def test_slow_clients_are_cut_off(tmp_path, monkeypatch):
    import torchpref.frontends.serve.net as serve_net

    monkeypatch.setattr(serve_net, "HEADER_TIMEOUT_S", 0.5)
    monkeypatch.setattr(serve_module, "BODY_TIMEOUT_S", 0.5)
    store = SessionStore(_items(), tmp_path, num_queries=3)
    server, thread, port = _serve_in_thread(create_app(store))
    try:
        silent = socket.create_connection(("127.0.0.1", port), timeout=60)
        trickle = socket.create_connection(("127.0.0.1", port), timeout=60)
        trickle.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # headers never finished
        assert silent.recv(1024) == b"" and trickle.recv(1024) == b""  # closed by the server
        slow = socket.create_connection(("127.0.0.1", port), timeout=60)
        slow.sendall(
            b"POST /api/new HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
            b"Content-Length: 100\r\n\r\n{"
        )  # a body that never arrives
        reply = b""
        while b"did not arrive" not in reply and (chunk := slow.recv(4096)):
            reply += chunk
        assert reply.startswith(b"HTTP/1.1 408") and b"did not arrive" in reply
        for s in (silent, trickle, slow):
            s.close()
        with socket.create_connection(("127.0.0.1", port), timeout=60) as ok:  # the server goes on
            ok.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
            assert ok.recv(64).startswith(b"HTTP/1.1 200")
    finally:
        server.should_exit = True
        thread.join(60)
        store.close()


def test_a_busy_port_is_named_with_port_0(tmp_path, capsys):
    from torchpref.cli import main

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(ServeError, match=rf"port {port} on 127.0.0.1 is in use.*--port 0"):
            listening_socket("127.0.0.1", port)
        csv_path = tmp_path / "items.csv"
        csv_path.write_text("a,b\n0,1\n1,0\n0.5,0.5\n")
        args = ["serve", "--features", str(csv_path), "--sessions", str(tmp_path / "s"), "--port", str(port)]
        started = time.monotonic()
        assert main(args) == 2
        err = capsys.readouterr().err
        assert f"port {port}" in err and "--port 0" in err and "Errno" not in err, err
        assert time.monotonic() - started >= 0  # (no bound on the time: named before the items are read)


@pytest.mark.parametrize(
    "argv, words",
    [
        (["elicit", "ITEMS"], ["not a built-in world", "--features ITEMS"]),
        (["serve", "ITEMS"], ["not a built-in world", "--features ITEMS"]),
        (["serve", "--csv", "ITEMS"], ["unknown option --csv", "--features FILE"]),
        (["elicit", "--csv", "ITEMS"], ["unknown option --csv", "--features FILE"]),
        (["serve", "lake", "--colour", "red"], ["unknown option --colour"]),
        (["elicit", "mars"], ["unknown world 'mars'", "lake"]),
        (["serve", "--features", "ITEMS", "more.csv"], ["unexpected argument 'more.csv'", "--features CSV"]),
    ],
)
def test_command_line_slips_name_the_fix(tmp_path, capsys, argv, words):
    from torchpref.cli import main

    csv_path = tmp_path / "items.csv"
    csv_path.write_text("a,b\n0,1\n1,0\n0.5,0.5\n")
    argv = [str(csv_path) if a == "ITEMS" else a for a in argv]
    words = [w.replace("ITEMS", str(csv_path)) for w in words]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert all(w in err for w in words) and "invalid choice" not in err, err


def test_an_image_column_without_image_column_gets_a_hint(tmp_path, capsys):
    from torchpref.cli import main

    csv_path = tmp_path / "items.csv"
    csv_path.write_text("name,speed,picture\naster,0.2,img/aster.png\nbroom,0.7,img/broom.png\n")
    assert main(["serve", "--features", str(csv_path), "--sessions", str(tmp_path / "s"), "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert "'img/aster.png' is not a finite number" in err and "--image-column picture" in err, err


def test_ratings_on_a_1_to_5_scale_name_likert_to_unit():
    import torchpref

    X = torch.rand(3, 2, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"likert_to_unit\(levels, num_levels=K\)"):
        torchpref.PreferenceGP(X, ratings=[1.0, 5.0, 3.0], rating_index=[0, 1, 2])
    with pytest.raises(ValueError, match=r"must lie in \[0, 1\], got \[-0.5\]\.$"):  # no scale hint below 0
        torchpref.PreferenceGP(X, ratings=[-0.5, 0.5, 0.5], rating_index=[0, 1, 2])


def test_pictures_are_made_ahead_of_the_questions():
    """``serve`` starts drawing every item's picture in the background, so that a question's
    pictures are ready when it is asked (each drawn once)."""
    calls = []
    png = b"\x89PNG\r\n\x1a\n" + b"\x00" * 16

    def render(item, index):
        calls.append(index)
        return png

    items = ServeItems(_items(n=12).X, ["a", "b", "c"], render=render)
    stop = items.prerender_in_background()
    deadline = time.monotonic() + 120
    while len(calls) < 12 and time.monotonic() < deadline:
        time.sleep(0.05)
    stop.set()
    assert sorted(calls) == list(range(12))
    assert items.picture(7) == (png, "image/png") and len(calls) == 12  # from the cache
