"""Realistic simulated raters: offset, gain, drift, partial scale use, lapses, seconds."""

import math

import pytest
import torch

from torchpref.simulation.raters import EffortModel, RaterProfile, RealisticUser, precision_for_noise
from torchpref.simulation.users import SimulatedUser, User


def _utility(X):
    return 2 * X[..., 0] - 1


def test_effort_model_seconds():
    plain, traj = EffortModel.plain(), EffortModel.trajectories(8.0)
    assert plain.rating() == 3.4 and plain.ranking(2) == 3.4 and plain.ranking(12) == pytest.approx(12.4)
    assert traj.rating() == pytest.approx(11.4) and traj.ranking(5) == pytest.approx(3.4 + 2.7 + 40)
    assert plain.costs(5) == {"rating": 3.4, "ranking": pytest.approx(6.1)}
    with pytest.raises(ValueError, match="m >= 2"):
        plain.ranking(1)
    with pytest.raises(ValueError, match="view_seconds"):
        EffortModel(view_seconds=-1.0)


def test_profile_validation():
    for bad in (
        {"lapse_rate": 1.5},
        {"rating_gain": 0.0},
        {"scale_range": (0.6, 0.4)},
        {"levels": 1},
        {"rating_offset": math.nan},
    ):
        with pytest.raises(ValueError, match=next(iter(bad))):
            RaterProfile(**bad)


def test_ideal_profile_answers_as_the_paper_user():
    """g = 1, b = 0, no drift, no lapse, full scale: the same mean rating as SimulatedUser."""
    g = torch.Generator().manual_seed(1)
    user = RealisticUser(_utility, RaterProfile(rating_precision=1e6), g)
    assert isinstance(user, User)
    paper = SimulatedUser(_utility, 0.1, 0.8, 1e6, torch.Generator().manual_seed(2))
    for x in (0.1, 0.5, 0.9):
        X = torch.tensor([[x]], dtype=torch.float64)
        assert abs(user.rate(X[0]) - float(paper.mean_rating(X))) < 2e-3


def test_offset_gain_and_scale_range_shape_the_ratings():
    g = torch.Generator().manual_seed(3)
    prof = RaterProfile(rating_offset=0.5, rating_gain=2.0, rating_precision=1e7, scale_range=(0.2, 0.6))
    user = RealisticUser(_utility, prof, g)
    X = torch.tensor([[0.3]], dtype=torch.float64)
    f = float(_utility(X))
    expect = 0.2 + 0.4 * 0.5 * math.erfc(-(2 * f + 0.5) / (math.sqrt(2) * 0.8) / math.sqrt(2))
    assert abs(user.rate(X[0]) - expect) < 1e-3
    assert abs(float(user.person_mean_rating(X)) - expect) < 1e-9
    ratings = [user.rate(torch.rand(1, generator=g, dtype=torch.float64)) for _ in range(200)]
    assert 0.2 - 1e-3 <= min(ratings) and max(ratings) <= 0.6 + 1e-3  # only part of the scale
    likert = RealisticUser(_utility, RaterProfile(levels=7), g)
    r = likert.rate(X[0])
    assert abs(7 * r - 0.5 - round(7 * r - 0.5)) < 1e-9  # a box's centre


def test_lapses_and_noise_in_choices():
    g = torch.Generator().manual_seed(4)
    X = torch.tensor([[0.9], [0.1], [0.2], [0.3], [0.4]], dtype=torch.float64)  # row 0 clearly best
    for eps in (0.0, 0.4):
        user = RealisticUser(_utility, RaterProfile(comparison_noise=1e-3, lapse_rate=eps), g)
        wrong = sum(user.choose(X) != 0 for _ in range(2000)) / 2000
        # a lapse picks uniformly among 5: wrong with probability eps * 4/5
        assert abs(wrong - eps * 0.8) < 0.035


def test_drift_is_a_random_walk_over_answers():
    g = torch.Generator().manual_seed(5)
    user = RealisticUser(_utility, RaterProfile(drift_sd=0.1), g)
    x = torch.tensor([0.5], dtype=torch.float64)
    drifts = []
    for _ in range(400):
        user.rate(x)
        drifts.append(user.drift)
    steps = torch.tensor(drifts).diff()
    assert abs(float(steps.std()) - 0.1) < 0.015 and abs(float(steps.mean())) < 0.02
    assert RealisticUser(_utility, RaterProfile(), g).drift == 0.0


def test_seconds_are_recorded_per_answer():
    g = torch.Generator().manual_seed(6)
    user = RealisticUser(_utility, RaterProfile(effort=EffortModel.trajectories(10.0), time_noise=0.2), g)
    X = torch.rand(5, 1, generator=g, dtype=torch.float64)
    for _ in range(300):
        user.rate(X[0])
        user.choose(X)
    mean = user.mean_seconds()
    # log-normal factor exp(0.2 z): mean exp(0.02)
    assert abs(mean["rating"] / (13.4 * math.exp(0.02)) - 1) < 0.05
    assert abs(mean["ranking"] / (56.1 * math.exp(0.02)) - 1) < 0.05
    assert [k for k, _, _ in user.seconds[:2]] == ["rating", "ranking"] and user.seconds[1][1] == 5


def test_typical_profiles_follow_the_published_ranges():
    g = torch.Generator().manual_seed(7)
    profiles = [RaterProfile.typical(g, spread=0.6) for _ in range(2000)]
    off = torch.tensor([p.rating_offset for p in profiles])
    gain = torch.tensor([p.rating_gain for p in profiles]).log()
    assert abs(float(off.std()) / 0.6 - 0.24) < 0.02 and abs(float(gain.std()) - 0.325) < 0.02
    partial = sum(p.scale_range != (0.0, 1.0) for p in profiles) / 2000
    assert abs(partial - 0.16) < 0.025
    assert all(0.05 <= p.lapse_rate <= 0.25 for p in profiles)
    # the rating noise, read back in latent units at mid-scale, is 0.33 of the spread
    nu = profiles[0].rating_precision
    assert nu == pytest.approx(precision_for_noise(0.198, 0.8))
    sd_u = 0.5 / math.sqrt(nu + 1)
    slope = 1 / (math.sqrt(2 * math.pi) * math.sqrt(2) * 0.8)
    assert sd_u / slope == pytest.approx(0.198, rel=1e-9)
    assert RaterProfile.typical(g, lapse_rate=0.0).lapse_rate == 0.0
