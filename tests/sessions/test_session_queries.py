"""A session over a fixed list of candidate queries: it asks the selector's choice among those not
yet answered, records the list in its header, resumes with it, and refuses lists that do not fit."""

import itertools

import pytest
import torch

from torchpref import BoxCandidates, RankingQuery, RatingQuery
from torchpref.selection import VariancePerEffort
from torchpref.sessions.errors import SessionMismatchError
from torchpref.sessions.session import PreferenceSession

D = torch.float64


def _pool(n=6, seed=0):
    return torch.rand(n, 2, generator=torch.Generator().manual_seed(seed), dtype=D)


def _queries(X):
    pairs = [RankingQuery(X[list(p)]) for p in itertools.combinations(range(3), 2)]
    return pairs + [RatingQuery(X[4]), RatingQuery(X[5])]


def _answer(q):
    return 3 if q.kind == "rating" else int(q.items.sum(-1).argmax())


def _key(q):
    return (q.kind, sorted(q.items.tolist()))


def test_asks_each_given_query_once_then_again(tmp_path):
    X = _pool()
    queries = _queries(X)
    s = PreferenceSession(X, queries=queries, session_file=tmp_path / "s.jsonl", num_queries=7)
    asked = []
    for _ in range(len(queries)):
        q = s.ask()
        assert q is s.ask()  # stable until answered
        asked.append(_key(q))
        s.tell(q, _answer(q))
    assert sorted(asked) == sorted(_key(q) for q in queries)  # every one, none twice
    nxt, header = s.ask(), s._journal.header
    assert _key(nxt) in asked  # then the list again
    s.close()
    with PreferenceSession.load(tmp_path / "s.jsonl") as resumed:
        assert _key(resumed.ask()) == _key(nxt)  # same list, same choice
        assert resumed._journal.header["queries"] == header["queries"]


def test_queries_alone_make_the_pool_and_choose_is_used():
    X = _pool()
    s = PreferenceSession(queries=_queries(X), selector=VariancePerEffort(m=2))
    assert s._pool.shape == (5, 2)  # the five distinct items shown
    q = s.ask()
    assert any(_key(q) == _key(o) for o in _queries(X))


def test_bad_query_lists_are_refused(tmp_path):
    X = _pool()
    with pytest.raises(ValueError, match="candidates"):
        PreferenceSession(X[:3], queries=_queries(X))  # items outside the pool
    with pytest.raises(ValueError, match="box"):
        PreferenceSession(BoxCandidates(torch.tensor([[0.0, 0.0], [1.0, 1.0]], dtype=D)), queries=_queries(X))
    with pytest.raises(ValueError, match="non-empty"):
        PreferenceSession(X, queries=[])
    with pytest.raises(ValueError, match="candidates"):
        PreferenceSession()
    PreferenceSession(X, queries=_queries(X), session_file=tmp_path / "a.jsonl").close()
    with pytest.raises(SessionMismatchError, match="queries"):
        PreferenceSession(X, queries=_queries(X)[:2], session_file=tmp_path / "a.jsonl")
