"""The study hardened (issue 51): downloads never empty, the refit queue surviving a dead or stuck
worker, the worker isolated from the working folder, ``current.json`` validated with a fallback,
``--selector`` honoured, CSV cells escaped, private files, settings checked before the folder is
written, one server per folder, participant ids from the link and a completion code."""

from __future__ import annotations

import csv
import io
import json
import os
import stat
import sys
import threading
import time
import warnings
from concurrent.futures import ThreadPoolExecutor

import pytest
import torch

pytest.importorskip("starlette", reason="the serve extra (starlette) is not installed")
pytest.importorskip("httpx", reason="starlette's test client needs httpx")
pytest.importorskip("matplotlib")

from torchpref.frontends.serve.app import PoolLimits, create_app
from torchpref.study.create import create_study
from torchpref.study.export import csv_cell, export, table_bytes
from torchpref.study.folder import StudyFolder
from torchpref.study.items import study_items
from torchpref.study.lock import ServerLock, StudyBusy
from torchpref.study.page import study_routes
from torchpref.study.refit import RefitRunner, refit
from torchpref.study.server import new_sessions
from torchpref.study.store import StudyStore, experimenter_key
from torchpref.testing.serve import TEST_BASE_URL, choose

Q = 3  # questions per participant
HOSTILE = '=HYPERLINK("http://evil","x")'


def _items(folder):
    folder.mkdir(parents=True, exist_ok=True)
    rows = [f'name,"{HOSTILE.replace(chr(34), chr(34) * 2)}",comfort']
    labels = ["=cmd", "@SUM(1)", "-2+3", "+1", "$\\frac{$"]  # the last: bad mathematics for matplotlib
    for i in range(10):
        rows.append(f"{labels[i % 5]}{i},{0.05 + 0.09 * i:.3f},{(0.37 * i) % 1:.3f}")
    (folder / "items.csv").write_text("\n".join(rows) + "\n")
    return folder / "items.csv"


def _client(store, key):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from starlette.testclient import TestClient
    app = create_app(store, extra_routes=study_routes(store, key))
    return TestClient(app, base_url=TEST_BASE_URL)


def _store(folder, refits=None, say=None):
    items = study_items(folder)
    refits = refits or RefitRunner(folder, timeout=300.0, nice=0)
    store = StudyStore(folder, items, new_sessions(folder, items), PoolLimits(), refits, say=say)
    return store, refits


def _participant(c, answers=Q, k0=0, participant=None):
    sid = c.post("/api/new", json={} if participant is None else {"participant": participant}).json()["sid"]
    for k in range(answers):
        st = c.get(f"/s/{sid}/state").json()
        r = c.post(f"/s/{sid}/answer", json={"qid": st["qid"], "answer": choose(st["question"], k0 + k)})
        assert r.status_code == 200, r.text
    return sid


def _number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _wait(refits, timeout=240):
    deadline = time.monotonic() + timeout
    while refits.busy() and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not refits.busy(), "a refit did not finish"


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A study of hostile item names with three finished participants (one from a link with an id)
    and a population fitted in process; its server's parts closed."""
    tmp = tmp_path_factory.mktemp("fitted")
    folder = create_study(tmp / "study", items=_items(tmp / "src"), num_queries=Q, completion_code="C0DE-51")
    dead = RefitRunner(folder, command=([sys.executable, "-c", "import sys; sys.stdin.read()"], str(tmp)))
    store, _ = _store(folder, dead)
    c = _client(store, experimenter_key(folder))
    sids = [_participant(c, k0=i, participant="-P1+" if i == 0 else None) for i in range(3)]
    dead.close()
    store.close()
    assert refit(folder, max_iter=3) == 1
    return folder, sids


# ------------------------------------------------------------------ downloads
def test_concurrent_exports_and_downloads_are_never_empty(tmp_path):
    folder = create_study(tmp_path / "study", items=_items(tmp_path / "src"), num_queries=Q)
    store, refits = _store(folder)
    key = experimenter_key(folder)
    c = _client(store, key)
    _participant(c, answers=2)
    export(folder)
    whole = (folder.exports / "answers.csv").read_bytes()
    assert whole.count(b"\n") == 3
    stop, seen = threading.Event(), []

    def read_back():
        while not stop.is_set():
            seen.append((folder.exports / "answers.csv").read_bytes())

    reader = threading.Thread(target=read_back)
    reader.start()
    with ThreadPoolExecutor(4) as pool:
        list(pool.map(lambda _: export(folder), range(24)))
    stop.set()
    reader.join()
    assert seen and all(s == whole for s in seen), "a reader saw a part of answers.csv"
    assert c.get(f"/study/?key={key}").status_code == 200
    with ThreadPoolExecutor(8) as pool:
        bodies = list(pool.map(lambda _: c.get("/study/download/answers.csv").content, range(32)))
    assert all(b == whole for b in bodies)
    refits.close()
    store.close()


# -------------------------------------------------------------- refit worker
def test_a_dead_refit_worker_is_logged_and_its_refit_asked_of_a_new_one(tmp_path, monkeypatch):
    """Killed mid-refit with another request waiting: logged, a new worker fits everyone. The worker
    is isolated: a torch.py in the folder the server runs in is never imported."""
    evil = tmp_path / "cwd"
    evil.mkdir()
    marker = tmp_path / "imported"
    (evil / "torch.py").write_text(f"open({str(marker)!r}, 'w').write('x')\nraise SystemExit(7)\n")
    monkeypatch.chdir(evil)
    monkeypatch.syspath_prepend(str(evil))
    monkeypatch.setattr(sys, "path", ["", *sys.path])
    folder = create_study(tmp_path / "study", items=_items(tmp_path / "src"), num_queries=Q)
    lines: list[str] = []
    refits = RefitRunner(folder, timeout=300.0, nice=0, say=lines.append)
    store, _ = _store(folder, refits, say=lines.append)
    c = _client(store, experimenter_key(folder))
    first = [_participant(c, k0=i) for i in range(2)]  # the second's finish asks for the first refit
    assert refits.busy()
    with refits._lock:
        worker = refits._worker
    assert worker is not None
    third = _participant(c, k0=2)  # waits for the refit running
    worker.kill()
    _wait(refits)
    events = [e["event"] for e in folder.events()]
    assert "refit worker lost" in events and "refit" in events
    pointer = folder.current()
    assert pointer is not None and set(pointer.participants) == {*first, third}
    assert refits.spawned >= 2 and not marker.exists()
    assert any("finished" in line for line in lines) and any("population v" in line for line in lines)
    refits.close()
    store.close()


def test_a_stuck_refit_worker_is_stopped_logged_and_replaced_and_the_queue_empties(tmp_path):
    folder = StudyFolder(tmp_path)
    hang = ([sys.executable, "-c", "import sys, time\nfor _ in sys.stdin: time.sleep(600)"], str(tmp_path))
    refits = RefitRunner(folder, timeout=1.0, nice=0, retries=1, command=hang)
    refits.request()
    refits.request()  # waits behind the stuck one
    deadline = time.monotonic() + 30
    while refits.busy() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not refits.busy(), "the page would say 'a refit is running' forever"
    events = [e for e in folder.events()]
    stopped = [e for e in events if e["event"] == "refit stopped"]
    lost = [e for e in events if e["event"] == "refit worker lost"]
    assert len(stopped) >= 2 and lost[0]["asked_again"] is True and lost[-1]["asked_again"] is False
    assert refits.spawned >= 2
    refits.close()


def test_a_worker_that_exits_at_once_is_retried_then_given_up(tmp_path):
    folder = StudyFolder(tmp_path)
    die = ([sys.executable, "-c", "import sys; sys.stdin.readline(); sys.exit(3)"], str(tmp_path))
    refits = RefitRunner(folder, nice=0, retries=1, command=die)
    refits.request()
    deadline = time.monotonic() + 30
    while refits.busy() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not refits.busy()
    lost = [e for e in folder.events() if e["event"] == "refit worker lost"]
    assert [e["asked_again"] for e in lost] == [True, False] and "status 3" in lost[0]["why"]
    assert refits.spawned == 2
    refits.close()


# --------------------------------------------------------------- current.json
def test_a_damaged_current_json_falls_back_to_the_newest_loadable_version(fitted, capsys):
    folder, sids = fitted
    pointer_file = folder.populations / "current.json"
    good = pointer_file.read_text()
    v1 = folder.version_path(1)
    try:
        (folder.populations / "v0002.pt").write_bytes(v1.read_bytes()[:100])  # a damaged newer version
        for bad in ('{"version": 9, "participants": []}', "{not json", '{"version": 2, "participants": []}'):
            pointer_file.write_text(bad)
            fresh = StudyFolder(folder.path)
            p = fresh.current()
            assert p is not None and p.version == 1 and p.fallback, bad
            assert set(p.participants) == set(sids)  # from the population file
            assert "current.json is not usable" in capsys.readouterr().err
        logged = [e for e in folder.events() if e["event"] == "population pointer"]
        assert logged and "v0001" in logged[-1]["why"]
        # no "participants": the server starts (and refits: it cannot know who is in it)
        pointer_file.write_text(json.dumps({"version": 1}))
        store, refits = _store(StudyFolder(folder.path))
        c = _client(store, experimenter_key(folder))
        sid = c.post("/api/new", json={}).json()["sid"]
        assert c.get(f"/s/{sid}/state").status_code == 200
        refits.close()
        store.close()
        # the population a session started from, damaged later: its reopening is a 503 saying so, logged
        saved = v1.read_bytes()
        try:
            v1.write_bytes(saved[:200])
            store, refits = _store(StudyFolder(folder.path))
            r = _client(store, experimenter_key(folder)).get(f"/s/{sid}/state")
            assert r.status_code == 503 and "population v1" in r.json()["error"]
            assert any(e["event"] == "session population unusable" for e in folder.events())
            refits.close()
            store.close()
        finally:
            v1.write_bytes(saved)
        (folder.sessions / f"{sid}.session.jsonl").unlink()
    finally:
        pointer_file.write_text(good)
        (folder.populations / "v0002.pt").unlink(missing_ok=True)
        for v in StudyFolder(folder.path).versions():
            if v > 1:
                folder.version_path(v).unlink()


# --------------------------------------------------------------- CSV and files
def test_csv_cells_that_a_spreadsheet_would_run_are_escaped(fitted):
    folder, sids = fitted
    assert [csv_cell(v) for v in ("=1+1", "+1", "-1", "@A1", "\tx", "\rx", "plain", -1.5)] == [
        "'=1+1", "'+1", "'-1", "'@A1", "'\tx", "'\rx", "plain", -1.5,
    ]  # fmt: skip
    for what in ("answers.csv", "participants.csv", "population_utility.csv"):
        table = list(csv.reader(io.StringIO(table_bytes(folder, what).decode())))
        assert len(table) > 1
        for row in table:
            for cell in row:
                assert not cell.startswith(("=", "+", "-", "@", "\t", "\r")) or _number(cell), (what, cell)
    utility = list(csv.DictReader(io.StringIO(table_bytes(folder, "population_utility.csv").decode())))
    assert "'" + HOSTILE in utility[0]  # the feature's name, escaped, its values in the CSV's own units
    assert float(utility[1]["'" + HOSTILE]) == pytest.approx(0.14) and utility[0]["item"] == "'=cmd0"
    answers = list(csv.DictReader(io.StringIO(table_bytes(folder, "answers.csv").decode())))
    assert {a["participant_id"] for a in answers} == {"'-P1+", ""}
    assert all(";" not in a["chosen"] and not a["chosen"].startswith("#") for a in answers if a["kind"] == "choice")


def test_everything_the_key_guards_is_private(fitted):
    folder, _ = fitted
    export(folder)
    from torchpref.study.report import report

    report(folder)
    seen = 0
    for root, dirs, files in os.walk(folder.path):
        for d in dirs:
            assert stat.S_IMODE(os.stat(os.path.join(root, d)).st_mode) == 0o700, d
        for f in files:
            mode = stat.S_IMODE(os.stat(os.path.join(root, f)).st_mode)
            assert mode & 0o077 == 0, (f, oct(mode))
            seen += 1
    assert stat.S_IMODE(os.stat(folder.path).st_mode) == 0o700 and seen >= 8


def test_the_report_names_participants_and_items(fitted):
    from torchpref.study.report import participant_utilities, report_html

    folder, sids = fitted
    page = report_html(folder)
    assert "-P1+" in page and "3 finished" in page and page.count("data:image/png;base64,") >= 4
    # a participant who started from the population: the report rebuilds their session's own model
    dead = RefitRunner(folder, command=([sys.executable, "-c", "import sys; sys.stdin.read()"], str(folder.path)))
    store, _ = _store(StudyFolder(folder.path), dead)
    c = _client(store, experimenter_key(folder))
    later = _participant(c, answers=2)
    try:
        with store.entry(later).lock:
            session = store.entry(later).session
            X = session.transform(study_items(folder).X)
            expected = session.model.posterior(X.unsqueeze(-2)).mean.reshape(-1).detach()
        assert session.model.mean_module is not None  # the population's person model
        got = participant_utilities(StudyFolder(folder.path))[later]
        assert torch.allclose(got, expected, atol=1e-8)
    finally:
        dead.close()
        store.close()
        for f in folder.sessions.glob(f"{later}.*"):
            f.unlink()


# -------------------------------------------------------------- serve settings
def test_a_study_records_and_honours_its_selector(tmp_path):
    folder = create_study(tmp_path / "study", items=_items(tmp_path / "src"), num_queries=Q, selector="random")
    assert folder.settings()["selector"] == "random"
    store, refits = _store(folder)
    key = experimenter_key(folder)
    c = _client(store, key)
    sid = _participant(c, answers=1)
    from torchpref.sessions.contents import read_session

    assert read_session(store.path(sid)).header.selector["class"].endswith("RandomMixed")
    c.get(f"/study/?key={key}")
    page = c.get("/study/").text
    assert "<strong>random</strong> selector" in page and "random rating or best-of-m" in page
    with pytest.raises(ValueError, match="selector='random'.*Serve it as it is"):
        create_study(folder.path, items=folder.path / "items.csv", selector="ucbc")
    refits.close()
    store.close()


def test_settings_are_checked_before_the_folder_is_written_and_the_retry_works(tmp_path, capsys):
    from torchpref.cli import main

    items = _items(tmp_path / "src")
    target = tmp_path / "study"
    assert main(["study", "serve", str(target), "--features", str(tmp_path / "typo.csv")]) == 2
    assert "does not exist" in capsys.readouterr().err and not target.exists()
    assert main(["study", "serve", str(target), "--features", str(items), "--image-column", "nope"]) == 2
    assert "nope" in capsys.readouterr().err and not target.exists()
    assert main(["study", "serve", str(target), "--features", str(items), "--redirect-url", "javascript:x"]) == 2
    assert "redirect_url" in capsys.readouterr().err and not target.exists()
    target.mkdir()
    (target / "sessions").mkdir()  # what an older version's failed start left: still taken as empty
    folder = create_study(target, items=items, num_queries=Q)
    assert folder.settings()["num_queries"] == Q
    with pytest.raises(ValueError, match="no participants yet, so you may also delete the folder"):
        create_study(target, items=items, num_queries=Q + 1)


def test_one_server_per_folder_and_a_stale_lock_taken_over(tmp_path):
    folder = create_study(tmp_path / "study", items=_items(tmp_path / "src"), num_queries=Q)
    first = ServerLock(folder)
    first.serving_at("http://127.0.0.1:8123/")
    with pytest.raises(StudyBusy, match=rf"process {os.getpid()} at http://127.0.0.1:8123/"):
        ServerLock(folder)
    first.release()
    (folder.path / ".server.lock").write_text(json.dumps({"pid": 999999999, "address": "http://old/"}))
    second = ServerLock(folder)  # the process named is gone: its lock is taken over, and logged
    assert [e["pid"] for e in folder.events() if e["event"] == "stale server lock taken over"] == [999999999]
    second.release()


def test_participant_id_from_the_link_completion_code_and_first_population_status(tmp_path):
    folder = create_study(
        tmp_path / "study", items=_items(tmp_path / "src"), num_queries=Q,
        completion_code="ABC123", redirect_url="https://example.org/done?c=ABC123",
    )  # fmt: skip
    slow = ([sys.executable, "-c", "import sys; sys.stdin.read()"], str(tmp_path))  # never answers: a long fit
    refits = RefitRunner(folder, command=slow, nice=0)
    store, _ = _store(folder, refits)
    key = experimenter_key(folder)
    c = _client(store, key)
    assert c.post("/api/new", json={"participant": "x" * 200}).status_code == 400
    sid = _participant(c, participant="PROLIFIC-42")
    st = c.get(f"/s/{sid}/state").json()
    assert st["done"] and st["completion"] == {"code": "ABC123", "redirect": "https://example.org/done?c=ABC123"}
    c.get(f"/study/?key={key}")
    assert "No population yet" in c.get("/study/").text
    _participant(c, k0=1)
    page = c.get("/study/").text
    assert "The first population is being fitted now" in page and "PROLIFIC-42" in page and "ABC123" in page
    rows = list(csv.DictReader(io.StringIO(c.get("/study/download/participants.csv").text)))
    assert {r["participant_id"] for r in rows} == {"PROLIFIC-42", ""}
    refits.close()
    store.close()
