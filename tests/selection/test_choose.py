"""Choosing among given queries: every built-in selector's ``choose`` values the queries as its
``select`` values the ones it builds (over all ratings and pairs of a small pool it returns the
query ``select`` asks), ties go to the first query, and bad lists are refused by name."""

import itertools

import pytest
import torch

import torchpref
from torchpref.data.queries import RankingQuery, RatingQuery
from torchpref.models.kernels import fixed_rbf_kernel
from torchpref.selection import (
    UCBC,
    InformationPerEffort,
    ProfileVariancePerEffort,
    RandomMixed,
    RandomRankings,
    RandomRatings,
    UCBRatings,
    VariancePerEffort,
)
from torchpref.selection.choosing import query_items
from torchpref.selection.per_second import ProfilePerSecond

D = torch.float64
N = 7


def _case(seed=5):
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(N, 2, generator=g, dtype=D)
    model = torchpref.PreferenceGP(
        X[:4],
        torch.tensor([[0, 1], [2, 3]]),
        torch.tensor([0.8, 0.3], dtype=D),
        torch.tensor([0, 3]),
        covar_module=fixed_rbf_kernel(0.2, 1.0, X),
        comparison_noise=0.1,
        rating_scale=0.8,
        rating_precision=10.0,
    )
    return model, X


def _all_queries(X):
    """Every rating (first, so they fix the items' order) and every pair of the pool."""
    ratings = [RatingQuery(X[i], i) for i in range(N)]
    pairs = [RankingQuery(X[list(p)], p) for p in itertools.combinations(range(N), 2)]
    return ratings + pairs


def _same(a, b):
    return a.kind == b.kind and torch.equal(a.items, b.items)


SELECTORS = [
    lambda: VariancePerEffort(m=2, rating_cost=1.0, ranking_cost=1.3),
    lambda: ProfileVariancePerEffort(m=2, rating_cost=1.0, ranking_cost=1.3),
    lambda: ProfileVariancePerEffort(m=2, rating_cost=1.0, ranking_cost=1.3, clipped=True),
    lambda: ProfilePerSecond(m=2, rating_seconds=1.0, ranking_seconds=1.3),
    lambda: UCBRatings(),
    lambda: UCBC(m=2),
]


@pytest.mark.parametrize("make", SELECTORS)
@pytest.mark.parametrize("seed", [5, 6])
def test_choose_over_the_queries_select_builds_returns_selects_query(make, seed):
    model, X = _case(seed)
    sel, queries = make(), _all_queries(X)
    step, num_steps = (3, 3) if isinstance(sel, UCBC) else (0, 10)  # UCBC: its rating branch (p = 0)
    picked = sel.select(model, X, torch.arange(N), step, num_steps, torch.Generator().manual_seed(1))
    i = sel.choose(model, queries, step=step, num_steps=num_steps, generator=torch.Generator().manual_seed(1))
    assert _same(queries[i], picked), (type(sel).__name__, queries[i], picked)


def test_information_selector_chooses_at_least_as_informative_a_query():
    """InformationPerEffort builds its ranking greedily from the most uncertain item; over every
    pair, choose's pick is worth at least select's (same samples, same value)."""
    model, X = _case()
    sel = InformationPerEffort(m=2, rating_cost=1.0, ranking_cost=1.3, num_plausible=N)
    queries = _all_queries(X)
    picked = sel.select(model, X, torch.arange(N), 0, 10, torch.Generator().manual_seed(1))
    i = sel.choose(model, queries, step=0, num_steps=10, generator=torch.Generator().manual_seed(1))
    qr = query_items(queries)
    rating_fn, ranking_fn = sel.scorers(model, qr.X.unsqueeze(0), [torch.Generator().manual_seed(1)])

    def value(q):
        rows = qr.rows[[_same(q, r) for r in queries].index(True)]
        v = rating_fn(rows.reshape(1, 1)) if q.kind == "rating" else ranking_fn(rows.reshape(1, 1, -1))
        return float(v) / sel.query_cost(rows.numel() if q.kind == "ranking" else 1)

    assert value(queries[i]) >= value(picked) - 1e-12
    if picked.kind == "rating":
        assert _same(queries[i], picked)


def test_a_lapsing_persons_pairs_are_valued_less():
    """Through the likelihood: with a large lapse rate the best pair is worth much less."""
    model, X = _case()
    sel = ProfilePerSecond(m=2, rating_seconds=1.0, ranking_seconds=1.0)
    qr = query_items(_all_queries(X))
    pairs = torch.stack(qr.rows[N:]).unsqueeze(0)

    def best_pair(eps):
        torchpref.calibrate_person(model, lapse_rate=eps)
        return float(sel.scorers(model, qr.X.unsqueeze(0), [torch.Generator().manual_seed(0)])[1](pairs).max())

    reliable, lapsing = best_pair(1e-5), best_pair(0.45)
    assert 0 < lapsing < 0.5 * reliable


@pytest.mark.parametrize("make,kind", [(RandomRatings, "rating"), (lambda: RandomRankings(m=2), "ranking")])
def test_random_selectors_choose_uniformly_among_their_kind(make, kind):
    model, X = _case()
    queries = _all_queries(X)
    g = torch.Generator().manual_seed(0)
    picks = [make().choose(model, queries, generator=g) for _ in range(2000)]
    assert all(queries[i].kind == kind for i in picks)
    counts = torch.bincount(torch.tensor(picks), minlength=len(queries)).to(D)
    ours = counts[[i for i, q in enumerate(queries) if q.kind == kind]]
    assert ours.min() > 0.5 * ours.mean()  # every one of its kind is drawn, none much less often
    mixed = [queries[RandomMixed(m=2, p_ranking=0.5).choose(model, queries, generator=g)].kind for _ in range(400)]
    assert 120 < mixed.count("rating") < 280


def test_ucbc_ranking_branch_prefers_high_ucb_sets():
    model, X = _case()
    pairs = _all_queries(X)[N:]
    sel = UCBC(m=2, temperatures=(0.05, 0.05))  # a cold softmax: the set of the largest UCBs
    ucb = torchpref.acquisition.functions.item_ucb(model, X, 3.0)[0]
    best = set(ucb.argsort(descending=True)[:2].tolist())
    i = sel.choose(model, pairs, step=0, num_steps=10, generator=torch.Generator().manual_seed(0))
    assert set(pairs[i].indices) == best


def test_ties_go_to_the_first_query_and_bad_lists_are_refused():
    model, X = _case()
    q = RatingQuery(X[5])
    assert VariancePerEffort(m=2).choose(model, [q, q, q], generator=torch.Generator().manual_seed(0)) == 0
    with pytest.raises(ValueError, match="non-empty"):
        UCBC().choose(model, [], generator=torch.Generator())
    with pytest.raises(ValueError, match=r"queries\[1\]"):
        UCBC().choose(model, [q, "rate item 3"], generator=torch.Generator())
    with pytest.raises(ValueError, match="twice"):
        UCBC().choose(model, [RankingQuery(X[[1, 1]])], generator=torch.Generator())


def test_default_selector():
    """The default (docs/selection.md, docs/real_raters.md): information about the order of the
    likeliest maximisers, per second of the plain effort model, rankings of the size worth most, a
    rating valued by the levels it can take; a session records it and rebuilds it from its header."""
    from torchpref.data.effort import EffortModel
    from torchpref.selection.combined import InformationAndProfile
    from torchpref.sessions.recorded import describe_selector, recorded_selector

    sel = torchpref.default_selector()
    assert isinstance(sel, InformationAndProfile) and sel.decide == "order" and sel.m == 5 and sel.choose_size
    assert (sel.rating_cost, sel.ranking_cost) == (3.4, 6.1) and sel.num_bins == 10
    effort = EffortModel.plain()
    assert [sel.query_cost(q) for q in range(1, 6)] == [effort.rating()] + [effort.ranking(q) for q in range(2, 6)]
    small = torchpref.default_selector(3)
    assert small.m == 2 and small.ranking_cost == 3.4
    assert torchpref.default_selector(10, num_levels=5).num_bins == 5
    desc = describe_selector(sel)
    assert "unrecorded" not in desc and describe_selector(recorded_selector(desc)) == desc
