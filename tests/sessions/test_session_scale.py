"""Sessions at constant cost (issue #22): the incremental session, its undo and its resume against
the reference replay (every answer through record_answer), and resuming files across versions."""

import json
import shutil
from pathlib import Path

import pytest
import torch

import torchpref.sessions.session as session_mod
from torchpref import RandomRankings
from torchpref.sessions.errors import SessionSettingsError
from torchpref.sessions.model_state import build_data, snapshot_path
from torchpref.sessions.session import PreferenceSession, read_session_file

SCALE = torch.tensor([100.0, 5.0], dtype=torch.float64)
FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


def pool(n: int = 40, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 2, generator=g, dtype=torch.float64) * SCALE


def utility(X: torch.Tensor) -> torch.Tensor:
    Z = X / SCALE
    return torch.sin(4 * Z[..., 0]) - (Z[..., 1] - 0.3) ** 2


def answer(q) -> int:
    if q.kind == "rating":
        return int(min(5, max(1, 3 + round(2 * float(utility(q.item))))))
    return int(utility(q.items).argmax())


def busy_session(path, X, n: int = 40, seed: int = 2) -> PreferenceSession:
    """A session of ``n`` rounds: asked and told, out-of-turn answers, no preference, undos."""
    s = PreferenceSession(X, session_file=path, seed=seed, num_queries=n)
    g = torch.Generator().manual_seed(seed)
    for k in range(n):
        q = s.ask()
        s.tell(q, answer(q))
        if k % 7 == 3:
            s.tell_no_preference(X[torch.randperm(X.shape[0], generator=g)[:3]])
        if k % 5 == 4:
            s.undo()
        if k % 11 == 6:
            i, j = torch.randperm(X.shape[0], generator=g)[:2].tolist()
            s.tell_rating((X[i] + X[j]) / 2, 2)  # not a pool item
    return s


def posterior(model, Z):
    with torch.no_grad():
        post = model.posterior(Z.unsqueeze(-2))
    return post.mean.reshape(-1), post.variance.reshape(-1)


@pytest.mark.slow  # a long loop (27-38 s here): make test-slow, which CI runs
def test_incremental_session_undo_and_resume_agree_with_a_full_replay(tmp_path):
    X = pool()
    path = tmp_path / "s.jsonl"
    s = busy_session(path, X)
    Z = s.transform(X)
    ref = s._replay(s._active())  # the reference: every answer in force told one by one
    live = posterior(s.model, Z)
    for a, b in zip(live, posterior(ref, Z), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-10)
    data, _ = build_data(s._anchor, s._active(), s.transform, ref.rating_eps, ref.rating_levels)
    for field in ("train_X", "comparisons", "ratings", "rating_index", "ties"):
        assert torch.equal(getattr(data, field), getattr(ref.data, field)), field
    q = s.ask()
    s.close()
    for keep_snapshot in (True, False):  # from the mode kept beside the file; from the data alone
        if not keep_snapshot:
            snapshot_path(path).unlink()
        r = PreferenceSession.load(path)
        tol = 1e-12 if keep_snapshot else 1e-6  # to round-off; to Newton's tolerance
        for a, b in zip(posterior(r.model, Z), live, strict=True):
            torch.testing.assert_close(a, b, rtol=0, atol=tol)
        rq = r.ask()
        assert rq.kind == q.kind and torch.equal(rq.items, q.items)  # the same next query
        r.close()


def test_undo_goes_back_to_the_earlier_model_without_replaying(tmp_path, monkeypatch):
    X = pool()
    s = busy_session(tmp_path / "s.jsonl", X, n=20)
    Z = s.transform(X)
    states = []
    for _ in range(4):
        states.append(posterior(s.model, Z))
        q = s.ask()
        s.tell(q, answer(q))
    calls = []
    monkeypatch.setattr(session_mod, "record_answer", lambda *a, **k: calls.append(1))
    for before in reversed(states):
        s.undo()
        for a, b in zip(posterior(s.model, Z), before, strict=True):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    assert calls == []  # no answer replayed


def test_resume_replays_at_most_the_answers_after_the_snapshot(tmp_path, monkeypatch):
    X = pool()
    path = tmp_path / "s.jsonl"
    s = busy_session(path, X, n=30)
    snap = snapshot_path(path).read_bytes()
    for _ in range(3):  # three answers the snapshot does not know of (a crash before it was written)
        q = s.ask()
        s.tell(q, answer(q))
    live = posterior(s.model, s.transform(X))
    s.close()
    snapshot_path(path).write_bytes(snap)
    real, calls = session_mod.record_answer, []

    def counting(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(session_mod, "record_answer", counting)
    r = PreferenceSession.load(path)
    assert len(calls) == 3
    for a, b in zip(posterior(r.model, r.transform(X)), live, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    r.close()
    snapshot_path(path).write_bytes(b'{"format": "torchpref-session-mode", "n": 3}\n' + b"\x00" * 5)  # damaged
    calls.clear()
    r = PreferenceSession.load(path)  # ignored: the data built in one pass, no replay
    assert calls == []
    torch.testing.assert_close(posterior(r.model, r.transform(X))[0], live[0], rtol=0, atol=1e-6)
    r.close()


def _fixture(tmp_path) -> tuple[Path, dict]:
    path = tmp_path / "old.jsonl"
    shutil.copy(FIXTURES / "session_v1_defaults.jsonl", path)
    return path, json.loads((FIXTURES / "session_v1_defaults.expected.json").read_text())


def _check_fixture(s: PreferenceSession, expected: dict) -> None:
    X = torch.tensor(read_session_file(s.path)[0]["candidates"]["items"], dtype=torch.float64)
    mean, sd = s.predict(X)
    torch.testing.assert_close(mean, torch.tensor(expected["mean"], dtype=torch.float64), rtol=0, atol=1e-6)
    torch.testing.assert_close(sd, torch.tensor(expected["sd"], dtype=torch.float64), rtol=0, atol=1e-6)
    q = s.ask()
    assert s.step == expected["step"] and q.kind == expected["next_query"]["kind"]
    assert q.items.tolist() == expected["next_query"]["items"]


def test_a_session_of_the_previous_release_resumes_with_the_same_posterior(tmp_path, monkeypatch):
    path, expected = _fixture(tmp_path)
    assert "model" not in read_session_file(path)[0]  # written before the header recorded it
    with PreferenceSession.load(path) as s:
        _check_fixture(s, expected)

    # a newer release changes the session defaults: the old file still resumes as it was written
    from torchpref.models.preference_gp import PreferenceGP, default_covar_module

    def new_default(train_X):
        kernel = default_covar_module(train_X.shape[-1]).to(train_X)
        kernel.base_kernel.lengthscale = 0.35
        return PreferenceGP(train_X, covar_module=kernel)

    monkeypatch.setattr(session_mod, "default_session_model", new_default)
    monkeypatch.setattr(session_mod, "default_selector", lambda n, num_levels=None: RandomRankings(m=2))
    with PreferenceSession.load(path) as s:
        _check_fixture(s, expected)
    with pytest.raises(SessionSettingsError, match="records a model") as err:
        PreferenceSession.load(path, model_factory=new_default)
    assert err.value.setting == "model" and "migrate=True" in str(err.value) and "lengthscale" in str(err.value)
    with pytest.raises(SessionSettingsError, match="records a selector"):
        PreferenceSession.load(path, selector=RandomRankings(m=2))
    with PreferenceSession.load(path, model_factory=new_default, migrate=True) as s:  # asked for: migrated
        X = torch.tensor(read_session_file(path)[0]["candidates"]["items"], dtype=torch.float64)
        assert (s.predict(X)[0] - torch.tensor(expected["mean"], dtype=torch.float64)).abs().max() > 1e-3


def test_the_header_records_model_and_selector_and_a_resume_uses_them(tmp_path):
    X = pool(12)
    path = tmp_path / "s.jsonl"

    def factory(train_X):
        from torchpref.models.preference_gp import PreferenceGP, default_covar_module

        kernel = default_covar_module(2).to(train_X)
        kernel.base_kernel.lengthscale = 0.3
        return PreferenceGP(train_X, covar_module=kernel, ties_offered=True)

    with PreferenceSession(X, session_file=path, selector=RandomRankings(m=3), model_factory=factory, seed=1) as s:
        for _ in range(5):
            q = s.ask()
            s.tell(q, answer(q))
        live, nxt = s.predict(X), s.ask()
    header = read_session_file(path)[0]
    assert header["selector"] == {"class": "torchpref.selection.strategies.RandomRankings", "options": {"m": 3}}
    lengthscale = header["model"]["state"]["covar_module.base_kernel.raw_lengthscale"]
    assert lengthscale["shape"] == [1, 2] and header["model"]["settings"]["ties_offered"] is True
    with PreferenceSession.load(path) as r:  # neither given: the recorded ones are rebuilt
        assert isinstance(r.selector, RandomRankings) and r.selector.m == 3
        torch.testing.assert_close(r.predict(X), live, rtol=0, atol=1e-12)
        assert torch.equal(r.ask().items, nxt.items)

    class Mine(RandomRankings):  # not a torchpref class: not rebuilt from the file
        pass

    other = tmp_path / "t.jsonl"
    PreferenceSession(X, session_file=other, selector=Mine(m=3)).close()
    with pytest.raises(SessionSettingsError, match="cannot build it") as err:
        PreferenceSession.load(other)
    assert err.value.setting == "selector"
    PreferenceSession.load(other, selector=Mine(m=3)).close()  # the same one given: resumes
