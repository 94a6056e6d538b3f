"""A large pool's session file records the pool by reference (its size, first item and digest),
resumes with the items given, refuses other items, still reads files that wrote a large pool out,
and checks a resumed file's answers against the pool."""

import json

import pytest
import torch

import torchpref
from torchpref.selection import shortlist as sl
from torchpref.sessions import settings
from torchpref.sessions.errors import SessionFileError, SessionMismatchError

D = torch.float64


@pytest.fixture
def small_inline_max(monkeypatch):
    """Pools of more than 40 items by reference (the real bound, 10,000, is only larger)."""
    monkeypatch.setattr(settings, "POOL_INLINE_MAX", 40)


def _pool(N=60, seed=0):
    return torch.rand(N, 3, generator=torch.Generator().manual_seed(seed), dtype=D)


def _answer_two(s):
    for _ in range(2):
        q = s.ask()
        s.tell(q, 4 if q.kind == "rating" else 0)


def test_a_large_pool_is_recorded_by_reference_and_resumes_with_its_items(tmp_path, small_inline_max):
    X, path = _pool(), tmp_path / "s.jsonl"
    with torchpref.PreferenceSession(X, session_file=path) as s:
        _answer_two(s)
        asked = s.ask()
    header = json.loads(path.read_text().splitlines()[0])
    spec = header["candidates"]
    assert "items" not in spec and spec["num_items"] == 60 and spec["first_item"] == X[0].tolist()
    assert spec["sha256"] == settings.pool_digest(X) and len(spec["sha256"]) == 64
    with torchpref.PreferenceSession.load(path, X) as s:
        assert s.step == 2 and torch.equal(s.ask().items, asked.items)
    with pytest.raises(ValueError, match="by reference .*candidates=X"):
        torchpref.PreferenceSession.load(path)
    other = X.clone()
    other[7, 1] += 1e-12
    with pytest.raises(SessionMismatchError, match="a pool of 60 items, digest"):
        torchpref.PreferenceSession.load(path, other)


def test_a_file_that_wrote_a_large_pool_out_still_resumes(tmp_path, monkeypatch):
    X, path = _pool(), tmp_path / "old.jsonl"
    with torchpref.PreferenceSession(X, session_file=path) as s:  # the pool written out (60 <= 10,000)
        _answer_two(s)
    assert "items" in json.loads(path.read_text().splitlines()[0])["candidates"]
    monkeypatch.setattr(settings, "POOL_INLINE_MAX", 40)  # now this pool would be by reference
    with torchpref.PreferenceSession(X, session_file=path) as s:
        assert s.step == 2
    with pytest.raises(SessionMismatchError):
        torchpref.PreferenceSession(_pool(seed=1), session_file=path)


def test_a_resumed_files_answers_are_checked_against_the_pool(tmp_path, small_inline_max):
    X, path = _pool(), tmp_path / "s.jsonl"
    with torchpref.PreferenceSession(X, session_file=path) as s:
        q = s.ask()
        s.tell(q, 4 if q.kind == "rating" else 0)
    lines = path.read_text().splitlines()
    rec = json.loads(lines[1])
    rec["items"][0][0] += 0.5  # the items no longer the pool's rows it names
    path.write_text("\n".join([lines[0], json.dumps(rec)] + lines[2:]) + "\n")
    with pytest.raises(SessionFileError, match="not the pool's rows"):
        torchpref.PreferenceSession.load(path, X)


def test_a_prior_models_first_question_computes_few_pairs(monkeypatch):
    """Without answers every item's bound ties with the exact scores: one block of pairs, not N."""
    X = torch.rand(20_000, 4, generator=torch.Generator().manual_seed(0), dtype=D)
    model = settings.default_session_model(X[:1])
    pairs = []
    real = sl._pairs

    def counted(model, Xr, xb):
        pairs.append(Xr.shape[1])
        return real(model, Xr, xb)

    monkeypatch.setattr(sl, "_pairs", counted)
    rows = sl.shortlist_rows(model, X.unsqueeze(0), 64)
    assert rows.shape == (1, 64) and sum(pairs) <= 1024
