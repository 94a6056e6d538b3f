import pytest
import torch

from torchpref.lake import InformationField, path_information, path_length, path_objectives


@pytest.fixture
def field():
    return InformationField.random(generator=torch.Generator().manual_seed(7))


def brute_force_integral(path, field, n=200_000):
    """Trapezoid rule on a very fine uniform resampling of one polyline."""
    seg = (path[1:] - path[:-1]).norm(dim=-1)
    cum = torch.cat([torch.zeros(1, dtype=path.dtype), seg.cumsum(0)])
    s = torch.linspace(0, float(cum[-1]), n, dtype=path.dtype)
    j = torch.searchsorted(cum, s, right=True).clamp(1, len(path) - 1)
    t = ((s - cum[j - 1]) / seg[j - 1].clamp_min(1e-300)).unsqueeze(-1)
    pts = path[j - 1] + t * (path[j] - path[j - 1])
    return float(torch.trapezoid(field(pts), s))


def test_integral_matches_brute_force(field):
    gen = torch.Generator().manual_seed(1)
    paths = torch.rand(3, 6, 2, generator=gen, dtype=torch.float64) * torch.tensor([400.0, 300.0]) - torch.tensor(
        [200.0, 150.0]
    )
    info = path_information(paths, field, step=0.5)
    for k in range(3):
        ref = brute_force_integral(paths[k], field)
        assert info[k] == pytest.approx(ref, rel=1e-4)


def test_constant_field_gives_length_and_padding_is_harmless():
    const = InformationField(torch.full((5, 5), 2.5, dtype=torch.float64), (-10.0, 10.0, -10.0, 10.0))
    p = torch.tensor([[[0.0, 0.0], [3.0, 4.0], [3.0, 0.0]]], dtype=torch.float64)
    assert path_length(p).item() == pytest.approx(9.0)
    assert path_information(p, const).item() == pytest.approx(22.5)
    padded = torch.cat([p, p[:, -1:].expand(1, 3, 2)], dim=1)
    assert torch.allclose(path_objectives(padded, const), path_objectives(p, const))


def test_objectives_are_differentiable(field):
    p = torch.tensor([[-100.0, 0.0], [0.0, 40.0], [100.0, 0.0]], dtype=torch.float64, requires_grad=True)
    (g,) = torch.autograd.grad(path_length(p), p)
    assert torch.allclose(g[1], torch.tensor([0.0, 2 * 40 / (100**2 + 40**2) ** 0.5], dtype=torch.float64))
    (g,) = torch.autograd.grad(path_information(p, field), p)
    assert torch.isfinite(g).all() and g[1].abs().sum() > 0
    # zero-length (padding) segments keep gradients finite
    q = torch.tensor([[0.0, 0.0], [1.0, 1.0], [1.0, 1.0]], dtype=torch.float64, requires_grad=True)
    (g,) = torch.autograd.grad(path_length(q), q)
    assert torch.isfinite(g).all()


def test_objectives_validate(field):
    with pytest.raises(ValueError, match="step"):
        path_information(torch.zeros(2, 2, dtype=torch.float64), field, step=0.0)
    with pytest.raises(ValueError, match="T >= 2"):
        path_length(torch.zeros(1, 2, dtype=torch.float64))
