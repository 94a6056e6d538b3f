"""The lake experiment on a tiny synthetic scenario (a real one takes seconds to plan)."""

import json

import pytest
import torch

from torchpref.experiments.lake import STRATEGIES, make_model, normalise, pool_bounds, run_lake_experiment
from torchpref.experiments.lake_plan import model_utility
from torchpref.lake import LakeOperator, LakeScenario, path_objectives
from torchpref.lake.plan import plan_with_utility
from torchpref.testing.lake_worlds import bent_paths, lake_and_field


@pytest.fixture(scope="module")
def scenario():
    lake, field = lake_and_field(0)
    offsets = torch.linspace(-150, 150, 121, dtype=torch.float64)
    paths = bent_paths(lake, offsets)
    paths = paths[lake.path_on_water(paths)]
    X = path_objectives(paths, field)
    # scale the field so that the operator's levels spread over the paths
    short = X[:, 0] < X[:, 0].quantile(0.5)
    field = field.scaled(160.0 / float(X[short, 1].max()))
    X = path_objectives(paths, field)
    tr, te = paths[0::2], paths[1::2]
    z = torch.zeros(len(tr), dtype=torch.long)
    return LakeScenario(
        lake,
        field,
        tr,
        path_objectives(tr, field),
        z,
        z.double(),
        te,
        path_objectives(te, field),
        torch.zeros(len(te), dtype=torch.long),
        torch.zeros(len(te), dtype=torch.float64),
    )


def test_tiny_run_writes_files(scenario, tmp_path):
    res = run_lake_experiment(
        trials=2,
        queries=3,
        out=tmp_path,
        workers=1,
        strategies=STRATEGIES[:2],
        scenario=scenario,
        progress=False,
        plan_trials=1,
        plan=[STRATEGIES[0]],
        plan_settings={"num_fresh": 0, "steps": 5},
    )
    data = json.loads((tmp_path / "lake.json").read_text())
    assert data["trials"] == 2 and data["queries"] == 3
    assert set(data["strategies"]) == set(STRATEGIES[:2])
    for entry in data["strategies"].values():
        assert set(entry) == {
            "error5_mean",
            "error5_sem",
            "wrms_mean",
            "wrms_sem",
            "chosen_rating_mean",
            "chosen_rating_sem",
        }
        assert all(len(v) == 4 for v in entry.values())
        assert all(1 <= c <= 5 for c in entry["chosen_rating_mean"])
    summary = json.loads((tmp_path / "lake_summary.json").read_text())
    assert set(summary["share_rated_5"]) == set(STRATEGIES[:2])
    assert all(0 <= v <= 1 for v in summary["share_rated_5"].values())
    assert summary["planning"][STRATEGIES[0]]["n"] == 1 and STRATEGIES[1] not in summary["planning"]
    (plan,) = summary["plans"]
    assert plan["planned"]["level"] >= 1 and plan["source"] in ("fallback", "start", "planned")
    for name in ("lake_plan_maps.png", "lake_plan_levels.png", "lake_field.png", "lake_objectives.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    lines = (tmp_path / "lake.csv").read_text().strip().splitlines()
    assert lines[0].startswith("strategy,queries") and len(lines) == 1 + 2 * 4
    assert (tmp_path / "lake.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert res["summary"]["wall_time_s"] > 0


def test_plan_with_utility_on_water_and_not_worse(scenario):
    bounds = pool_bounds(scenario)
    op = LakeOperator()
    Z = normalise(scenario.train_X, bounds)
    # a model that has seen the operator's ratings of a few pool paths
    idx = torch.arange(0, Z.shape[0], 3)
    model = make_model(
        Z[idx[:2]], torch.tensor([[0, 1]]) if op.choose(scenario.train_X[idx[:2]]) == 0 else torch.tensor([[1, 0]])
    )
    for i in idx:
        model.add_observations(Z[i : i + 1], ratings=[op.rate(scenario.train_X[i])], rating_index=[0])

    utility = model_utility(model, bounds)
    res = plan_with_utility(scenario, utility, num_starts=2, steps=30)
    assert bool(scenario.lake.path_on_water(res.path))
    assert torch.equal(res.path[0], scenario.lake.start) or torch.allclose(res.path[0], scenario.lake.start)
    assert torch.allclose(res.path[-1], scenario.lake.goal)
    assert res.utility >= res.fallback_utility
    with torch.no_grad():
        u = utility(path_objectives(res.path, scenario.field).unsqueeze(0))
    assert abs(float(u) - res.utility) < 1e-4  # the candidates share one quadrature (their longest segment)
