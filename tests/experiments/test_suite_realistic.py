"""The suite's realistic families and effort models in seconds (a tiny run)."""

import json

import pytest
import torch

from torchpref.experiments import suite
from torchpref.experiments.families import ALL_FAMILIES, FAMILIES, REALISTIC_FAMILIES, setup
from torchpref.simulation.raters import EffortModel, RealisticUser
from torchpref.simulation.users import SimulatedUser


def test_realistic_families_draw_people_for_the_utility():
    assert len(REALISTIC_FAMILIES) >= 5 and not set(REALISTIC_FAMILIES) & set(FAMILIES)
    assert list(ALL_FAMILIES)[: len(FAMILIES)] == list(FAMILIES)  # the idealised families' seeds keep their places
    for f in REALISTIC_FAMILIES.values():
        s = setup(f, 11, EffortModel.trajectories())
        assert isinstance(s.user, RealisticUser) and s.user.profile.effort.view_seconds == 10.0
        r = s.user.rate(s.x0[0])
        assert 0 < r < 1
        assert torch.equal(s.u_true, s.user.mean_rating(s.eval_X))  # the truth: the undistorted rating
    lapsing = [setup(REALISTIC_FAMILIES["lapsing"], k).user.profile.lapse_rate for k in range(20)]
    assert min(lapsing) >= 0.25 and max(lapsing) <= 0.4
    compressed = setup(REALISTIC_FAMILIES["compressed"], 3).user.profile.scale_range
    assert 0.4 <= compressed[1] - compressed[0] <= 0.67
    # an idealised family is unchanged: the paper's user
    assert isinstance(setup(FAMILIES["two-bumps"], 3).user, SimulatedUser)


def test_effort_models_and_groups():
    assert suite.effort_costs("units") == {"rating": 1.0, "ranking": 2.0}
    assert suite.effort_costs("plain") == {"rating": 3.4, "ranking": pytest.approx(6.1)}
    assert suite.effort_budgets("trajectories") == (134.0, 268.0)
    with pytest.raises(ValueError, match="effort"):
        suite.effort_costs("minutes")
    assert suite._checked(["realistic", "waves"], ("fixed",)) == [*REALISTIC_FAMILIES, "waves"]
    with pytest.raises(ValueError, match="unknown family"):
        suite._checked(["martians"], ("fixed",))


def test_a_tiny_realistic_run_counts_seconds(tmp_path):
    res = suite.run_suite(
        families=["lapsing"],
        trials=2,
        queries=3,
        seed=4,
        out=tmp_path,
        workers=1,
        strategies=["random ratings", "random rankings", "profile per second"],
        conditions=("fixed",),
        effort="trajectories",
        batch_size=2,
        progress=False,
    )
    assert res["summary"]["settings"]["costs"] == {"rating": 13.4, "ranking": pytest.approx(56.1)}
    trials = json.loads((tmp_path / "suite_trials.json").read_text())["lapsing/fixed"]
    for t in trials:
        assert t["random ratings"]["cost"] == pytest.approx([0.0, 13.4, 26.8, 40.2])
        assert t["random rankings"]["cost"][-1] == pytest.approx(3 * 56.1)
        kinds = t["profile per second"]["kinds"]
        cost = sum(13.4 if k == "rating" else 56.1 for k in kinds)
        assert t["profile per second"]["cost"][-1] == pytest.approx(cost)
