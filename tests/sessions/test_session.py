"""PreferenceSession: ask/tell, out-of-turn answers, undo, the session file and its recovery."""

import json
import os
import warnings

import pytest
import torch

from torchpref import BoxCandidates, RankingQuery, RatingQuery, likert_to_unit
from torchpref.sessions.errors import (
    SessionFileCorrupt,
    SessionFileError,
    SessionMismatchError,
    SessionRepairWarning,
    SessionVersionError,
)
from torchpref.sessions.session import (
    FORMAT_VERSION,
    PreferenceSession,
    default_session_model,
    read_session_file,
    step_generator,
)

SCALE = torch.tensor([100.0, 5.0], dtype=torch.float64)


def pool(n: int = 30, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 2, generator=g, dtype=torch.float64) * SCALE


def utility(X: torch.Tensor) -> torch.Tensor:
    Z = X / SCALE
    return -((Z[..., 0] - 0.7) ** 2 + (Z[..., 1] - 0.3) ** 2)


def answer(q) -> int:
    if q.kind == "rating":
        return int(min(5, max(1, 1 + int((float(utility(q.item)) + 0.5) * 8))))
    return int(utility(q.items).argmax())


def run(session: PreferenceSession, n: int) -> None:
    for _ in range(n):
        q = session.ask()
        session.tell(q, answer(q))


def assert_same_posterior(a: PreferenceSession, b: PreferenceSession, X: torch.Tensor, atol: float = 1e-8) -> None:
    ma, sa = a.predict(X)
    mb, sb = b.predict(X)
    torch.testing.assert_close(ma, mb, rtol=0, atol=atol)
    torch.testing.assert_close(sa, sb, rtol=0, atol=atol)


def test_ask_is_stable_until_answered_and_tell_updates_model():
    s = PreferenceSession(pool(), seed=1)
    q = s.ask()
    assert s.ask() is q
    assert isinstance(q, (RatingQuery, RankingQuery))
    before = s.predict(pool())[0].clone()
    s.tell(q, answer(q))
    assert s.step == 1 and len(s.history) == 1
    assert s.history[0].step == 0
    assert not torch.equal(before, s.predict(pool())[0])
    assert s.ask() is not q


def test_rating_levels_go_through_likert_to_unit():
    X = pool()
    s = PreferenceSession(X, num_levels=5)
    s.tell_rating(X[3], 4)
    assert s.history[0].value == float(likert_to_unit(4, 5)) == pytest.approx(0.7)
    assert s.model.ratings.tolist() == [pytest.approx(0.7)]
    torch.testing.assert_close(s.model.train_X[s.model.rating_index[0]], s.transform(X[3]))


def test_session_equals_model_built_directly():
    X = pool()
    s = PreferenceSession(X)
    s.tell_rating(X[2], 5)
    s.tell_choice(X[[4, 5, 6]], 1)
    m = default_session_model(s.transform(X[:1]))
    m.add_observations(s.transform(X[2:3]), ratings=[0.9], rating_index=[0])
    m.add_observations(s.transform(X[[4, 5, 6]]), comparisons=torch.tensor([[1, 0], [1, 2]]))
    Xt = s.transform(X)
    with torch.no_grad():
        torch.testing.assert_close(s.model.posterior(Xt).mean, m.posterior(Xt).mean, rtol=0, atol=1e-8)


def test_out_of_turn_answers_and_no_preference(tmp_path):
    X = pool()
    s = PreferenceSession(X, session_file=tmp_path / "s.jsonl")
    q = s.ask()
    s.tell_rating(torch.tensor([55.0, 2.5], dtype=torch.float64), 3)  # not a pool item
    s.tell_choice(X[[0, 7]], 0)
    n_obs = s.model.data.num_observations
    s.tell_no_preference(X[[1, 2, 3]])
    assert s.model.data.num_observations == n_obs + 3  # a tie between every two items shown
    assert s.model.ties.shape == (3, 2) and s.model.ties_offered
    assert [h.kind for h in s.history] == ["rating", "choice", "no_preference"]
    assert all(h.step is None for h in s.history)
    assert s.ask() is not q  # the pending query is re-derived after any answer
    s.close()
    kinds = [r["kind"] for r in read_session_file(tmp_path / "s.jsonl")[1]]
    assert kinds == ["rating", "choice", "no_preference"]


def test_tell_none_to_ranking_is_no_preference():
    s = PreferenceSession(pool(), seed=0, selector=_always_ranking())
    q = s.ask()
    s.tell(q, None)
    assert s.history[0].kind == "no_preference" and s.history[0].step == 0
    m = q.items.shape[0]
    assert s.model.data.num_observations == m * (m - 1) // 2  # ties between the items shown


def _always_ranking():
    from torchpref import RandomRankings

    return RandomRankings(m=4)


@pytest.mark.parametrize("bad", [0, 6, 2.5, "4", True, float("nan"), None])
def test_bad_rating_leaves_session_and_file_unchanged(tmp_path, bad):
    X = pool()
    path = tmp_path / "s.jsonl"
    s = PreferenceSession(X, session_file=path, selector=_rating_selector())
    s.tell_rating(X[0], 2)
    size, before = path.stat().st_size, s.predict(X)[0]
    q = s.ask()
    with pytest.raises(ValueError, match="rating"):
        s.tell(q, bad)
    assert path.stat().st_size == size and s.step == 1 and s.ask() is q
    torch.testing.assert_close(s.predict(X)[0], before, rtol=0, atol=0)


def _rating_selector():
    from torchpref import UCBRatings

    return UCBRatings()


@pytest.mark.parametrize("bad", [-1, 5, 1.5, "0", True])
def test_bad_choice_leaves_session_and_file_unchanged(tmp_path, bad):
    path = tmp_path / "s.jsonl"
    s = PreferenceSession(pool(), session_file=path, selector=_always_ranking())
    size = path.stat().st_size
    q = s.ask()
    with pytest.raises(ValueError, match="index"):
        s.tell(q, bad)
    assert path.stat().st_size == size and s.step == 0


def test_bad_items_are_rejected():
    X = pool()
    s = PreferenceSession(X)
    with pytest.raises(ValueError, match="m x 2"):
        s.tell_rating(torch.zeros(3, dtype=torch.float64), 3)
    with pytest.raises(ValueError, match="finite"):
        s.tell_choice(torch.tensor([[1.0, float("inf")], [0.0, 0.0]]), 0)
    with pytest.raises(ValueError, match="itself"):
        s.tell_choice(X[[1, 1]], 0)  # the same item twice
    assert s.step == 0


def test_write_failure_leaves_file_and_model_unchanged(tmp_path, monkeypatch):
    import torchpref.sessions.journal as mod

    X = pool()
    path = tmp_path / "s.jsonl"
    s = PreferenceSession(X, session_file=path)
    s.tell_rating(X[0], 4)
    size, before = path.stat().st_size, s.predict(X)

    def half_then_fail(fd, data):
        os.write(fd, data[: len(data) // 2])
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(mod, "_write_all", half_then_fail)
    with pytest.raises(OSError):
        s.tell_rating(X[1], 2)
    assert path.stat().st_size == size and s.step == 1
    torch.testing.assert_close(s.predict(X), before, rtol=0, atol=0)


def test_undo_rebuilds_the_model_and_is_logged(tmp_path):
    X = pool()
    path = tmp_path / "s.jsonl"
    s = PreferenceSession(X, session_file=path, seed=4)
    run(s, 4)
    ref = PreferenceSession(X, seed=4)
    run(ref, 3)
    undone = s.undo()
    assert undone.step == 3 and s.step == 3
    assert_same_posterior(s, ref, X, atol=1e-12)  # the model before answer 4, to round-off
    assert s.ask().items.tolist() == ref.ask().items.tolist()  # query 3 is asked again
    run(s, 1)
    s.close()
    header, records, _ = read_session_file(path)
    assert [r["type"] for r in records] == ["answer"] * 4 + ["undo", "answer"]
    assert records[4]["undoes"] == records[3]["seq"]
    resumed = PreferenceSession.load(path)
    assert [h.seq for h in resumed.history] == [1, 2, 3, 6]
    assert_same_posterior(resumed, s, X, atol=1e-12)


def test_undo_everything_then_nothing_to_undo():
    X = pool()
    s = PreferenceSession(X)
    s.tell_rating(X[0], 1)
    s.tell_no_preference(X[[1, 2]])
    assert s.undo().kind == "no_preference"
    assert s.undo().kind == "rating"
    with pytest.raises(ValueError, match="nothing to undo"):
        s.undo()
    assert_same_posterior(s, PreferenceSession(X), X, atol=1e-12)


def test_restart_continues_as_if_uninterrupted(tmp_path):
    X = pool(40, seed=2)
    path = tmp_path / "s.jsonl"
    ref = PreferenceSession(X, seed=7, num_queries=12)
    run(ref, 12)
    for chunk in (5, 1, 6):
        s = PreferenceSession(X, session_file=path, seed=7, num_queries=12)
        run(s, chunk)
        s.close()
    s = PreferenceSession.load(path)
    assert s.done and s.step == 12
    assert [h.items.tolist() for h in s.history] == [h.items.tolist() for h in ref.history]
    assert [h.answer for h in s.history] == [h.answer for h in ref.history]
    assert_same_posterior(s, ref, X, atol=1e-12)


def test_box_candidates_are_persisted(tmp_path):
    box = BoxCandidates(torch.tensor([[0.0, -1.0], [2.0, 1.0]], dtype=torch.float64), num=50)
    path = tmp_path / "box.jsonl"
    s = PreferenceSession(box, session_file=path, seed=3, num_queries=6)
    run(s, 6)
    s.close()
    r = PreferenceSession.load(path)
    assert r.done
    assert_same_posterior(r, s, torch.rand(10, 2, dtype=torch.float64), atol=1e-12)
    assert r.best_item()[0] is None


def test_header_and_record_format(tmp_path):
    X = pool()
    path = tmp_path / "s.jsonl"
    s = PreferenceSession(X, session_file=path, names=["distance", "information"], metadata={"who": "test"})
    q = s.ask()
    s.tell(q, answer(q))
    s.close()
    lines = path.read_text().splitlines()
    header, rec = json.loads(lines[0]), json.loads(lines[1])
    assert header["type"] == "header" and header["version"] == FORMAT_VERSION and header["dim"] == 2
    assert header["names"] == ["distance", "information"] and header["metadata"] == {"who": "test"}
    assert torch.tensor(header["candidates"]["items"], dtype=torch.float64).equal(X)
    assert rec["type"] == "answer" and rec["v"] == FORMAT_VERSION and rec["seq"] == 1 and "time" in rec
    assert torch.tensor(rec["items"], dtype=torch.float64).equal(q.items)  # exact float64 round trip
    assert rec["query"]["step"] == 0 and rec["query"]["kind"] == q.kind


def _session_file(tmp_path, n=3):
    X = pool()
    path = tmp_path / "s.jsonl"
    s = PreferenceSession(X, session_file=path, seed=5)
    run(s, n)
    s.close()
    return X, path


def test_truncated_last_line_is_reported_not_dropped(tmp_path):
    X, path = _session_file(tmp_path)
    data = path.read_bytes()
    last_start = data.rstrip(b"\n").rfind(b"\n") + 1
    path.write_bytes(data[: last_start + 25])  # a crash mid-write of answer 3
    with pytest.raises(SessionFileCorrupt, match="line 4") as err:
        PreferenceSession(X, session_file=path, seed=5)
    assert err.value.line_number == 4 and err.value.repairable and "repair=True" in str(err.value)
    with pytest.raises(SessionFileCorrupt):
        PreferenceSession.load(path)
    assert path.read_bytes() == data[: last_start + 25]  # nothing changed by failing to open


def test_repair_reports_keeps_the_partial_line_and_reasks(tmp_path):
    X, path = _session_file(tmp_path)
    data = path.read_bytes()
    last_start = data.rstrip(b"\n").rfind(b"\n") + 1
    path.write_bytes(data[: last_start + 25])
    with pytest.warns(SessionRepairWarning, match="line 4"):
        s = PreferenceSession.load(path, repair=True)
    assert s.step == 2 and path.read_bytes() == data[:last_start]
    assert data[last_start : last_start + 25] in (tmp_path / "s.jsonl.dropped").read_bytes()
    ref = PreferenceSession(X, seed=5)
    run(ref, 3)
    run(s, 1)  # answer 3 is asked again and re-answered
    assert [h.items.tolist() for h in s.history] == [h.items.tolist() for h in ref.history]
    assert_same_posterior(s, ref, X, atol=1e-12)


def test_invalid_last_line_with_newline_and_partial_header(tmp_path):
    X, path = _session_file(tmp_path, n=1)
    good = path.read_bytes()
    path.write_bytes(good + b"\x00\x00\x00\n")  # zero-filled block after a crash
    with pytest.raises(SessionFileCorrupt, match="line 3"):
        PreferenceSession(X, session_file=path, seed=5)
    with pytest.warns(SessionRepairWarning):
        s = PreferenceSession(X, session_file=path, seed=5, repair=True)
    assert s.step == 1 and path.read_bytes() == good
    s.close()
    path.write_bytes(good[:10])  # crash (or a full disk) while writing the header: no answer can be lost
    with pytest.warns(SessionRepairWarning, match="incomplete header"):
        s = PreferenceSession(X, session_file=path, seed=5)  # repaired without being asked
    assert s.step == 0 and read_session_file(path)[0]["type"] == "header"


def test_bad_line_in_the_middle_is_not_repairable(tmp_path):
    X, path = _session_file(tmp_path)
    lines = path.read_bytes().split(b"\n")
    lines[2] = lines[2][:20]
    path.write_bytes(b"\n".join(lines))
    with pytest.raises(SessionFileCorrupt, match="line 3") as err:
        PreferenceSession(X, session_file=path, seed=5, repair=True)
    assert not err.value.repairable


def test_newer_version_and_other_dimensions_are_clear_errors(tmp_path):
    X, path = _session_file(tmp_path, n=1)
    lines = path.read_text().splitlines()
    header = json.loads(lines[0])
    newer = dict(header, version=FORMAT_VERSION + 1)
    path.write_text("\n".join([json.dumps(newer)] + lines[1:]) + "\n")
    with pytest.raises(SessionVersionError, match=f"version {FORMAT_VERSION + 1}"):
        PreferenceSession.load(path)
    rec = dict(json.loads(lines[1]), v=FORMAT_VERSION + 1)
    path.write_text("\n".join([lines[0], json.dumps(rec)]) + "\n")
    with pytest.raises(SessionVersionError, match="line 2"):
        PreferenceSession.load(path)
    path.write_text("\n".join(lines) + "\n")
    X3 = torch.rand(10, 3, dtype=torch.float64)
    with pytest.raises(SessionMismatchError, match="2-dimensional items, but these items have 3"):
        PreferenceSession(X3, session_file=path)
    with pytest.raises(SessionMismatchError, match="candidates"):
        PreferenceSession(pool(seed=9), session_file=path, seed=5)
    with pytest.raises(SessionMismatchError, match="seed"):
        PreferenceSession(X, session_file=path, seed=6)
    assert issubclass(SessionMismatchError, ValueError) and issubclass(SessionFileCorrupt, ValueError)


def test_file_in_use_by_another_session(tmp_path):
    X = pool()
    path = tmp_path / "s.jsonl"
    s = PreferenceSession(X, session_file=path)
    with pytest.raises(SessionFileError, match="in use"):
        PreferenceSession(X, session_file=path)
    s.close()
    PreferenceSession(X, session_file=path).close()


def test_step_generator_depends_on_seed_and_step_only():
    a = torch.rand(3, generator=step_generator(1, 4))
    assert torch.equal(a, torch.rand(3, generator=step_generator(1, 4)))
    assert not torch.equal(a, torch.rand(3, generator=step_generator(1, 5)))
    assert not torch.equal(a, torch.rand(3, generator=step_generator(2, 4)))


def test_best_item_is_the_argmax_of_the_posterior_mean():
    X = pool()
    s = PreferenceSession(X, seed=2)
    run(s, 8)
    i, x = s.best_item()
    assert torch.equal(x, X[i]) and i == int(s.predict(X)[0].argmax())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert 0 <= float(s.expected_rating(X[:1])) <= 1


def test_duplicate_pool_items_are_never_shown_together():
    from torchpref import RandomRankings

    X = pool(6)
    X = torch.cat([X, X[:4]])  # the same items twice (e.g. two planners' identical paths)
    s = PreferenceSession(X, selector=RandomRankings(m=5), num_queries=10)
    for _ in range(10):
        q = s.ask()
        assert torch.unique(q.items, dim=0).shape[0] == 5 and all(i < 6 for i in q.indices)
        s.tell(q, 0)


def test_docs_sessions_example_runs(tmp_path, monkeypatch):
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "docs" / "sessions.md").read_text()
    code = re.findall(r"```python\n(.*?)```", text, re.S)[0]
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    exec(code, ns)
    assert ns["s"].done and (tmp_path / "me.jsonl").exists()
    ns["s"].close()
    again: dict = {}  # a reader who runs it twice resumes the file: the same answers, none added
    exec(code, again)
    assert [h.answer for h in again["s"].history] == [h.answer for h in ns["s"].history]
    assert (tmp_path / "me.jsonl").read_text().count("\n") == 15
    again["s"].close()


@pytest.mark.parametrize("metadata", [{"who": object()}, {"score": float("nan")}, ["not", "a", "dict"]])
def test_metadata_that_json_cannot_hold_is_refused_before_the_file_is_made(tmp_path, metadata):
    with pytest.raises(ValueError, match="metadata must"):
        PreferenceSession(pool(6), session_file=tmp_path / "s.jsonl", metadata=metadata)
    assert not (tmp_path / "s.jsonl").exists()


def test_a_query_told_twice_or_from_another_session_is_refused(tmp_path):
    from torchpref import RandomRankings

    a = PreferenceSession(pool(8, seed=1), session_file=tmp_path / "a.jsonl", selector=RandomRankings(m=3))
    b = PreferenceSession(pool(8, seed=2), session_file=tmp_path / "b.jsonl", selector=RandomRankings(m=3))
    q = a.ask()
    size = (tmp_path / "b.jsonl").stat().st_size
    with pytest.raises(ValueError, match="not this session's pool rows"):
        b.tell(q, 0)  # before the model is touched: no warning, nothing rebuilt
    assert b.step == 0 and (tmp_path / "b.jsonl").stat().st_size == size and b._model_version == b._version
    a.tell(q, 0)
    with pytest.raises(ValueError, match="already answered"):
        a.tell(q, 1)  # a second click on the same question
    assert a.step == 1 and len(a.records) == 1
    a.undo()
    a.tell(q, 1)  # once its answer is undone, the query may be answered again
    assert a.step == 1 and a.history[-1].answer == 1


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(selector="ucb"), TypeError, "selector must be a Selector"),  # an AttributeError at the first ask
        (dict(model_factory=3), TypeError, "model_factory must be callable"),
        (dict(model_factory=lambda X: 3), TypeError, "model_factory must return a PreferenceGP, got int"),
    ],
)
def test_selector_and_model_factory_are_checked_when_the_session_opens(tmp_path, kwargs, error, match):
    with pytest.raises(error, match=match):
        PreferenceSession(pool(6), session_file=tmp_path / "s.jsonl", **kwargs)


def test_a_pool_with_nan_items_is_named():
    from torchpref import FinitePool

    X = pool(4)
    X[1, 0] = float("nan")
    with pytest.raises(ValueError, match="the pool's items must be finite"):
        PreferenceSession(FinitePool(X))


def test_response_time_is_recorded_validated_and_optional(tmp_path):
    X = pool()
    path = tmp_path / "s.jsonl"
    s = PreferenceSession(X, session_file=path, seed=3)
    q = s.ask()
    s.tell(q, answer(q), response_time=2.5)
    s.tell_rating(X[4], 3, response_time=0)
    s.tell_choice(X[[5, 6]], 1)
    s.tell_no_preference(X[[7, 8]], response_time=torch.tensor(1.25))
    for bad in (-1.0, float("nan"), float("inf"), True, "3"):
        with pytest.raises(ValueError, match="response_time"):
            s.tell_rating(X[9], 3, response_time=bad)
    assert s.step == 4
    assert [h.response_time for h in s.history] == [2.5, 0.0, None, 1.25]
    s.close()
    assert [r["response_time"] for r in read_session_file(path)[1]] == [2.5, 0.0, None, 1.25]
    lines = path.read_text().splitlines()
    rec = json.loads(lines[2])
    rec["response_time"] = -3
    path.write_text("\n".join(lines[:2] + [json.dumps(rec)] + lines[3:]) + "\n")
    with pytest.raises(SessionFileError, match="line 3: 'response_time' must be null"):
        read_session_file(path)
