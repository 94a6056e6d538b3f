import math

import pytest
import torch

from torchpref.lake import InformationField, bilinear_sample, perlin_grid, perlin_noise
from torchpref.lake.field import random_gradients


@pytest.fixture
def gen():
    return torch.Generator().manual_seed(1234)


def test_perlin_zero_at_lattice_points(gen):
    grads = random_gradients(6, 5, generator=gen)
    ij = torch.stack(torch.meshgrid(torch.arange(6.0), torch.arange(5.0), indexing="ij"), -1).double()
    assert perlin_noise(ij, grads).abs().max() < 1e-12
    # but not zero in between
    mid = ij[:-1, :-1] + torch.tensor([0.3, 0.6], dtype=torch.float64)
    assert perlin_noise(mid, grads).abs().max() > 0.05


def test_perlin_grid_statistics_and_continuity(gen):
    g = perlin_grid((201, 201), 8, octaves=1, generator=gen)
    # lattice points of the grid: every 25 nodes
    assert g[::25, ::25].abs().max() < 1e-12
    assert abs(float(g.mean())) < 0.05
    assert 0.1 < float(g.std()) < 0.5
    assert g.abs().max() <= math.sqrt(0.5) + 1e-9  # bound of 2-D Perlin noise with unit gradients
    # continuity: neighbouring nodes (1/25 of a cell apart) differ little
    assert (g[1:] - g[:-1]).abs().max() < 0.1
    assert (g[:, 1:] - g[:, :-1]).abs().max() < 0.1


def test_perlin_small_steps_small_changes(gen):
    grads = random_gradients(5, 5, generator=gen)
    p = 4 * torch.rand(1000, 2, generator=gen, dtype=torch.float64)
    h = 1e-6
    diff = (perlin_noise(p + h, grads) - perlin_noise(p, grads)).abs()
    assert diff.max() < 10 * h


def test_bilinear_reproduces_nodes_and_linear_functions(gen):
    extent = (-3.0, 5.0, 1.0, 4.0)
    ny, nx = 7, 9
    xs = torch.linspace(extent[0], extent[1], nx, dtype=torch.float64)
    ys = torch.linspace(extent[2], extent[3], ny, dtype=torch.float64)
    pts = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1)
    grid = 2 * pts[..., 0] - 3 * pts[..., 1] + 1  # linear: reproduced exactly everywhere
    assert torch.allclose(bilinear_sample(grid, extent, pts), grid, atol=1e-12)
    q = torch.stack(
        [
            extent[0] + 8 * torch.rand(50, generator=gen, dtype=torch.float64),
            extent[2] + 3 * torch.rand(50, generator=gen, dtype=torch.float64),
        ],
        -1,
    )
    assert torch.allclose(bilinear_sample(grid, extent, q), 2 * q[:, 0] - 3 * q[:, 1] + 1, atol=1e-12)


def test_bilinear_gradient_matches_finite_differences(gen):
    field = InformationField.random(generator=gen)
    xmin, xmax, ymin, ymax = field.extent
    p = torch.stack(
        [
            xmin + 10 + (xmax - xmin - 20) * torch.rand(200, generator=gen, dtype=torch.float64),
            ymin + 10 + (ymax - ymin - 20) * torch.rand(200, generator=gen, dtype=torch.float64),
        ],
        -1,
    )
    p.requires_grad_(True)
    (grad,) = torch.autograd.grad(field(p).sum(), p)
    h = 1e-5
    for k in range(2):
        e = torch.zeros(2, dtype=torch.float64)
        e[k] = h
        fd = (field(p.detach() + e) - field(p.detach() - e)) / (2 * h)
        # central differences are exact for a piecewise-linear function unless a cell edge lies
        # within h; allow those rare points
        close = (fd - grad[:, k]).abs() < 1e-6
        assert close.float().mean() > 0.97
    assert grad.abs().max() > 0  # a real gradient, not zeros


def test_field_random_is_seeded_and_validates():
    a = InformationField.random(generator=torch.Generator().manual_seed(5))
    b = InformationField.random(generator=torch.Generator().manual_seed(5))
    c = InformationField.random(generator=torch.Generator().manual_seed(6))
    assert torch.equal(a.grid, b.grid) and not torch.equal(a.grid, c.grid)
    assert a.grid.dtype == torch.float64 and (a.grid >= 0).all()
    with pytest.raises(ValueError, match="extent"):
        InformationField(torch.zeros(3, 3), (1.0, 0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="saturation"):
        InformationField.random(saturation=1.5)
    with pytest.raises(ValueError, match="factor"):
        a.scaled(-1.0)
