"""The selector per second: its seconds (effort model, measured response times), its values against
the profile selector's, and the person's lapse rate lowering what a ranking is worth."""

import pytest
import torch
from test_variance_reduction import _model

from torchpref.data.queries import RankingQuery, RatingQuery
from torchpref.models.calibration import calibrate_person
from torchpref.selection.per_second import ProfilePerSecond
from torchpref.selection.top_profile import ProfileVariancePerEffort
from torchpref.simulation.raters import EffortModel

D = torch.float64


def _case():
    g = torch.Generator().manual_seed(5)
    X = torch.rand(12, 2, generator=g, dtype=D)
    model = _model(X, torch.tensor([[0, 1], [2, 3], [4, 5]]), torch.tensor([0.8, 0.3]), torch.tensor([4, 7]))
    return model, torch.rand(1, 30, 2, generator=g, dtype=D)


def _values(sel, model, Xc, seed=0):
    return sel.values(model, Xc, [torch.Generator().manual_seed(seed)])


def test_seconds_from_the_effort_model_then_from_measurements():
    sel = ProfilePerSecond(m=5, effort=EffortModel.trajectories(10.0), min_answers=2)
    assert sel.seconds() == {"rating": 13.4, "ranking": pytest.approx(56.1)}
    sel.record_seconds("rating", 20.0)
    assert sel.seconds()["rating"] == 13.4  # one answer is not enough
    sel.record_seconds("rating", 30.0)
    assert sel.seconds()["rating"] == 25.0
    sel.record_seconds("ranking", 2 * EffortModel.trajectories(10.0).ranking(3), m=3)  # rescaled to m = 5
    sel.record_seconds("ranking", 112.2)
    assert sel.seconds()["ranking"] == pytest.approx(112.2)
    for bad in ({"kind": "tie", "seconds": 1.0}, {"kind": "rating", "seconds": 0.0}):
        with pytest.raises(ValueError):
            sel.record_seconds(**bad)
    with pytest.raises(ValueError, match="target"):
        ProfilePerSecond(target="levels")
    with pytest.raises(ValueError, match="min_answers"):
        ProfilePerSecond(min_answers=0)
    with pytest.raises(ValueError, match="EffortModel"):
        ProfilePerSecond(effort=3.0)


@pytest.mark.parametrize("target,clipped", [("top", False), ("clipped", True)])
def test_one_target_is_the_profile_selector(target, clipped):
    """With one profile and the same seconds as costs, the values are the profile selector's."""
    model, Xc = _case()
    mine = _values(ProfilePerSecond(m=4, target=target, rating_seconds=1.0, ranking_seconds=2.0), model, Xc)
    theirs = _values(ProfileVariancePerEffort(m=4, rating_cost=1.0, ranking_cost=2.0, clipped=clipped), model, Xc)
    for a, b in zip(mine, theirs):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)


def test_both_targets_sum_their_reductions():
    """The rating of the chosen item is worth the two profiles' reductions together (same samples)."""
    model, Xc = _case()
    both = _values(ProfilePerSecond(m=4, rating_seconds=1.0, ranking_seconds=2.0), model, Xc)
    top = _values(ProfilePerSecond(m=4, target="top", rating_seconds=1.0, ranking_seconds=2.0), model, Xc)
    clip = _values(ProfilePerSecond(m=4, target="clipped", rating_seconds=1.0, ranking_seconds=2.0), model, Xc)
    assert float(both[1]) >= max(float(top[1]), float(clip[1])) - 1e-12  # the best of a sum >= each best
    assert float(both[1]) <= float(top[1]) + float(clip[1]) + 1e-12


def test_lapses_lower_a_rankings_value_not_a_ratings():
    model, Xc = _case()
    sel = ProfilePerSecond(m=4, rating_seconds=1.0, ranking_seconds=2.0)
    calibrate_person(model, lapse_rate=1e-6)
    _, rating0, rows0, ranking0 = _values(sel, model, Xc)
    model.likelihood.comparison.lapse_rate = 0.4
    _, rating1, _, ranking1 = _values(sel, model, Xc)
    assert float(ranking1) < 0.8 * float(ranking0)  # a lapse-prone person's ranking tells less
    # the rating's value moves only through the posterior's change (the lapse also reweights comparisons)
    assert float(rating0) > 0 and float(rating1) > 0
    # and a lapse rate of 0 values rankings as the model without the lapse likelihood does (to eps / 2)
    plain, _ = _case()
    torch.testing.assert_close(ranking0, _values(sel, plain, Xc)[3], rtol=1e-3, atol=0.0)


def test_seconds_decide_the_kind():
    model, Xc = _case()
    cheap_rankings = ProfilePerSecond(m=4, rating_seconds=1e3, ranking_seconds=1.0)
    cheap_ratings = ProfilePerSecond(m=4, rating_seconds=1.0, ranking_seconds=1e3)
    g = torch.Generator().manual_seed(0)
    assert isinstance(cheap_rankings.select(model, Xc[0], None, 0, 10, g), RankingQuery)
    assert isinstance(cheap_ratings.select(model, Xc[0], None, 0, 10, torch.Generator().manual_seed(0)), RatingQuery)
    # measured seconds override: a person whose rankings take ages gets ratings
    sel = ProfilePerSecond(m=4, rating_seconds=1e3, ranking_seconds=1.0, min_answers=1)
    sel.record_seconds("ranking", 1e6)
    assert isinstance(sel.select(model, Xc[0], None, 0, 10, torch.Generator().manual_seed(0)), RatingQuery)
