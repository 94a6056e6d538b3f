import pytest
import torch

from torchpref.lake import InformationField, Lake, LakeOperator, make_scenario, path_objectives, rrt_star, stomp
from torchpref.lake.planners import path_cost, resample_by_arc_length


@pytest.fixture(scope="module")
def world():
    gen = torch.Generator().manual_seed(11)
    lake = Lake.random(generator=gen)
    xmin, xmax, ymin, ymax = lake.bounds
    field = InformationField.random(generator=gen, extent=(xmin - 5, xmax + 5, ymin - 5, ymax + 5))
    return lake, field


def fine_on_water(lake, paths, n=400):
    t = torch.linspace(0, 1, n, dtype=torch.float64).view(-1, 1, 1, 1)
    pts = paths[:, :-1] + t * (paths[:, 1:] - paths[:, :-1])
    return lake.contains(pts).all(0).all(-1)


def check_paths(lake, paths):
    assert torch.allclose(paths[:, 0], lake.start) and torch.allclose(paths[:, -1], lake.goal)
    assert lake.path_on_water(paths).all()
    assert fine_on_water(lake, paths).all()


@pytest.mark.parametrize("planner", ["stomp", "rrt"])
def test_paths_stay_on_water_and_trade_distance_for_information(world, planner):
    lake, field = world
    w = torch.tensor([0.0, 0.3, 100.0], dtype=torch.float64) / field.max
    gen = torch.Generator().manual_seed(0)
    if planner == "stomp":
        paths = stomp(lake, field, w, generator=gen, init_std=0.0, iterations=40, num_rollouts=12)
    else:
        paths = rrt_star(lake, field, w, generator=gen, num_samples=500)
    check_paths(lake, paths)
    X = path_objectives(paths, field)
    straight = float((lake.goal - lake.start).norm())
    assert X[0, 0] < 1.03 * straight  # w = 0: nearly the straight line
    assert X[-1, 1] > X[0, 1] and X[-1, 0] > X[0, 0]  # large w: longer and more informative
    # each weight's path is at least as good for that weight as the w = 0 path
    assert (path_cost(paths, field, w) <= path_cost(paths[:1].expand_as(paths), field, w) + 1e-6).all()


def test_stomp_keeps_water_on_a_nonconvex_lake():
    # a lake with a peninsula pushing into the middle; the straight line grazes it
    v = torch.tensor(
        [[-200, -100], [200, -100], [200, 100], [20, 100], [0, 20], [-20, 100], [-200, 100]], dtype=torch.float64
    )
    lake = Lake(v, torch.tensor([-150.0, 0.0]), torch.tensor([150.0, 0.0]))
    field = InformationField.random(generator=torch.Generator().manual_seed(2), extent=(-205, 205, -105, 105))
    w = torch.tensor([0.0, 1.0, 50.0], dtype=torch.float64)
    paths = stomp(lake, field, w, generator=torch.Generator().manual_seed(3), iterations=30)
    check_paths(lake, paths)
    paths = rrt_star(lake, field, w, generator=torch.Generator().manual_seed(3), num_samples=400)
    check_paths(lake, paths)


def test_resample_by_arc_length():
    p = torch.tensor([[[0.0, 0.0], [3.0, 0.0], [3.0, 1.0]]], dtype=torch.float64)
    r = resample_by_arc_length(p, 5)
    expected = torch.tensor([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0], [3.0, 1.0]], dtype=torch.float64)
    assert torch.allclose(r[0], expected)


def test_planners_validate(world):
    lake, field = world
    with pytest.raises(ValueError, match="weights"):
        stomp(lake, field, torch.tensor([-1.0]))
    with pytest.raises(ValueError, match="radius"):
        rrt_star(lake, field, torch.tensor([1.0]), step=10.0, radius=5.0)


def test_small_scenario():
    sc = make_scenario(4, paths_per_planner=12, stomp_options={"iterations": 20}, rrt_options={"num_samples": 300})
    for paths, X, planner in (
        (sc.train_paths, sc.train_X, sc.train_planner),
        (sc.test_paths, sc.test_X, sc.test_planner),
    ):
        assert paths.shape[0] == 24 and X.shape == (24, 2) and planner.tolist() == [0] * 12 + [1] * 12
        check_paths(sc.lake, paths)
        assert torch.allclose(X, path_objectives(paths, sc.field), rtol=1e-9)
    # the field was scaled for a share of about 10 % rated 5 in the training set
    share = (LakeOperator().level(sc.train_X) == 5).float().mean()
    assert 0.04 <= share <= 0.3
    again = make_scenario(4, paths_per_planner=12, stomp_options={"iterations": 20}, rrt_options={"num_samples": 300})
    assert torch.equal(again.train_X, sc.train_X)
    with pytest.raises(ValueError, match="seed"):
        make_scenario()
