"""``torchpref serve`` over HTTP (Starlette's test client, no browser): the answer protocol
(acknowledged only once in the file, repeats, stale and foreign questions), validation of every
browser input, response times in the journal and the CSV, resuming, the summary and downloads,
and the safety rules (Host check, token, images only from their folder, other interfaces only
when allowed)."""

from __future__ import annotations

import csv
import io
import json
import os
import threading
import warnings

import pytest
import torch

pytest.importorskip("starlette", reason="the serve extra (starlette) is not installed")
pytest.importorskip("jinja2", reason="the serve extra (jinja2) is not installed")
pytest.importorskip("httpx", reason="starlette's test client needs httpx")

with warnings.catch_warnings():  # starlette's note that a later httpx is preferred
    warnings.simplefilter("ignore")

from torchpref.data.features import FeaturesError
from torchpref.frontends.serve.app import ServeError, _check_network
from torchpref.frontends.serve.items import items_from_csv
from torchpref.frontends.serve.store import SessionStore, make_qid
from torchpref.sessions.session import PreferenceSession
from torchpref.testing.serve import random_items as _items
from torchpref.testing.serve import serve_client as _client

PNG = b"\x89PNG\r\n\x1a\n" + b"\x00" * 32


def _answer_for(q):
    return 4 if q["kind"] == "rating" else 1


def _answers(path):
    return [json.loads(line) for line in path.read_text().splitlines()[1:] if '"answer"' in line]


def test_answers_recorded_with_response_times_then_summary(served):
    store, c, sid = served
    page = c.get(f"/s/{sid}/")
    assert page.status_code == 200 and "serve.js" in page.text
    assert "default-src 'self'" in page.headers["content-security-policy"]
    kinds, times = [], []
    for k in range(8):
        st = c.get(f"/s/{sid}/state").json()
        assert st["answered"] == k and not st["done"]
        q = st["question"]
        kinds.append(q["kind"])
        times.append(0.5 + k)
        r = c.post(f"/s/{sid}/answer", json={"qid": st["qid"], "answer": _answer_for(q), "response_time": 0.5 + k})
        assert r.status_code == 200, r.text
        timing = dict(part.strip().split(";dur=") for part in r.headers["server-timing"].split(","))
        assert float(timing["answer"]) > 0 and float(timing["cpu"]) >= 0
        assert r.json()["answered"] == k + 1 and r.json()["recommended"]["label"].startswith("#")
    done = c.get(f"/s/{sid}/state").json()
    assert done["done"] and done["question"] is None
    r = c.post(f"/s/{sid}/answer", json={"qid": done["qid"], "answer": 1})
    assert r.status_code == 409 and "all 8 questions are answered" in r.json()["error"]
    assert set(kinds) == {"rating", "ranking"}  # UCBC asks both kinds
    recs = _answers(store.path(sid))
    assert [r["response_time"] for r in recs] == times
    assert [r["query"]["step"] for r in recs] == list(range(8))
    rows = list(csv.DictReader(io.StringIO(c.get(f"/s/{sid}/download/answers.csv").text)))
    assert [float(r["response_time"]) for r in rows] == times
    assert all(r["in_force"] == "1" for r in rows)
    assert store.entry(sid).session.history[3].response_time == times[3]
    summary = c.get(f"/s/{sid}/summary?x=2&y=1")
    assert summary.status_code == 200 and summary.text.count("<tr>") == 6  # header + top 5
    assert 'id="median-seconds">4.5<' in summary.text  # the median of 0.5 .. 7.5 s (upper of the middle two)
    png = c.get(f"/s/{sid}/utility.png?x=2&y=1")
    assert png.headers["content-type"] == "image/png" and png.content.startswith(b"\x89PNG")
    assert c.get(f"/s/{sid}/utility.png?x=7").status_code == 400
    jsonl = c.get(f"/s/{sid}/download/session.jsonl")
    assert jsonl.content == store.path(sid).read_bytes()
    assert "attachment" in jsonl.headers["content-disposition"]


def test_session_file_replays_to_the_same_model_and_checkpoint_loads(served, tmp_path):
    import torchpref

    store, c, sid = served
    for _ in range(6):
        st = c.get(f"/s/{sid}/state").json()
        c.post(f"/s/{sid}/answer", json={"qid": st["qid"], "answer": _answer_for(st["question"])})
    live = store.entry(sid).session
    X = store.items.X
    mean, std = live.predict(X)
    ckpt = tmp_path / "model.pt"
    ckpt.write_bytes(c.get(f"/s/{sid}/download/model.pt").content)
    loaded = torchpref.load_model(ckpt)
    with torch.no_grad():
        assert torch.allclose(loaded.posterior(live.transform(X).unsqueeze(-2)).mean.reshape(-1), mean, atol=1e-10)
    copy = tmp_path / "copy.session.jsonl"
    copy.write_bytes(store.path(sid).read_bytes())
    with PreferenceSession.load(copy) as again:
        m2, s2 = again.predict(X)
    # a replay equals the live, incremental session to round-off (docs/sessions.md)
    assert torch.allclose(m2, mean, atol=1e-9) and torch.allclose(s2, std, atol=1e-9)


def test_repeat_is_acknowledged_once_stale_and_foreign_refused(served):
    store, c, sid = served
    other = c.post("/api/new", json={}).json()["sid"]
    st = c.get(f"/s/{sid}/state").json()
    body = {"qid": st["qid"], "answer": _answer_for(st["question"]), "response_time": 2.0}
    assert c.post(f"/s/{sid}/answer", json=body).status_code == 200
    again = c.post(f"/s/{sid}/answer", json=body)  # a retry after a lost reply
    assert again.status_code == 200 and again.json()["duplicate"] is True
    assert len(_answers(store.path(sid))) == 1
    changed = dict(body, answer=0 if body["answer"] != 0 else 1)
    r = c.post(f"/s/{sid}/answer", json=changed)  # the same question, answered differently
    assert r.status_code == 409 and "already answered" in r.json()["error"] and r.json()["state"]["answered"] == 1
    # another session's current question (same position in its file): refused, nothing recorded
    st_other = c.get(f"/s/{other}/state").json()
    st_now = c.get(f"/s/{sid}/state").json()
    foreign = {"qid": st_other["qid"], "answer": _answer_for(st_other["question"])}
    assert c.post(f"/s/{sid}/answer", json=foreign).status_code == 409
    forged = {"qid": make_qid(other, 1, None), "answer": 1}
    assert c.post(f"/s/{sid}/answer", json=forged).status_code == 409
    # an older question after undo + new answer
    assert c.post(f"/s/{sid}/undo", json={"qid": st_now["qid"]}).status_code == 200
    assert c.post(f"/s/{sid}/undo", json={"qid": st_now["qid"]}).status_code == 409  # double click: stale
    assert c.post(f"/s/{sid}/answer", json=body).status_code == 409  # answered, then undone: stale
    recs = store.entry(sid).session.records
    assert [r["type"] for r in recs] == ["answer", "undo"]
    assert _answers(store.path(other)) == []


@pytest.mark.parametrize(
    "body, status, words",
    [
        ({"qid": "Q", "answer": "3"}, 400, "must be"),
        ({"qid": "Q", "answer": True}, 400, "must be"),
        ({"qid": "Q", "answer": 2.5}, 400, "must be"),
        ({"qid": "Q", "answer": 99}, 400, "must be"),
        ({"qid": "Q", "answer": -1}, 400, "must be"),
        ({"qid": "Q", "answer": 1, "response_time": -1}, 400, "response_time"),
        ({"qid": "Q", "answer": 1, "response_time": "1"}, 400, "response_time"),
        ({"qid": "Q", "answer": 1, "response_time": 1e9}, 400, "response_time"),
        ({"qid": "Q", "answer": 1, "extra": 1}, 400, "unknown field"),
        ({"answer": 1}, 400, "qid"),
        ([1, 2], 400, "JSON object"),
    ],
)
def test_invalid_answers_are_refused_and_nothing_recorded(served, body, status, words):
    store, c, sid = served
    st = c.get(f"/s/{sid}/state").json()
    if isinstance(body, dict) and body.get("qid") == "Q":
        body = dict(body, qid=st["qid"])
    r = c.post(f"/s/{sid}/answer", json=body)
    assert r.status_code == status and words in r.json()["error"], r.text
    assert _answers(store.path(sid)) == [] and store.entry(sid).session.step == 0
    assert c.get(f"/s/{sid}/state").json()["qid"] == st["qid"]  # the same question is still asked


def test_malformed_requests(served):
    store, c, sid = served
    qid = c.get(f"/s/{sid}/state").json()["qid"]
    good = json.dumps({"qid": qid, "answer": 1})
    assert c.post(f"/s/{sid}/answer", content=good, headers={"content-type": "text/plain"}).status_code == 415
    headers = {"content-type": "application/json"}
    assert c.post(f"/s/{sid}/answer", content="{nope", headers=headers).status_code == 400
    inf = good.replace("}", ', "response_time": 1e999}')  # JSON's overflow to infinity
    assert c.post(f"/s/{sid}/answer", content=inf, headers=headers).status_code == 400
    assert c.post(f"/s/{sid}/answer", content=good.replace("1}", "NaN}"), headers=headers).status_code == 400
    big = json.dumps({"qid": qid, "answer": 1, "pad": "x" * 5000})
    assert c.post(f"/s/{sid}/answer", content=big, headers=headers).status_code == 413
    cross = dict(headers, origin="http://evil.example")
    assert c.post(f"/s/{sid}/answer", content=good, headers=cross).status_code == 403
    assert c.post("/api/new", content="{}", headers=cross).status_code == 403
    assert c.get("/s/../etc/state").status_code == 404
    assert c.get("/s/no.such/state").status_code == 404
    assert c.get("/s/nosuchsession/state").status_code == 404
    assert c.post("/s/nosuchsession/answer", content=good, headers=headers).status_code == 404
    assert c.get(f"/s/{sid}/download/other.txt").status_code == 404
    assert store.entry(sid).session.step == 0 and len(store.sids) == 1


def test_ties_and_levels_follow_the_settings(tmp_path):
    from torchpref.selection.strategies import UCBC

    store = SessionStore(_items(), tmp_path, num_queries=4, ties=False, selector=UCBC(m=5))  # a ranking first
    c = _client(store)
    sid = c.post("/api/new", json={}).json()["sid"]
    st = c.get(f"/s/{sid}/state").json()
    assert st["question"]["kind"] == "ranking" and st["question"]["ties"] is False
    r = c.post(f"/s/{sid}/answer", json={"qid": st["qid"], "answer": None})
    assert r.status_code == 400 and "no preference" in r.json()["error"]
    store2 = SessionStore(_items(), tmp_path / "t", num_queries=4, selector=UCBC(m=5))
    c2 = _client(store2)
    sid2 = c2.post("/api/new", json={}).json()["sid"]
    st = c2.get(f"/s/{sid2}/state").json()
    assert c2.post(f"/s/{sid2}/answer", json={"qid": st["qid"], "answer": None}).status_code == 200
    assert _answers(store2.path(sid2))[0]["kind"] == "no_preference"


def test_restarted_store_resumes_the_same_question(tmp_path):
    store = SessionStore(_items(), tmp_path, num_queries=6)
    c = _client(store)
    sid = c.post("/api/new", json={}).json()["sid"]
    for _ in range(3):
        st = c.get(f"/s/{sid}/state").json()
        c.post(f"/s/{sid}/answer", json={"qid": st["qid"], "answer": _answer_for(st["question"])})
    st = c.get(f"/s/{sid}/state").json()
    store.close()
    # a half-written last line, as a kill in the middle of a write leaves it: never acknowledged
    with open(store.path(sid), "ab") as f:
        f.write(b'{"type":"answer","v":1,"seq":4,"ti')
    store2 = SessionStore(_items(), tmp_path, num_queries=6)
    c2 = _client(store2)
    again = c2.get(f"/s/{sid}/state").json()
    assert again == st
    assert (tmp_path / f"{sid}.session.jsonl.dropped").exists()
    # a file made for other items is refused, not overwritten
    store3 = SessionStore(_items(seed=1), tmp_path, num_queries=6)
    r = _client(store3).get(f"/s/{sid}/state")
    assert r.status_code == 409 and "cannot be opened" in r.json()["error"]
    store2.close()


def test_sessions_in_parallel_threads(tmp_path):
    store = SessionStore(_items(), tmp_path, num_queries=5)
    c = _client(store)
    sids = [c.post("/api/new", json={}).json()["sid"] for _ in range(3)]
    errors = []

    def answer_all(sid):
        try:
            for _ in range(5):
                st = c.get(f"/s/{sid}/state").json()
                r = c.post(f"/s/{sid}/answer", json={"qid": st["qid"], "answer": _answer_for(st["question"])})
                assert r.status_code == 200, r.text
        except Exception as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=answer_all, args=(s,)) for s in sids]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=300)
    assert not errors and not any(t.is_alive() for t in threads)
    for sid in sids:
        assert [r["seq"] for r in _answers(store.path(sid))] == [1, 2, 3, 4, 5]


def test_host_check_and_token(tmp_path):
    store = SessionStore(_items(), tmp_path, num_queries=3)
    c = _client(store)
    assert c.get("/", headers={"host": "attacker.example:8000"}).status_code == 421  # DNS rebinding
    assert c.get("/", headers={"host": "localhost:8000"}).status_code == 200
    token = "a-long-enough-token-1234"
    t = _client(store, token=token, allowed_hosts=["*"])
    t.follow_redirects = False
    assert t.get("/").status_code == 403
    assert t.get("/?token=wrong").status_code == 403
    r = t.get("/?token=" + token)
    assert r.status_code == 303 and r.headers["location"] == "/" and "httponly" in r.headers["set-cookie"].lower()
    assert t.get("/").status_code == 200  # the cookie from now on
    assert t.post("/api/new", json={}).status_code == 200


def test_network_settings():
    assert _check_network("127.0.0.1", 8000, False, None) is None
    assert _check_network("::1", 0, False, "x" * 20) == "x" * 20
    with pytest.raises(ServeError, match="allow_remote"):
        _check_network("0.0.0.0", 8000, False, None)
    made = _check_network("0.0.0.0", 8000, True, None)
    assert isinstance(made, str) and len(made) >= 16
    with pytest.raises(ServeError, match="16 characters"):
        _check_network("0.0.0.0", 8000, True, "short")
    with pytest.raises(ServeError, match="port"):
        _check_network("127.0.0.1", 70000, False, None)


def _image_csv(tmp_path, names):
    folder = tmp_path / "images"
    folder.mkdir(exist_ok=True)
    lines = ["name,speed,cost,picture"]
    for k, n in enumerate(names):
        lines.append(f"item {k},{k * 0.3 % 1:.2f},{k * 0.7 % 1:.2f},{n}")
    path = tmp_path / "items.csv"
    path.write_text("\n".join(lines) + "\n")
    return path, folder


def test_images_only_from_their_folder(tmp_path):
    path, folder = _image_csv(tmp_path, ["a.png", "b.png", "sub/c.png"])
    (folder / "sub").mkdir()
    for n in ("a.png", "b.png", "sub/c.png"):
        (folder / n).write_bytes(PNG + n.encode())
    items = items_from_csv(path, image_column="picture", image_dir=folder)
    assert items.names == ["speed", "cost"] and items.labels == ["item 0", "item 1", "item 2"]
    c = _client(SessionStore(items, tmp_path / "s", num_queries=2))
    r = c.get("/picture/2")
    assert r.status_code == 200 and r.content == PNG + b"sub/c.png" and r.headers["content-type"] == "image/png"
    for bad in ("/picture/3", "/picture/-1", "/picture/x", "/picture/..%2Fitems.csv", "/static/..%2Fserve.py"):
        assert c.get(bad).status_code == 404, bad
    secret = tmp_path / "secret.png"
    secret.write_bytes(PNG)
    for name, words in (
        ("../secret.png", "not a file inside"),
        (str(secret), "not a file inside"),
        ("missing.png", "no image file"),
        ("notes.txt", "not a .png"),
        ("", "not a file inside"),
    ):
        bad_csv, _ = _image_csv(tmp_path, ["a.png", name])
        with pytest.raises(FeaturesError, match=words):
            items_from_csv(bad_csv, image_column="picture", image_dir=folder)
    os.symlink(secret, folder / "link.png")  # a link inside the folder to a file outside it
    bad_csv, _ = _image_csv(tmp_path, ["a.png", "link.png"])
    with pytest.raises(FeaturesError, match="not a file inside"):
        items_from_csv(bad_csv, image_column="picture", image_dir=folder)
    with pytest.raises(FeaturesError, match="no column 'photo'"):
        items_from_csv(path, image_column="photo")


def test_a_session_from_python_with_a_render_function(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    X = _items().X

    def render(item, index):
        fig = Figure(figsize=(2, 2))
        fig.add_subplot().bar(range(3), item.tolist())
        return fig

    session = PreferenceSession(X, session_file=tmp_path / "mine.session.jsonl", num_queries=3)
    from torchpref.frontends.serve.app import NewSessions, PoolLimits, ServeItemsSpec, _store

    store = _store(session, ServeItemsSpec(render, noun="design"), "unused", NewSessions(3, 0, 5), PoolLimits())
    c = _client(store)
    assert store.sids == ["mine"] and c.post("/api/new", json={}).status_code == 403
    st = c.get("/s/mine/state").json()
    pic = st["question"]["options"][0]["picture"]
    assert pic.startswith("../../picture/")
    assert c.get("/picture/" + pic.rsplit("/", 1)[1]).content.startswith(b"\x89PNG")
    c.post("/s/mine/answer", json={"qid": st["qid"], "answer": _answer_for(st["question"]), "response_time": 1.25})
    assert session.history[0].response_time == 1.25
    assert "continue it" in c.get("/").text


def test_missing_extra_is_named(monkeypatch):
    import sys

    from torchpref.frontends.serve import app as serve_module

    monkeypatch.setitem(sys.modules, "uvicorn", None)
    with pytest.raises(ImportError, match=r"torchpref\[serve\]"):
        serve_module._require()


def test_cli_refuses_unsafe_or_incomplete_settings(tmp_path, capsys):
    from torchpref.cli import main

    csv_path = tmp_path / "items.csv"
    csv_path.write_text("a,b\n0,1\n1,0\n0.5,0.5\n")
    assert main(["serve"]) == 2
    assert "give either a world" in capsys.readouterr().err
    assert main(["serve", "--features", str(csv_path), "--host", "0.0.0.0", "--sessions", str(tmp_path / "s")]) == 2
    assert "--allow-remote" in capsys.readouterr().err
    assert main(["serve", "--features", str(csv_path), "--image-dir", str(tmp_path)]) == 2
    assert "--image-dir needs --image-column" in capsys.readouterr().err


def test_lazy_export():
    import torchpref
    from torchpref.frontends.serve.app import serve

    assert torchpref.serve is serve


SCRIPT = """
import sys, torch, torchpref
from matplotlib.figure import Figure

X = torch.tensor([[0.1, 0.2], [0.5, 0.9], [0.9, 0.4], [0.3, 0.7]], dtype=torch.float64)
session = torchpref.PreferenceSession(X, session_file=sys.argv[1], num_queries=4, names=["a", "b"])

def render(item, index):
    fig = Figure(figsize=(2, 2))
    fig.add_subplot().bar([0, 1], item.tolist())
    return fig

def ready(url):  # called once the server accepts connections: the page is there
    import urllib.request
    with urllib.request.urlopen(url + "state", timeout=60) as r:
        print("READY", url, r.status, flush=True)

torchpref.serve(session, render=render, host=sys.argv[3], port=int(sys.argv[2]), noun="design", ready=ready)
"""


def test_serve_from_python_in_a_process(tmp_path):
    """``torchpref.serve(session, render=...)`` as a user's script runs it, on another loopback
    address than 127.0.0.1 (its own address is an allowed Host): ``ready`` is called once the
    page can be fetched, then the page, its pictures, an answer with its response time in the
    user's session file."""
    import subprocess
    import sys

    from torchpref.testing.serve import START_S, free_port, get_json, post

    script = tmp_path / "serve_me.py"
    script.write_text(SCRIPT)
    port = free_port()
    log = open(tmp_path / "log.txt", "w+")
    env = dict(os.environ, MPLBACKEND="Agg")
    proc = subprocess.Popen(
        [sys.executable, str(script), str(tmp_path / "me.session.jsonl"), str(port), "127.0.0.2"],
        stdout=log,
        stderr=subprocess.STDOUT,
        env=env,
    )
    base = f"http://127.0.0.2:{port}/s/me/"
    try:
        import time

        deadline = time.monotonic() + START_S
        while True:
            try:
                st = get_json(base + "state", timeout=5)
                break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    log.seek(0)
                    pytest.fail(f"the script's server did not start:\n{log.read()[-3000:]}")
                time.sleep(0.3)
        import urllib.request

        pic = st["question"]["options"][0]["picture"].rsplit("/", 1)[1]
        with urllib.request.urlopen(f"http://127.0.0.2:{port}/picture/{pic}", timeout=60) as r:
            assert r.read().startswith(b"\x89PNG")
        a = 3 if st["question"]["kind"] == "rating" else 0
        status, reply, _ = post(base + "answer", {"qid": st["qid"], "answer": a, "response_time": 4.5})
        assert status == 200 and reply["answered"] == 1 and st["noun"] == "design"
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        log.seek(0)
        printed = log.read()
        log.close()
    assert f"READY http://127.0.0.2:{port}/s/me/ 200" in printed, printed[-3000:]
    assert printed.index("torchpref serve: open") < printed.index("READY")  # the link is printed once it works
    recs = _answers(tmp_path / "me.session.jsonl")
    assert len(recs) == 1 and recs[0]["response_time"] == 4.5


def test_ratings_in_the_unit_interval(tmp_path):
    """A served session without levels (``num_levels=None``): the page's slider sends a number in
    [0, 1], anything else is refused."""
    from torchpref.frontends.serve.app import NewSessions, PoolLimits, ServeItemsSpec, _store
    from torchpref.selection.strategies import UCBRatings

    session = PreferenceSession(
        _items().X, selector=UCBRatings(), num_levels=None, session_file=tmp_path / "unit.session.jsonl"
    )
    store = _store(session, ServeItemsSpec(), "unused", NewSessions(3, 0, None), PoolLimits())
    c = _client(store)
    st = c.get("/s/unit/state").json()
    assert st["question"]["kind"] == "rating" and st["question"]["levels"] is None
    for bad in (1.5, -0.1, "0.5", True, None):
        r = c.post("/s/unit/answer", json={"qid": st["qid"], "answer": bad})
        assert r.status_code == 400 and "[0, 1]" in r.json()["error"], bad
    assert c.post("/s/unit/answer", json={"qid": st["qid"], "answer": 0.7}).status_code == 200
    assert [(r["answer"], r["value"]) for r in _answers(tmp_path / "unit.session.jsonl")] == [(0.7, 0.7)]


def test_command_line_names_the_missing_extra(tmp_path, monkeypatch, capsys):
    import sys

    from torchpref.cli import MISSING_EXTRA, main

    csv_path = tmp_path / "items.csv"
    csv_path.write_text("a,b\n0,1\n1,0\n0.5,0.5\n")
    monkeypatch.setitem(sys.modules, "uvicorn", None)
    assert main(["serve", "--features", str(csv_path), "--sessions", str(tmp_path / "s")]) == MISSING_EXTRA
    assert 'pip install "torchpref[serve]"' in capsys.readouterr().err
    assert not (tmp_path / "s").exists()  # checked before any work


def test_serve_settings_are_grouped_and_keywords_override_them():
    from torchpref.frontends.serve.app import Listen, NewSessions, PoolLimits
    from torchpref.frontends.serve.options import grouped as _grouped

    new, listen, limits = _grouped(
        {"num_queries": 6, "port": 0, "max_open": 3}, NewSessions(seed=4), Listen(host="localhost"), None
    )
    assert (new.num_queries, new.seed, new.ties) == (6, 4, True)
    assert (listen.host, listen.port) == ("localhost", 0)
    assert limits == PoolLimits(max_open=3)
    with pytest.raises(TypeError, match="num_querys"):
        _grouped({"num_querys": 6}, None, None, None)


def test_session_store_names_an_unknown_setting(tmp_path):
    with pytest.raises(TypeError, match="seeed.*NewSessions"):
        SessionStore(_items(), tmp_path, seeed=3)


def test_serve_asks_only_from_a_question_list(tmp_path):
    """``serve --question-list``: every new session asks from the list (and resumes with it)."""
    from torchpref.sessions.query_list import read_question_list

    items = _items()
    qfile = tmp_path / "q.txt"
    qfile.write_text("0, 1, 2\n3\n4, 5\n6\n")
    queries = tuple(read_question_list(qfile, items.X))
    allowed = [sorted([0, 1, 2]), [3], sorted([4, 5]), [6]]
    store = SessionStore(items, tmp_path / "s", num_queries=4, queries=queries)
    c = _client(store)
    sid = c.post("/api/new", json={}).json()["sid"]
    for _ in range(4):
        st = c.get(f"/s/{sid}/state").json()
        shown = sorted(o["index"] for o in st["question"]["options"])
        assert shown in allowed, shown
        assert (
            c.post(f"/s/{sid}/answer", json={"qid": st["qid"], "answer": _answer_for(st["question"])}).status_code
            == 200
        )
    header = json.loads(store.path(sid).read_text().splitlines()[0])
    assert sorted(sorted(q[1:]) for q in header["queries"]) == sorted(allowed)


def test_favicon_and_a_friendly_not_found_page(served):
    store, c, sid = served
    r = c.get("/favicon.ico")
    assert r.status_code == 200 and r.headers["content-type"] == "image/x-icon" and r.content[:4] == b"\x00\x00\x01\x00"
    page = c.get("/nowhere/at/all", headers={"accept": "text/html"})
    assert page.status_code == 404 and "Back to the start page" in page.text and 'href="/"' in page.text
    api = c.get("/nowhere", headers={"accept": "application/json"})
    assert api.status_code == 404 and "no page" in api.json()["error"]
    assert "favicon.ico" in c.get(f"/s/{sid}/").text  # every page names its icon


def test_warm_up_leaves_no_file_and_no_session(tmp_path):
    """``serve`` asks and answers one throwaway question before it listens (the first participant's
    first answers were the soak's slowest): nothing of it is written or kept, and a session given
    out afterwards starts at question 1 as any other."""
    store = SessionStore(_items(), tmp_path / "s", num_queries=3)
    store.warm_up()
    assert list((tmp_path / "s").iterdir()) == [] and store.pool.open_sids == []
    c = _client(store)
    sid = c.post("/api/new", json={}).json()["sid"]
    assert c.get(f"/s/{sid}/state").json()["answered"] == 0
    assert [p.name for p in (tmp_path / "s").iterdir()] == [f"{sid}.session.jsonl"]
