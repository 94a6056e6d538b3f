"""The combination (rankings by I(y; f), ratings by the clipped profile, one value per second) and
the qEUBO selector: each is the selectors it is made of where it should be, and a session can
record and rebuild both."""

import pytest
import torch

import torchpref
from torchpref.data.queries import RankingQuery, RatingQuery
from torchpref.models.kernels import fixed_rbf_kernel
from torchpref.selection import InformationPerEffort, ProfileVariancePerEffort
from torchpref.selection.combined import InformationAndProfile
from torchpref.selection.eubo import ExpectedBestOption, expected_best_option
from torchpref.sessions.recorded import describe_selector, recorded_selector

D = torch.float64
N = 12


def _model(seed=0):
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(N, 2, generator=g, dtype=D)
    model = torchpref.PreferenceGP(
        X[:6],
        torch.tensor([[0, 1], [2, 3], [4, 5]]),
        torch.tensor([0.7, 0.2], dtype=D),
        torch.tensor([0, 3]),
        covar_module=fixed_rbf_kernel(0.3, 1.0, X),
        comparison_noise=0.2,
        rating_scale=0.8,
        rating_precision=20.0,
    )
    return model, X


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_its_rating_is_the_clipped_profiles_and_its_ranking_the_informations(seed):
    """With rankings priced out it asks the clipped profile's rating, with ratings priced out the
    utility information's ranking (same samples: the same generator and number of samples)."""
    model, X = _model(seed)
    idx = torch.arange(N)

    def ask(sel):
        return sel.select(model, X, idx, 0, 10, torch.Generator().manual_seed(seed))

    rate = ask(InformationAndProfile(m=3, rating_cost=1.0, ranking_cost=1e9))
    profile = ask(ProfileVariancePerEffort(m=3, rating_cost=1.0, ranking_cost=1e9, clipped=True))
    assert rate.kind == profile.kind == "rating" and rate.index == profile.index
    rank = ask(InformationAndProfile(m=3, rating_cost=1e9, ranking_cost=1.0))
    info = ask(InformationPerEffort(m=3, rating_cost=1e9, ranking_cost=1.0, target="utility", num_samples=256))
    assert rank.kind == info.kind == "ranking" and rank.indices == info.indices


@pytest.mark.parametrize("decide", ["information", "profile", "sum"])
def test_it_asks_the_larger_value_per_second_under_one_value(decide):
    model, X = _model(4)
    sel = InformationAndProfile(m=3, decide=decide)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        rating_row, rating_value, rows, ranking_value = sel.values(model, X.unsqueeze(0), [g])
        rate, rank = sel.scorers(model, X.unsqueeze(0), [torch.Generator().manual_seed(0)])
        torch.testing.assert_close(rating_value, rate(rating_row.reshape(1, 1))[0] / sel.rating_cost)
        torch.testing.assert_close(ranking_value, rank(rows.unsqueeze(1))[0] / sel.ranking_cost)
    q = sel.select(model, X, torch.arange(N), 0, 10, torch.Generator().manual_seed(0))
    assert q.kind == ("ranking" if float(ranking_value) > float(rating_value) else "rating")


def test_seconds_default_to_the_plain_effort_model_and_bad_settings_are_refused():
    sel = InformationAndProfile()
    assert (sel.rating_cost, sel.ranking_cost) == (3.4, 6.1)
    assert InformationAndProfile(m=4, rating_cost=1.0).ranking_cost == 1.75  # per-effort units
    with pytest.raises(ValueError, match="decide"):
        InformationAndProfile(decide="both")
    with pytest.raises(ValueError, match="num_samples"):
        InformationAndProfile(num_samples=1)


def test_combination_chooses_among_given_queries():
    model, X = _model(5)
    queries = [RatingQuery(X[i], i) for i in range(N)] + [RankingQuery(X[[i, i + 1, i + 2]], (i, i + 1, i + 2)) for i in range(0, N - 2, 2)]  # fmt: skip
    sel = InformationAndProfile(m=3, rating_cost=1.0, ranking_cost=1e9)
    i = sel.choose(model, queries, generator=torch.Generator().manual_seed(0))
    assert queries[i].kind == "rating"
    only_rankings = queries[N:]
    j = InformationAndProfile(m=3).choose(model, only_rankings, generator=torch.Generator().manual_seed(0))
    assert only_rankings[j].kind == "ranking"


def test_qeubo_builds_the_set_of_largest_expected_best_option_among_pairs():
    """For m = 2 among all items, the greedy build is exhaustive: its pair has the largest qEUBO."""
    model, X = _model(6)
    sel = ExpectedBestOption(m=2, num_samples=512, num_plausible=N)
    q = sel.select(model, X, torch.arange(N), 0, 10, torch.Generator().manual_seed(0))
    from torchpref.selection.samples import joint_posterior, joint_samples

    mean, cov = joint_posterior(model, X.unsqueeze(0))
    F, _ = joint_samples(mean, cov, [torch.Generator().manual_seed(0)], 512)
    pairs = torch.combinations(torch.arange(N), 2)
    values = expected_best_option(F, pairs.unsqueeze(0))[0]
    assert set(q.indices) == set(pairs[values.argmax()].tolist())
    queries = [RankingQuery(X[p], tuple(p.tolist())) for p in pairs]
    i = sel.choose(model, queries, generator=torch.Generator().manual_seed(0))
    assert i == int(values.argmax())
    with pytest.raises(ValueError, match="num_plausible"):
        ExpectedBestOption(num_plausible=1)


@pytest.mark.parametrize("sel", [InformationAndProfile(m=4, decide="profile"), ExpectedBestOption(m=3)])
def test_a_session_can_record_and_rebuild_them(sel):
    desc = describe_selector(sel)
    assert "unrecorded" not in desc
    again = recorded_selector(desc)
    assert type(again) is type(sel) and describe_selector(again) == desc
