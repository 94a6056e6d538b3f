"""Which solver answers in a study (issue 52): a participant's served answers, once their session
starts from the refitted population (a person model with the population's prior mean), are solved
by the compiled path; the refit itself records its solver (the population's joint Newton loop in
torch: the compiled path solves one person's problem, not the population's)."""

from __future__ import annotations

import pytest

pytest.importorskip("starlette", reason="the serve extra (starlette) is not installed")
pytest.importorskip("httpx", reason="starlette's test client needs httpx")
pytest.importorskip("matplotlib")

from torchpref.inference import fast_path
from torchpref.population.fit import SOLVER
from torchpref.population.io import load_population
from torchpref.sessions.journal import read_session_file
from torchpref.testing.serve import choose

from .test_study import KEY_Q, _participant, _study, _wait

needs_numba = pytest.mark.skipif(not fast_path.available(), reason="numba is not installed (the fast extra)")


@needs_numba
def test_a_study_refit_records_its_solver_and_its_served_answers_are_compiled(tmp_path):
    with fast_path.fast_path("on"):
        assert fast_path.warm_up() is not None, fast_path.status()  # built first if need be
    fast_path.set_fast_path("on")  # the whole process: the test client serves from other threads
    try:
        folder, store, refits, key, client = _study(tmp_path)
        c = client()
        for i in range(2):
            _participant(c, k0=i)
        _wait(refits)
        pointer = folder.current()
        assert pointer is not None
        refit_events = [e for e in folder.events() if e["event"] == "refit"]
        assert refit_events and refit_events[-1]["solver"] == SOLVER == "torch"
        assert load_population(folder.version_path(pointer.version)).stats["solver"] == SOLVER
        # a participant who starts from that population: every answer, and the question after it,
        # solved by the compiled solver
        sid = c.post("/api/new", json={}).json()["sid"]
        header, _, _ = read_session_file(store.path(sid))
        assert header["metadata"]["study_population"] == pointer.version
        solvers = []
        for k in range(KEY_Q):
            st = c.get(f"/s/{sid}/state").json()
            r = c.post(f"/s/{sid}/answer", json={"qid": st["qid"], "answer": choose(st["question"], k)})
            assert r.status_code == 200, r.text
            session = store.entry(sid).session
            assert session.model.mean_module is not None  # the population's prior mean
            solvers.append(session.model.mode.solver)
        assert solvers == ["compiled"] * KEY_Q
        refits.close()
        store.close()
    finally:
        fast_path.set_fast_path(None)
