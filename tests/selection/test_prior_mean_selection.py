"""Selection on a person model with a prior mean (issue 41): every built-in selector and BoTorch's
qEUBO run on ``pop.person_model(...)`` and on the batched model of such models; a selector's
values move with the prior mean where they should and only there."""

import pytest
import torch
from botorch.acquisition.preference import qExpectedUtilityOfBestOption
from gpytorch.means import ConstantMean, Mean

import torchpref
from torchpref.data.preference_data import PreferenceData
from torchpref.models.batch import BatchedPreferenceGP
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
from torchpref.selection.combined import InformationAndProfile
from torchpref.selection.eubo import ExpectedBestOption
from torchpref.selection.per_second import ProfilePerSecond
from torchpref.selection.robust import EpsilonExplore

D = torch.float64


@pytest.fixture(scope="module")
def pop_and_pool():
    g = torch.Generator().manual_seed(11)
    pool = torch.rand(9, 2, generator=g, dtype=D)
    u = 2 * pool[:, 0] - pool[:, 1]
    people = []
    for _ in range(10):
        idx = torch.randperm(9, generator=g)[:6]
        C = [[i, j] if u[idx[i]] > u[idx[j]] else [j, i] for i, j in [(0, 1), (2, 3), (4, 5), (1, 2), (3, 4)]]
        people.append(PreferenceData.create(pool[idx], torch.tensor(C)))
    return torchpref.fit_population(people, max_iter=5), pool


SELECTORS = [
    lambda: UCBC(m=3),
    lambda: UCBRatings(),
    lambda: RandomRatings(),
    lambda: RandomRankings(m=3),
    lambda: RandomMixed(m=3),
    lambda: InformationPerEffort(m=3, num_samples=64),
    lambda: InformationPerEffort(m=3, num_samples=64, target="utility"),
    lambda: InformationPerEffort(m=3, num_samples=64, target="top+levels"),
    lambda: InformationPerEffort(m=3, num_samples=64, target="maximizer"),
    lambda: VariancePerEffort(m=3, num_samples=64),
    lambda: ProfileVariancePerEffort(m=3, num_samples=64),
    lambda: ProfileVariancePerEffort(m=3, num_samples=64, clipped=True),
    lambda: ProfilePerSecond(m=3, num_samples=64),
    lambda: InformationAndProfile(m=3, num_samples=64),
    lambda: InformationAndProfile(m=3, num_samples=64, decide="profile"),
    lambda: InformationAndProfile(m=3, num_samples=64, decide="sum"),
    lambda: ExpectedBestOption(m=3, num_samples=64),
    lambda: EpsilonExplore(InformationPerEffort(m=3, num_samples=64), 0.5),
]


def _person(pop, pool, k):
    C = torch.tensor([[k, k + 1]])
    return pop.person_model(PreferenceData.create(pool, C), rating_precision=20.0)


@pytest.mark.parametrize("make", SELECTORS)
def test_every_selector_runs_on_a_person_model_and_its_batch_alike(make, pop_and_pool):
    """On pop.person_model and on a BatchedPreferenceGP of three of them, each trial's query is the
    single model's (same posterior, same generator)."""
    pop, pool = pop_and_pool
    models = [_person(pop, pool, k) for k in range(3)]
    batch = BatchedPreferenceGP.from_models(models)
    X = pool.expand(3, *pool.shape)
    idx = [torch.arange(9)] * 3
    together = make().select_batch(batch, X, idx, 1, 10, [torch.Generator().manual_seed(k) for k in range(3)])
    for k, model in enumerate(models):
        alone = make().select(model, pool, torch.arange(9), 1, 10, torch.Generator().manual_seed(k))
        assert alone.kind == together[k].kind and torch.equal(alone.items, together[k].items)


class _Bump(Mean):
    """A prior mean of ``height`` at one item, 0 elsewhere."""

    def __init__(self, item, height):
        super().__init__()
        self.item, self.height = item, height

    def forward(self, x):
        return self.height * ((x - self.item).abs().amax(-1) < 1e-12).to(x)


def _gp(X, mean=None):
    return torchpref.PreferenceGP(
        X[:4], torch.tensor([[0, 1], [2, 3]]), covar_module=fixed_rbf_kernel(0.3, 1.0, X), mean_module=mean
    )


def test_ucb_selectors_follow_a_raised_prior_mean():
    X = torch.rand(8, 2, generator=torch.Generator().manual_seed(2), dtype=D)
    for j in (5, 6):
        model = _gp(X, _Bump(X[j], 4.0))
        q = UCBRatings().select(model, X, torch.arange(8), 0, 10, torch.Generator())
        assert q.index == j
        q = ExpectedBestOption(m=2, num_samples=256).select(model, X, torch.arange(8), 0, 10, torch.Generator())
        assert j in q.indices


def _constant(c):
    mean = ConstantMean().double()
    mean.constant.data.fill_(c)
    return mean


def test_a_constant_prior_mean_moves_ratings_values_not_rankings():
    """Comparisons see differences: with a constant prior mean c the samples shift by c, so a
    ranking's information is unchanged to rounding and its qEUBO moves by exactly c; a rating's
    answer depends on the level, so its information changes."""
    X = torch.rand(8, 2, generator=torch.Generator().manual_seed(3), dtype=D)
    rows2 = torch.tensor([[[0, 5], [2, 7], [1, 6]]])
    rows1 = torch.tensor([[4, 6, 7]])
    sel = InformationPerEffort(m=2, num_samples=128, target="utility")
    values = {}
    for c in (0.0, 1.5):
        with torch.no_grad():
            rate, rank = sel.scorers(_gp(X, _constant(c)), X.unsqueeze(0), [torch.Generator().manual_seed(0)])
            values[c] = rate(rows1), rank(rows2)
    torch.testing.assert_close(values[1.5][1], values[0.0][1], rtol=1e-7, atol=1e-9)
    assert float((values[1.5][0] - values[0.0][0]).abs().max()) > 1e-3
    from torchpref.selection.eubo import expected_best_option
    from torchpref.selection.samples import joint_posterior, joint_samples

    eubo = {}
    for c in (0.0, 1.5):
        mean, cov = joint_posterior(_gp(X, _constant(c)), X.unsqueeze(0))
        F, _ = joint_samples(mean, cov, [torch.Generator().manual_seed(0)], 64)
        eubo[c] = expected_best_option(F, rows2)
    torch.testing.assert_close(eubo[1.5], eubo[0.0] + 1.5)


def test_botorchs_qeubo_runs_on_a_person_model_and_agrees_with_the_selectors_estimate(pop_and_pool):
    pop, pool = pop_and_pool
    model = _person(pop, pool, 2)
    from torchpref.selection.eubo import expected_best_option
    from torchpref.selection.samples import joint_posterior, joint_samples

    sets = torch.tensor([[0, 3, 7], [1, 2, 8]])
    botorch = qExpectedUtilityOfBestOption(pref_model=model)(pool[sets]).detach()
    mean, cov = joint_posterior(model, pool.unsqueeze(0))
    F, _ = joint_samples(mean, cov, [torch.Generator().manual_seed(0)], 40_000)
    ours = expected_best_option(F, sets.unsqueeze(0))[0]
    spread = F[0][:, sets].amax(-1).std(0) / 40_000**0.5
    assert float(((ours - botorch).abs() / (spread + 0.02 * botorch.abs())).max()) < 4
