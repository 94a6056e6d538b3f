"""The active-learning loop: records, observations, metrics, refits, callbacks, seeds."""

import pytest
import torch

import torchpref.selection.active as active
from torchpref.data.queries import BoxCandidates, RankingQuery, RatingQuery
from torchpref.experiments.wave import make_model
from torchpref.selection.active import run_active_learning
from torchpref.selection.strategies import RandomMixed
from torchpref.simulation.users import SimulatedUser
from torchpref.simulation.utility_functions import WaveFunction

BOUNDS = torch.tensor([[0.0], [1.0]], dtype=torch.float64)


def _setup(seed: int):
    g = torch.Generator().manual_seed(seed)
    truth = WaveFunction.random(generator=g)
    user = SimulatedUser.paper_wave(lambda X: truth(X, noise=False), generator=torch.Generator().manual_seed(seed + 1))
    x0 = torch.tensor([[0.2], [0.7]], dtype=torch.float64)
    first = user.choose(x0)
    return make_model(x0, torch.tensor([[first, 1 - first]])), user


def _run(seed=0, q=6, **kw):
    model, user = _setup(seed)
    hist = run_active_learning(
        model,
        user,
        BoxCandidates(BOUNDS, 20),
        RandomMixed(m=3),
        q,
        generator=torch.Generator().manual_seed(seed + 2),
        metrics=lambda m: {"mean0": float(m.posterior(BOUNDS[:1]).mean.detach())},
        **kw,
    )
    return model, hist


def test_records_and_observations():
    model, hist = _run(q=8)
    assert len(hist.records) == 8 and len(hist.metrics) == 9 and hist.model is model
    n_items, n_cmp, ratings = 2, 1, []
    for r in hist.records:
        if isinstance(r.query, RatingQuery):
            assert 0 <= r.answer <= 1
            ratings.append(r.answer)
            n_items += 1
        else:
            assert isinstance(r.query, RankingQuery) and 0 <= r.answer < r.query.m
            n_items += r.query.m
            n_cmp += r.query.m - 1
    assert model.train_X.shape[0] == n_items
    assert model.comparisons.shape[0] == n_cmp
    torch.testing.assert_close(
        model.ratings, torch.tensor(ratings, dtype=torch.float64).clamp(1e-6, 1 - 1e-6), atol=1e-5, rtol=0
    )
    # each query's items are in the model, in order, and the ranking's winner is preferred
    row = 2
    for r in hist.records:
        items = r.query.items
        torch.testing.assert_close(model.train_X[row : row + items.shape[0]], items)
        row += items.shape[0]
    assert hist.cumulative_cost()[-1] == pytest.approx(8.0)


def test_seeds_give_identical_histories():
    _, h1 = _run(seed=3)
    _, h2 = _run(seed=3)
    _, h3 = _run(seed=4)
    assert [r.answer for r in h1.records] == [r.answer for r in h2.records]
    assert h1.metrics == h2.metrics
    assert h1.metrics != h3.metrics


def test_refit_every_and_callback(monkeypatch):
    calls, seen = [], []
    monkeypatch.setattr(active, "fit_model", lambda m: calls.append(m.train_X.shape[0]) or m)
    _, hist = _run(q=7, refit_every=3, callback=lambda step, rec, model, met: seen.append((step, rec, met)))
    assert len(calls) == 2  # after queries 3 and 6
    assert [s for s, _, _ in seen] == list(range(7))
    assert [rec for _, rec, _ in seen] == hist.records
    assert [met for _, _, met in seen] == hist.metrics[1:]


def test_bad_input():
    model, user = _setup(0)
    with pytest.raises(ValueError, match="-1"):
        run_active_learning(model, user, BoxCandidates(BOUNDS), RandomMixed(), -1, generator=torch.Generator())
    with pytest.raises(ValueError, match="0"):
        run_active_learning(
            model, user, BoxCandidates(BOUNDS), RandomMixed(), 2, generator=torch.Generator(), refit_every=0
        )


def test_pool_with_repeated_rows_never_shows_an_item_twice():
    """``FinitePool`` offers each distinct item once (first row's index), so random rankings of a
    pool full of duplicates still compare distinct items and the loop runs."""
    from torchpref.data.queries import FinitePool
    from torchpref.selection.strategies import RandomRankings

    base = torch.tensor([[0.1], [0.3], [0.5], [0.9]], dtype=torch.float64)
    pool = base[torch.tensor([0, 1, 1, 2, 0, 3, 3, 3])]
    X, idx = FinitePool(pool).draw(torch.Generator())
    assert idx.tolist() == [0, 1, 3, 5]
    torch.testing.assert_close(X, pool[idx])
    model, user = _setup(4)
    hist = run_active_learning(
        model, user, FinitePool(pool), RandomRankings(m=4), 5, generator=torch.Generator().manual_seed(0)
    )
    for r in hist.records:
        assert len({float(x) for x in r.query.items.reshape(-1)}) == 4
