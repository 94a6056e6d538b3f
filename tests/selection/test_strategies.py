"""Selectors return valid queries; UCBC's schedule; UCB ratings is the argmax of eq. 12."""

import pytest
import torch

from torchpref.data.queries import RankingQuery, RatingQuery
from torchpref.experiments.wave import make_model
from torchpref.selection.strategies import (
    UCBC,
    InformationPerEffort,
    RandomMixed,
    RandomRankings,
    RandomRatings,
    UCBRatings,
)
from torchpref.selection.top_profile import ProfileVariancePerEffort
from torchpref.selection.variance_reduction import VariancePerEffort


@pytest.fixture
def model():
    X = torch.tensor([[0.1], [0.4], [0.45], [0.8]], dtype=torch.float64)
    C = torch.tensor([[1, 0], [1, 3], [2, 3]])
    m = make_model(X, C)
    m.add_observations(torch.tensor([[0.42]], dtype=torch.float64), ratings=[0.8], rating_index=[0])
    return m


SELECTORS = [
    RandomRatings(),
    RandomRankings(m=4),
    RandomMixed(m=3),
    UCBRatings(),
    UCBC(m=5),
    InformationPerEffort(m=4),
    InformationPerEffort(m=4, target="maximizer"),
    InformationPerEffort(m=3, target="utility", ranking_cost=5.0),
    VariancePerEffort(m=4),
    ProfileVariancePerEffort(m=4),
]


@pytest.mark.parametrize("selector", SELECTORS, ids=lambda s: type(s).__name__)
@pytest.mark.parametrize("pool", [False, True])
def test_valid_queries(model, selector, pool, generator):
    X = torch.rand(30, 1, generator=generator, dtype=torch.float64)
    idx = torch.arange(100, 130) if pool else None
    for step in range(4):
        q = selector.select(model, X, idx, step, 4, generator)
        assert isinstance(q, (RatingQuery, RankingQuery))
        if isinstance(q, RatingQuery):
            row = (X == q.item).all(-1).nonzero().reshape(-1)
            assert row.numel() == 1
            assert (q.index == 100 + int(row)) if pool else q.index is None
        else:
            rows = [int((X == x).all(-1).nonzero()) for x in q.items]
            assert len(set(rows)) == q.m >= 2
            assert (q.indices == tuple(100 + r for r in rows)) if pool else q.indices is None


def test_ucbc_schedule(model, generator):
    sel = UCBC()
    assert [sel.ranking_probability(t, 4) for t in range(4)] == [1.0, 0.75, 0.5, 0.25]
    assert sel.ranking_probability(5, 4) == 0.0
    X = torch.rand(20, 1, generator=generator, dtype=torch.float64)
    assert isinstance(sel.select(model, X, None, 0, 10, generator), RankingQuery)  # probability 1
    # frequency of rankings at step t of T is (T - t) / T
    kinds = [sel.select(model, X, None, 6, 8, generator).kind for _ in range(400)]
    assert abs(kinds.count("ranking") / 400 - 0.25) < 0.07


def test_ucbc_ranking_softmax_temperature(model, generator):
    """The ranking draw is a softmax of UCB / T: a tiny T takes the top-UCB candidates, a huge T
    draws near-uniformly (the authors' 5 and 25 are close to the latter)."""
    X = torch.rand(12, 1, generator=generator, dtype=torch.float64)
    with torch.no_grad():
        post = model.posterior(X.unsqueeze(-2))
        ucb = post.mean.reshape(-1) + 3.0 * post.variance.reshape(-1).sqrt()
    top3 = ucb.sort(descending=True).values[:3]  # values: far from the data UCBs tie

    def first_rows(temperature, draws):
        sel = UCBC(m=3, temperatures=(temperature, temperature))
        out = []
        for _ in range(draws):
            q = sel.select(model, X, None, 0, 10, generator)  # step 0: always a ranking
            out.append({int((X == x).all(-1).nonzero()) for x in q.items})
        return out

    for rows in first_rows(1e-6, 20):
        torch.testing.assert_close(ucb[sorted(rows)].sort(descending=True).values, top3, rtol=0, atol=1e-4)
    hits = sum(0 in rows for rows in first_rows(1e4, 600)) / 600
    assert abs(hits - 3 / 12) < 0.07  # uniform: each item in a 3-of-12 draw with probability 1/4


def test_ucb_ratings_is_argmax(model, generator):
    X = torch.rand(50, 1, generator=generator, dtype=torch.float64)
    with torch.no_grad():
        post = model.posterior(X.unsqueeze(-2))
        ucb = post.mean.reshape(-1) + 3.0 * post.variance.reshape(-1).sqrt()
        # independently: mean and variance from the Laplace formulas
        K = model.covar_module(model.train_X).to_dense()
        ks = model.covar_module(X, model.train_X).to_dense()
        W = model.W()
        f = model.mode.f
        mean = ks @ torch.linalg.solve(K + 1e-10 * torch.eye(K.shape[0], dtype=K.dtype), f)
        prior_var = model.covar_module.outputscale  # k(x, x) of the experiment's RBF kernel
        var = prior_var - (
            ks * torch.linalg.solve(K + torch.linalg.inv(W + 1e-12 * torch.eye(K.shape[0], dtype=K.dtype)), ks.mT).mT
        ).sum(-1)
    torch.testing.assert_close(post.mean.reshape(-1), mean, atol=1e-5, rtol=1e-5)
    q = UCBRatings(gamma=3.0).select(model, X, None, 0, 1, generator)
    assert torch.equal(q.item, X[int((mean + 3.0 * var.clamp_min(0).sqrt()).argmax())])
    assert torch.equal(q.item, X[int(ucb.argmax())])


def test_bad_arguments():
    with pytest.raises(ValueError, match="-1"):
        InformationPerEffort(rating_cost=-1)
    with pytest.raises(ValueError, match="entropy"):
        InformationPerEffort(target="entropy")
    with pytest.raises(ValueError, match="top_fraction"):
        InformationPerEffort(top_fraction=1.0)


@pytest.mark.parametrize("target", ["top", "maximizer"])
def test_information_per_effort_costs_and_determinism(model, target, generator):
    X = torch.rand(40, 1, generator=generator, dtype=torch.float64)
    kinds = {}
    for name, kw in {"cheap ratings": {"ranking_cost": 1e6}, "cheap rankings": {"rating_cost": 1e6}}.items():
        sel = InformationPerEffort(m=4, target=target, **kw)
        q1 = sel.select(model, X, None, 0, 5, torch.Generator().manual_seed(7))
        q2 = sel.select(model, X, None, 0, 5, torch.Generator().manual_seed(7))
        kinds[name] = q1.kind
        a = q1.item if q1.kind == "rating" else q1.items
        b = q2.item if q2.kind == "rating" else q2.items
        assert torch.equal(a, b)  # same generator state, same query
    assert kinds == {"cheap ratings": "rating", "cheap rankings": "ranking"}


def test_top_target_avoids_known_bad_region(generator):
    """Low ratings all over [0, 0.5]: every item of the queries lies in the unexplored half,
    where membership of the top set is uncertain."""
    X0 = torch.linspace(0, 0.5, 26, dtype=torch.float64).reshape(-1, 1)
    m = make_model(X0[:2], torch.tensor([[1, 0]]))
    m.add_observations(X0, ratings=[0.1] * 26, rating_index=list(range(26)))
    sel = InformationPerEffort(m=5, ranking_cost=1.0)
    for t in range(3):
        X = torch.rand(100, 1, generator=generator, dtype=torch.float64)
        q = sel.select(m, X, None, t, 3, generator)
        items = q.item.reshape(-1) if q.kind == "rating" else q.items.reshape(-1)
        assert (items > 0.52).all(), items


def test_ucb_selectors_take_any_botorch_model():
    """Without ``marginals`` (here BoTorch's PairwiseGP) the UCB selectors use ``posterior``."""
    from botorch.models import PairwiseGP

    from torchpref.selection.strategies import UCBC, UCBRatings

    g = torch.Generator().manual_seed(0)
    X = torch.rand(6, 1, generator=g, dtype=torch.float64)
    model = PairwiseGP(X, torch.tensor([[0, 1], [2, 3], [4, 5]]))
    cand = torch.rand(30, 1, generator=g, dtype=torch.float64)
    post = model.posterior(cand.unsqueeze(-2))
    ucb = post.mean.reshape(-1) + 3.0 * post.variance.reshape(-1).sqrt()
    q = UCBRatings(gamma=3.0).select(model, cand, None, 0, 5, g)
    assert torch.equal(q.item, cand[int(ucb.argmax())])
    assert UCBC(m=3).select(model, cand, None, 0, 5, g).kind in ("rating", "ranking")
