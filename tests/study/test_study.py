"""``torchpref study``: participants over HTTP, the population refitted in a process of its own as
they finish, each session's population version in its header, the experimenter's page behind its
key, exports whose rows are the session files' answers, and the report."""

from __future__ import annotations

import csv
import json
import time
import warnings

import pytest
import torch

pytest.importorskip("starlette", reason="the serve extra (starlette) is not installed")
pytest.importorskip("httpx", reason="starlette's test client needs httpx")
pytest.importorskip("matplotlib")

from torchpref.frontends.serve.app import NewSessions, PoolLimits, create_app
from torchpref.population.io import load_population
from torchpref.sessions.journal import read_session_file
from torchpref.study.create import create_study
from torchpref.study.export import answer_rows, export
from torchpref.study.items import study_items
from torchpref.study.page import study_routes
from torchpref.study.refit import RefitRunner, finished_participants, refit
from torchpref.study.report import report
from torchpref.study.store import StudyStore, experimenter_key
from torchpref.testing.serve import TEST_BASE_URL, choose, write_items

KEY_Q = 4  # questions per participant


def _study(tmp_path, runner_timeout=300.0):
    csv_path = write_items(tmp_path / "src", n=16, d=2, pictures=False)
    folder = create_study(tmp_path / "study", items=csv_path, num_queries=KEY_Q)
    items = study_items(folder)
    refits = RefitRunner(folder, timeout=runner_timeout, nice=0)
    store = StudyStore(folder, items, NewSessions(KEY_Q, 0, 5, True), PoolLimits(), refits)
    key = experimenter_key(folder)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from starlette.testclient import TestClient
    app = create_app(store, extra_routes=study_routes(store, key))
    return folder, store, refits, key, lambda: TestClient(app, base_url=TEST_BASE_URL)


def _participant(c, answers=KEY_Q, k0=0):
    sid = c.post("/api/new", json={}).json()["sid"]
    for k in range(answers):
        st = c.get(f"/s/{sid}/state").json()
        r = c.post(f"/s/{sid}/answer", json={"qid": st["qid"], "answer": choose(st["question"], k0 + k)})
        assert r.status_code == 200, r.text
    return sid


def _wait(refits, timeout=240):
    deadline = time.monotonic() + timeout
    while refits.busy() and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not refits.busy(), "a refit did not finish"


def test_a_study_refits_its_population_as_participants_finish(tmp_path):
    folder, store, refits, key, client = _study(tmp_path)
    c = client()
    first = [_participant(c, k0=i) for i in range(3)]
    _wait(refits)
    pointer = folder.current()
    assert pointer is not None and set(pointer.participants) == set(first)
    pop = load_population(folder.version_path(pointer.version))  # a loadable file
    assert pop is not None
    later = _participant(c, answers=1)  # starts from the current population: its header says which
    header, _, _ = read_session_file(store.path(later))
    assert header["metadata"]["study_population"] == pointer.version
    assert header["model"]["mean"] is not None  # a prior mean: the population's
    early, _, _ = read_session_file(store.path(first[0]))
    assert early["metadata"]["study_population"] is None  # started before any population
    # a session closed and reopened comes back from the version it recorded
    store.pool.close()  # every session closed (an idle server's): reopened from its file on the next request
    assert later not in store.pool.open_sids
    st = c.get(f"/s/{later}/state").json()
    assert st["answered"] == 1
    reopened = store.entry(later).session
    assert reopened.model.mean_module is not None  # rebuilt from the population version it recorded
    events = [e["event"] for e in folder.events()]
    assert events.count("finished") == 3 and "refit" in events
    refits.close()
    store.close()


def test_experimenter_page_needs_its_key_and_a_participant_link_cannot_reach_it(tmp_path):
    folder, store, refits, key, client = _study(tmp_path)
    c = client()
    sid = _participant(c)
    assert c.get("/study/").status_code == 403
    assert c.get(f"/study/?key={'x' * len(key)}").status_code == 403
    assert c.get("/study/download/answers.csv").status_code == 403
    r = c.get(f"/study/?key={key}", follow_redirects=False)
    assert r.status_code == 303 and "key" not in r.headers["location"]
    page = c.get("/study/")
    assert page.status_code == 200 and sid in page.text and "Participants" in page.text
    rows = list(csv.DictReader(c.get("/study/download/answers.csv").text.splitlines()))
    assert len(rows) == KEY_Q and {r["participant"] for r in rows} == {sid}
    other = client()  # a participant's browser: their own link, no key
    assert other.get(f"/s/{sid}/state").status_code == 200 and other.get("/study/").status_code == 403
    _wait(refits)
    refits.close()
    store.close()


def test_export_rows_are_the_session_files_answers_and_the_report_has_its_figures(tmp_path):
    folder, store, refits, key, client = _study(tmp_path)
    c = client()
    sids = [_participant(c, k0=i) for i in range(3)]
    undo_sid = _participant(c, answers=2)
    st = c.get(f"/s/{undo_sid}/state").json()
    assert c.post(f"/s/{undo_sid}/undo", json={"qid": st["qid"]}).status_code == 200
    _wait(refits)
    files = export(folder)
    with open(folder.exports / "answers.csv") as fh:
        rows = list(csv.DictReader(fh))
    expected = []
    for sid in [*sids, undo_sid]:
        _, raw, _ = read_session_file(store.path(sid))
        undone = {r["undoes"] for r in raw if r["type"] == "undo"}
        expected += [
            (sid, r["seq"], r["kind"], r["time"], int(r["seq"] not in undone)) for r in raw if r["type"] == "answer"
        ]
    got = [(r["participant"], int(r["seq"]), r["kind"], r["time"], int(r["in_force"])) for r in rows]
    assert sorted(got) == sorted(expected)
    assert len(answer_rows(folder)) == len(expected)
    people = list(csv.DictReader(open(folder.exports / "participants.csv")))
    assert {p["participant"]: p["status"] for p in people} == {**{s: "finished" for s in sids}, undo_sid: "in progress"}
    utility = list(csv.DictReader(open(folder.exports / "population_utility.csv")))
    assert len(utility) == 16 and all(float(u["sd"]) > 0 for u in utility)
    page = report(folder).read_text()
    assert page.count("data:image/png;base64,") >= 4 and "Agreement between participants" in page
    assert all(f.is_file() for f in files)
    refits.close()
    store.close()


def test_refit_keeps_the_previous_population_when_a_refit_fails(tmp_path):
    folder, store, refits, key, client = _study(tmp_path)
    c = client()
    for i in range(2):
        _participant(c, k0=i)
    _wait(refits)
    before = folder.current()
    assert before is not None
    # a damaged session file of a third finished participant: the refit still fits the others
    sid = _participant(c, k0=5)
    _wait(refits)
    path = store.path(sid)
    path.write_text(path.read_text()[:-20])
    assert sid not in [s for s, _, _ in finished_participants(folder)]
    v = refit(folder)
    assert v is not None and folder.current().version == v
    assert json.loads((folder.populations / "current.json").read_text())["file"] == f"v{v:04d}.pt"
    refits.close()
    store.close()


def test_refit_data_are_the_session_models_data(tmp_path):
    """The refit's data of a participant are their session model's data (same items, answers), and
    read_session's model of the file is the session's model (the same posterior)."""
    from torchpref.sessions.contents import read_session

    folder, store, refits, key, client = _study(tmp_path)
    c = client()
    sid = _participant(c)
    entry = store.entry(sid)
    model_data = entry.session.model.data
    contents = read_session(store.path(sid))
    data = contents.data
    assert len(contents.in_force) == KEY_Q and contents.finished
    torch.testing.assert_close(data.train_X, model_data.train_X)
    assert torch.equal(data.comparisons, model_data.comparisons) and torch.equal(data.ratings, model_data.ratings)
    X = entry.session.transform(study_items(folder).X)
    with torch.no_grad():
        mine = contents.model().posterior(X.unsqueeze(-2)).mean
        theirs = entry.session.model.posterior(X.unsqueeze(-2)).mean
    torch.testing.assert_close(mine, theirs)
    _wait(refits)
    refits.close()
    store.close()


def test_cli_refuses_a_folder_that_is_not_a_study(tmp_path, capsys):
    from torchpref.cli import main

    assert main(["study", "export", str(tmp_path)]) == 2
    assert "not a torchpref study" in capsys.readouterr().err
    assert main(["study", "serve", str(tmp_path / "new")]) == 2  # a new study needs its items
    assert "needs its items" in capsys.readouterr().err
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "other.txt").write_text("x")
    with pytest.raises(ValueError, match="not a study"):
        create_study(tmp_path / "busy", items=write_items(tmp_path / "src", n=5, d=2, pictures=False))


def test_cli_exports_and_reports_a_study(tmp_path, capsys):
    from torchpref.cli import main

    folder, store, refits, key, client = _study(tmp_path)
    c = client()
    for i in range(2):
        _participant(c, k0=i)
    _wait(refits)
    refits.close()
    store.close()
    assert main(["study", "export", str(folder.path)]) == 0
    assert main(["study", "report", str(folder.path), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert "answers.csv" in out and (tmp_path / "out" / "report.html").is_file()


def test_a_study_whose_session_files_record_the_pool_by_reference(tmp_path, monkeypatch):
    """A large pool's headers hold its digest, not its items (here from 9 items on): the refit's data
    are still the session model's, and the exports read the pool from the study's items.csv."""
    from torchpref.sessions import settings
    from torchpref.sessions.contents import read_session
    from torchpref.study.items import study_space

    monkeypatch.setattr(settings, "POOL_INLINE_MAX", 8)
    folder, store, refits, key, client = _study(tmp_path)
    c = client()
    sid = _participant(c)
    header, _, _ = read_session_file(store.path(sid))
    assert "items" not in header["candidates"] and header["candidates"]["num_items"] == 16
    contents = read_session(store.path(sid))
    model_data = store.entry(sid).session.model.data
    assert len(contents.in_force) == KEY_Q
    torch.testing.assert_close(contents.data.train_X, model_data.train_X)
    space = study_space(folder)
    torch.testing.assert_close(space.unit, store.entry(sid).session.transform(store.items.X))
    assert len(answer_rows(folder)) == KEY_Q
    _wait(refits)
    refits.close()
    store.close()
