"""Large pools: the shortlist (torchpref/selection/shortlist.py) is found without the pool's joint
covariance, keeps what it promises (the incumbent, the likeliest to beat it, answered items),
chooses as the exact selector where it covers the pool, and a session over a large pool asks in
reasonable time."""

import time

import pytest
import torch
from torch.distributions import Normal

import torchpref
from torchpref.models.batch import BatchedPreferenceGP
from torchpref.models.kernels import fixed_rbf_kernel
from torchpref.selection import shortlist as sl
from torchpref.selection.combined import InformationAndProfile
from torchpref.selection.defaults import default_selector
from torchpref.selection.shortlist import SHORTLIST_ABOVE, Shortlisted, for_pool, shortlist_rows
from torchpref.selection.strategies import UCBC, InformationPerEffort, RandomMixed

D = torch.float64


def _model(X: torch.Tensor, seed: int = 0, n: int = 8) -> torchpref.PreferenceGP:
    """A model told about ``n`` of the pool's items: best-of-2 choices and two ratings."""
    g = torch.Generator().manual_seed(seed)
    rows = torch.randperm(X.shape[0], generator=g)[:n]
    u = -((X[rows] - 0.3) ** 2).sum(-1)
    pairs = torch.arange(n).reshape(-1, 2)
    comps = torch.where((u[pairs[:, 0]] > u[pairs[:, 1]]).unsqueeze(-1), pairs, pairs.flip(-1))
    return torchpref.PreferenceGP(
        X[rows],
        comps,
        torch.tensor([0.8, 0.3], dtype=D),
        torch.tensor([0, 1]),
        covar_module=fixed_rbf_kernel(0.2, 1.0, X[:2]),
        comparison_noise=0.1,
        rating_scale=1.0,
        rating_precision=20.0,
    )


def _pool(N: int, d: int = 4, seed: int = 1) -> torch.Tensor:
    return torch.rand(N, d, generator=torch.Generator().manual_seed(seed), dtype=D)


def test_a_pool_of_200k_items_never_builds_a_large_joint_covariance(monkeypatch):
    """Every joint posterior asked for has at most the shortlist's size of points (the exact
    selector's, on the shortlist); the pool's 200,000 items are only ever seen as marginals or pairs."""
    X = _pool(200_000)
    model = _model(X)
    seen = []
    predict = torchpref.PreferenceGP._predict

    def guarded(self, Xt, diag=False):
        if not diag:
            seen.append(Xt.shape[-2])
            assert Xt.shape[-2] <= 256, f"a joint covariance of {Xt.shape[-2]} points"
        return predict(self, Xt, diag)

    monkeypatch.setattr(torchpref.PreferenceGP, "_predict", guarded)
    q = Shortlisted(default_selector(200_000)).select(model, X, torch.arange(200_000), 0, 14, torch.Generator())
    assert seen and max(seen) == 256 and min(seen) == 2  # the pairs, and the exact selector's shortlist
    rows = [q.index] if q.kind == "rating" else list(q.indices)
    assert all(0 <= i < 200_000 for i in rows) and torch.equal(X[rows], q.items)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_shortlist_keeps_the_incumbent_the_answered_items_and_the_likeliest_to_beat_it(seed):
    X = _pool(3000, seed=seed)
    model = _model(X, seed)
    rows = shortlist_rows(model, X.unsqueeze(0), 64)[0]
    assert rows.shape == (64,) and rows.unique().numel() == 64
    mean, var = model.marginals(X)
    assert int(mean.argmax()) in rows.tolist()
    answered = [int(((X == x).all(-1)).nonzero()) for x in model.train_X]
    assert set(answered) <= set(rows.tolist())
    # the likeliest 8 to beat the incumbent (its eighth), by brute force over every pair
    b = int(mean.argmax())
    post = model.posterior(torch.stack([X, X[b].expand_as(X)], dim=-2))
    cov = post.distribution.covariance_matrix
    z = (post.mean[..., 0, 0] - post.mean[..., 1, 0]) / (cov[:, 0, 0] + cov[:, 1, 1] - 2 * cov[:, 0, 1]).sqrt()
    z[b] = torch.inf
    assert set(z.topk(8).indices.tolist()) <= set(rows.tolist())
    assert set(mean.topk(8).indices.tolist()) <= set(rows.tolist())
    ranks = mean.argsort(descending=True).argsort()[rows]  # the pool's ranks are all represented
    assert all(((ranks >= lo) & (ranks < lo + 500)).sum() >= 3 for lo in range(0, 3000, 500))
    # and the pruned scores equal the brute force where computed
    beat = sl._beat_order(
        model, X.unsqueeze(0), mean.unsqueeze(0), var.sqrt().unsqueeze(0), mean.argmax(-1, True), 64, 500
    )
    done = torch.isfinite(beat[0]) & (torch.arange(3000) != b)
    assert done.sum() >= 64 and torch.allclose(beat[0][done], z[done], rtol=1e-9, atol=1e-9)
    assert set(beat[0].topk(64).indices.tolist()) == set(z.topk(64).indices.tolist())
    assert Normal(0.0, 1.0).cdf(z[z.isfinite()]).max() < 1  # probabilities, not certainties


@pytest.mark.parametrize("selector", [InformationAndProfile(m=3, decide="sum"), InformationPerEffort(m=3)])
def test_where_the_shortlist_covers_the_pool_the_choice_is_the_exact_one(selector):
    X = _pool(40)
    model = _model(X)
    idx = torch.arange(40)
    exact = selector.select(model, X, idx, 2, 14, torch.Generator().manual_seed(3))
    short = Shortlisted(selector, size=40).select(model, X, idx, 2, 14, torch.Generator().manual_seed(3))
    assert (exact.kind, exact.items.tolist()) == (short.kind, short.items.tolist())
    # a shortlist of all but the items it cannot choose: the same choice, with its pool rows
    pool = Shortlisted(selector, size=39).select(model, X, idx, 2, 14, torch.Generator().manual_seed(3))
    assert pool.kind in ("rating", "ranking") and (pool.index if pool.kind == "rating" else pool.indices) is not None
    none = Shortlisted(selector, size=39).select(model, X, None, 2, 14, torch.Generator().manual_seed(3))
    assert (none.index if none.kind == "rating" else none.indices) is None


def test_batched_trials_get_each_trials_own_shortlist_and_choice():
    X = torch.stack([_pool(600, seed=1), _pool(600, seed=2)])
    models = [_model(X[0], 0), _model(X[1], 1)]
    sel = Shortlisted(InformationAndProfile(m=3), size=64)
    gens = lambda: [torch.Generator().manual_seed(5), torch.Generator().manual_seed(6)]  # noqa: E731
    batch = sel.select_batch(BatchedPreferenceGP.from_models(models), X, [None, None], 0, 14, gens())
    for b in range(2):
        alone = sel.select(models[b], X[b], None, 0, 14, gens()[b])
        assert batch[b].kind == alone.kind and torch.allclose(batch[b].items, alone.items)


def test_bad_settings_are_refused_by_name():
    with pytest.raises(ValueError, match="size must be a whole number >= 1, got 0"):
        Shortlisted(UCBC(), size=0)
    with pytest.raises(ValueError, match="chunk must be"):
        Shortlisted(UCBC(), chunk=2.5)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="selector must be a Selector"):
        Shortlisted("ucbc")  # type: ignore[arg-type]


def test_sessions_shortlist_large_pools_of_selectors_that_are_not_linear():
    big = SHORTLIST_ABOVE + 1
    assert isinstance(for_pool(default_selector(big), big), Shortlisted)
    assert not isinstance(for_pool(default_selector(SHORTLIST_ABOVE), SHORTLIST_ABOVE), Shortlisted)
    assert not isinstance(for_pool(default_selector(None), None), Shortlisted)  # not known
    for linear in (UCBC(), RandomMixed()):
        assert for_pool(linear, 10**6) is linear
    wrapped = for_pool(default_selector(big), big)
    assert for_pool(wrapped, big) is wrapped and wrapped.m == 5


def test_a_session_over_50k_items_asks_within_reason(tmp_path):
    """Twelve answers, each question within seconds of CPU (the benchmark measures it properly);
    no item is rated twice."""
    X = _pool(50_000)
    s = torchpref.PreferenceSession(X, session_file=tmp_path / "s.jsonl", num_queries=14)
    cpu = []
    rated = []
    for _ in range(12):
        t = time.process_time()
        q = s.ask()
        cpu.append(time.process_time() - t)
        if q.kind == "rating":
            rated.append(q.index)
            s.tell(q, 3)
        else:
            s.tell(q, 0)
    assert len(rated) == len(set(rated))
    assert sorted(cpu)[len(cpu) // 2] < 5.0, cpu
