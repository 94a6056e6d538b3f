"""Planning through a utility of the objectives: a known optimum, the shoreline, the risk-aware
criterion and the scenario cache."""

import pytest
import torch

from torchpref.experiments.lake import make_model, normalise, pool_bounds
from torchpref.experiments.lake_plan import compare, improvement_bound
from torchpref.lake import LakeOperator, LakeScenario, path_objectives
from torchpref.lake import scenario as scenario_module
from torchpref.lake.plan import plan_with_utility
from torchpref.lake.scenario import cached_scenario, load_scenario, save_scenario, scenario_cache_path
from torchpref.testing.lake_worlds import bent_paths, lake_and_field


@pytest.fixture(scope="module")
def world():
    lake, field = lake_and_field(3)
    paths = bent_paths(lake, torch.linspace(-120, 120, 41, dtype=torch.float64))
    paths = paths[lake.path_on_water(paths)]
    X = path_objectives(paths, field)
    z = torch.zeros(len(paths), dtype=torch.long)
    return LakeScenario(lake, field, paths, X, z, z.double(), paths, X, z, z.double())


def test_known_optimum_shortest_path(world):
    """Utility = -distance: the optimum is the straight line from start to goal (on the water here)."""
    lake = world.lake
    straight = float((lake.goal - lake.start).norm())
    assert bool(lake.path_on_water(torch.stack([lake.start, lake.goal]).unsqueeze(0)))
    bent = world.train_paths[world.train_X[:, 0].argsort(descending=True)[:3]]  # the longest paths
    res = plan_with_utility(world, lambda X: -X[..., 0], starts=bent, fallback=bent[0], steps=300, lr=2.0)
    assert res.source == "planned"
    assert straight - 1e-9 <= float(res.objectives[0]) <= 1.01 * straight
    assert float(bent[:, 1:].sub(bent[:, :-1]).norm(dim=-1).sum(-1).min()) > 1.1 * straight  # the starts were far off


def test_planned_paths_stay_on_the_water(world):
    """Utility = +distance pushes the waypoints into the shore: every returned path is on the water."""
    lake = world.lake
    for offsets in ([-100.0, 0.0, 100.0], [40.0]):
        starts = bent_paths(lake, torch.tensor(offsets, dtype=torch.float64))
        starts = starts[lake.path_on_water(starts)]
        res = plan_with_utility(world, lambda X: X[..., 0], starts=starts, fallback=starts[0], steps=150, lr=5.0)
        assert bool(lake.path_on_water(res.path))
        assert res.utility >= res.fallback_utility
        assert torch.allclose(res.path[0], lake.start) and torch.allclose(res.path[-1], lake.goal)


def test_fallback_kept_when_nothing_is_strictly_better(world):
    fb = world.train_paths[0]
    res = plan_with_utility(
        world, lambda X: torch.zeros(X.shape[:-1], dtype=X.dtype), starts=fb.unsqueeze(0), fallback=fb, steps=3
    )
    assert res.source == "fallback" and res.path is fb and res.utility == res.fallback_utility == 0.0


def test_plan_with_utility_rejects_bad_arguments(world):
    with pytest.raises(ValueError, match="num_starts"):
        plan_with_utility(world, lambda X: X[..., 0], num_starts=0)
    with pytest.raises(ValueError, match="starts must be"):
        plan_with_utility(world, lambda X: X[..., 0], starts=world.train_paths[0], fallback=world.train_paths[0])


def _model(world):
    op = LakeOperator(info_good=float(world.train_X[:, 1].median()), info_poor=float(world.train_X[:, 1].min()))
    bounds = pool_bounds(world)
    Z = normalise(world.train_X, bounds)
    model = make_model(Z[:2].clone(), torch.tensor([[op.choose(world.train_X[:2]), 1 - op.choose(world.train_X[:2])]]))
    for i in range(2, Z.shape[0], 4):
        model.add_observations(Z[i : i + 1], ratings=[op.rate(world.train_X[i])], rating_index=[0])
    return model, bounds


def test_improvement_bound_against_posterior_samples(world):
    model, bounds = _model(world)
    ref = world.train_X[5]
    X = world.train_X[[1, 9, 20]]
    c0 = improvement_bound(model, bounds, ref, 0.0)(X)
    c2 = improvement_bound(model, bounds, ref, 2.0)(X)
    with torch.no_grad():
        samples = []
        for x in X:
            post = model.posterior(normalise(torch.stack([x, ref]), bounds))
            f = post.rsample(torch.Size([40000])).squeeze(-1)
            samples.append(f[..., 0] - f[..., 1])
        d = torch.stack(samples, -1).reshape(-1, 3)
    assert torch.allclose(c0, d.mean(0), atol=0.02)
    sd = (c0 - c2) / 2
    assert torch.allclose(sd, d.std(0), rtol=0.03)
    # the reference against itself: no improvement, no uncertainty
    assert abs(float(improvement_bound(model, bounds, ref, 2.0)(ref.unsqueeze(0)))) < 1e-5


def test_improvement_bound_trust_region_and_errors(world):
    model, bounds = _model(world)
    far = torch.tensor([[world.train_X[:, 0].max() * 3, world.train_X[:, 1].max() * 3]], dtype=torch.float64)
    plain = improvement_bound(model, bounds, world.train_X[5], 1.0)
    trust = improvement_bound(model, bounds, world.train_X[5], 1.0, answered=model.train_X, trust_radius=0.1)
    assert float(trust(far)) < float(plain(far)) - 1.0
    near = world.train_X[:1]  # an answered item: inside the region, no penalty
    assert torch.allclose(trust(near), plain(near))
    with pytest.raises(ValueError, match="beta"):
        improvement_bound(model, bounds, world.train_X[5], -1.0)
    with pytest.raises(ValueError, match="answered"):
        improvement_bound(model, bounds, world.train_X[5], 1.0, trust_radius=0.1)


def test_compare_finer_measure():
    op = LakeOperator()
    x = torch.tensor([480.0, 160.0], dtype=torch.float64)
    same_level_longer = torch.tensor([495.0, 170.0], dtype=torch.float64)
    c = compare(op, x, same_level_longer)
    assert c["level"] == c["other_level"] == 5 and c["at_least_as_good"] and c["strictly_better"]
    assert c["distance_diff"] == -15.0 and c["info_margin"] == 10.0
    below = torch.tensor([400.0, 149.0], dtype=torch.float64)  # shorter, but under the threshold: level 2
    c = compare(op, below, x)
    assert c["level"] == 2 and not c["at_least_as_good"] and not c["strictly_better"]


def test_scenario_cache_round_trip_and_build_once(world, tmp_path, monkeypatch):
    path = save_scenario(world, tmp_path / "s.pt")
    back = load_scenario(path)
    for name in ("train_paths", "train_X", "test_X", "train_planner"):
        assert torch.equal(getattr(back, name), getattr(world, name))
    assert torch.equal(back.lake.vertices, world.lake.vertices) and back.field.extent == world.field.extent
    calls = []

    def fake_make(seed, progress=False):
        calls.append(seed)
        return world

    monkeypatch.setattr(scenario_module, "make_scenario", fake_make)
    a = cached_scenario(7, tmp_path)
    b = cached_scenario(7, tmp_path)
    assert calls == [7] and torch.equal(a.train_X, b.train_X)
    assert scenario_cache_path(7, tmp_path).exists()
    cached_scenario(8, tmp_path)
    assert calls == [7, 8]
    scenario_cache_path(7, tmp_path).write_bytes(b"not a scenario")
    with pytest.warns(RuntimeWarning, match="rebuilding"):
        cached_scenario(7, tmp_path)
    assert calls == [7, 8, 7]
    with pytest.raises(ValueError, match="not a usable lake scenario"):
        load_scenario(tmp_path / "missing.pt")
