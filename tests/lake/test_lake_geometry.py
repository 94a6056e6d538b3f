import pytest
import torch

from torchpref.lake import Lake


@pytest.fixture
def square():
    v = torch.tensor([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]], dtype=torch.float64)
    return Lake(v, torch.tensor([1.0, 1.0]), torch.tensor([9.0, 9.0]))


@pytest.fixture
def u_shape():
    # a U: water everywhere in [0, 30] x [0, 20] except the notch [10, 20] x [5, 20]
    v = torch.tensor([[0, 0], [30, 0], [30, 20], [20, 20], [20, 5], [10, 5], [10, 20], [0, 20]], dtype=torch.float64)
    return Lake(v, torch.tensor([5.0, 15.0]), torch.tensor([25.0, 15.0]))


def test_contains(square, u_shape):
    p = torch.tensor([[5.0, 5.0], [-1.0, 5.0], [11.0, 5.0], [5.0, 10.5], [9.99, 0.01]], dtype=torch.float64)
    assert square.contains(p).tolist() == [True, False, False, False, True]
    q = torch.tensor([[15.0, 10.0], [15.0, 2.0], [5.0, 18.0], [25.0, 18.0]], dtype=torch.float64)
    assert u_shape.contains(q).tolist() == [False, True, True, True]
    assert u_shape.contains(q.view(2, 2, 2)).shape == (2, 2)


def test_segments_on_water_exact(u_shape):
    a = torch.tensor([[5.0, 15.0], [5.0, 2.0], [5.0, 4.9], [5.0, 15.0]], dtype=torch.float64)
    b = torch.tensor([[25.0, 15.0], [25.0, 2.0], [25.0, 4.9], [5.0, 2.0]], dtype=torch.float64)
    # across the notch: both ends on water but the segment crosses land
    assert u_shape.segments_on_water(a, b).tolist() == [False, True, True, True]
    # a segment that just clips the notch's corner
    assert not bool(u_shape.segments_on_water(torch.tensor([5.0, 4.0]), torch.tensor([15.0, 6.0])))


def test_path_on_water_agrees_with_fine_sampling(u_shape):
    gen = torch.Generator().manual_seed(0)
    paths = torch.rand(300, 4, 2, generator=gen, dtype=torch.float64) * torch.tensor([30.0, 20.0])
    exact = u_shape.path_on_water(paths)
    t = torch.linspace(0, 1, 2001, dtype=torch.float64).view(-1, 1, 1, 1)
    fine = paths[:, :-1] + t * (paths[:, 1:] - paths[:, :-1])  # 2001 x 300 x 3 x 2
    sampled = u_shape.contains(fine).all(0).all(-1)
    # sampling can miss a crossing but never finds one the exact test misses
    assert not (exact & ~sampled).any()
    assert (exact == sampled).float().mean() > 0.98
    assert 0 < exact.sum() < 300


def test_signed_distance(square):
    p = torch.tensor([[5.0, 5.0], [1.0, 3.0], [12.0, 5.0], [13.0, 14.0]], dtype=torch.float64)
    sd = square.signed_distance(p)
    assert torch.allclose(sd, torch.tensor([-5.0, -1.0, 2.0, 5.0], dtype=torch.float64))
    p.requires_grad_(True)
    (g,) = torch.autograd.grad(square.signed_distance(p).sum(), p)
    assert torch.allclose(g[1], torch.tensor([-1.0, 0.0], dtype=torch.float64))
    assert torch.allclose(g[3], torch.tensor([0.6, 0.8], dtype=torch.float64))


def test_random_lake():
    gen = torch.Generator().manual_seed(3)
    lake = Lake.random(generator=gen)
    assert float((lake.goal - lake.start).norm()) == pytest.approx(390.0)
    assert bool(lake.path_on_water(torch.stack([lake.start, lake.goal]).unsqueeze(0)))
    again = Lake.random(generator=torch.Generator().manual_seed(3))
    assert torch.equal(lake.vertices, again.vertices)


def test_lake_validates(square):
    with pytest.raises(ValueError, match="not on the water"):
        Lake(square.vertices, torch.tensor([20.0, 1.0]), torch.tensor([5.0, 5.0]))
    with pytest.raises(ValueError, match="vertices"):
        Lake(torch.zeros(2, 2), torch.zeros(2), torch.zeros(2))
    with pytest.raises(ValueError, match="roughness"):
        Lake.random(roughness=0.9)
