r"""The information field over the lake: a sum of 2-D Gaussians plus Perlin noise.

The field is stored on a regular grid and sampled bilinearly; the sampler is
differentiable with respect to the query points, so that planners can follow its gradient.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["InformationField", "bilinear_sample", "perlin_noise", "perlin_grid"]


def _fade(t: Tensor) -> Tensor:
    # quintic fade 6t^5 - 15t^4 + 10t^3 (Perlin 2002): zero first and second derivative at 0, 1
    return t * t * t * (t * (t * 6.0 - 15.0) + 10.0)


def perlin_noise(points: Tensor, gradients: Tensor) -> Tensor:
    r"""Evaluate 2-D gradient (Perlin) noise at points given in lattice coordinates.

    The lattice has a unit gradient at every integer point ``(i, j)``; the noise at a point is
    the faded bilinear blend of the four corner dot products ``g_ij . (p - (i, j))``. It is zero
    at every lattice point and continuous (C^2) everywhere.

    Args:
        points: ``... x 2`` coordinates ``(u, v)`` in lattice units, with
            ``0 <= u <= nu - 1`` and ``0 <= v <= nv - 1``; points outside are clamped.
        gradients: ``nu x nv x 2`` gradient vectors on the lattice.

    Returns:
        The noise, a tensor of shape ``...``.
    """
    if gradients.dim() != 3 or gradients.shape[-1] != 2 or min(gradients.shape[:2]) < 2:
        raise ValueError(f"gradients must be nu x nv x 2 with nu, nv >= 2, got {tuple(gradients.shape)}.")
    nu, nv = gradients.shape[0], gradients.shape[1]
    u = points[..., 0].clamp(0, nu - 1)
    v = points[..., 1].clamp(0, nv - 1)
    i0 = u.floor().long().clamp(max=nu - 2)
    j0 = v.floor().long().clamp(max=nv - 2)
    fu, fv = u - i0, v - j0

    def corner(di: int, dj: int) -> Tensor:
        g = gradients[i0 + di, j0 + dj]  # ... x 2
        return g[..., 0] * (fu - di) + g[..., 1] * (fv - dj)

    su, sv = _fade(fu), _fade(fv)
    bottom = torch.lerp(corner(0, 0), corner(1, 0), su)
    top = torch.lerp(corner(0, 1), corner(1, 1), su)
    return torch.lerp(bottom, top, sv)


def random_gradients(
    nu: int, nv: int, *, generator: torch.Generator | None = None, dtype: torch.dtype = torch.float64
) -> Tensor:
    """Random unit gradient vectors on an ``nu x nv`` lattice (angles uniform on the circle)."""
    angle = 2 * math.pi * torch.rand(nu, nv, generator=generator, dtype=dtype)
    return torch.stack([angle.cos(), angle.sin()], dim=-1)


def perlin_grid(
    shape: tuple[int, int],
    cells: int | tuple[int, int] = 4,
    *,
    octaves: int = 3,
    persistence: float = 0.5,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
) -> Tensor:
    r"""Fractal Perlin noise on a ``ny x nx`` grid: a sum of octaves with ``2^k cells`` lattice
    cells across and amplitudes ``persistence^k``.

    Args:
        shape: ``(ny, nx)``, the grid shape.
        cells: lattice cells across the grid in the first octave, ``(cells_x, cells_y)`` or one
            number for both.
        octaves: number of octaves, ``>= 1``.
        persistence: amplitude ratio between successive octaves, in ``(0, 1]``.
        generator: the random source of the gradients.

    Returns:
        A ``ny x nx`` tensor; the first and last rows and columns lie on lattice points.
    """
    ny, nx = shape
    if ny < 2 or nx < 2:
        raise ValueError(f"shape must be at least 2 x 2, got {shape}.")
    cx, cy = (cells, cells) if isinstance(cells, int) else cells
    if cx < 1 or cy < 1:
        raise ValueError(f"cells must be positive, got {cells}.")
    if octaves < 1:
        raise ValueError(f"octaves must be at least 1, got {octaves}.")
    if not 0 < persistence <= 1:
        raise ValueError(f"persistence must be in (0, 1], got {persistence}.")
    ys = torch.linspace(0, 1, ny, dtype=dtype)
    xs = torch.linspace(0, 1, nx, dtype=dtype)
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    out = torch.zeros(ny, nx, dtype=dtype)
    for k in range(octaves):
        fx, fy = cx * 2**k, cy * 2**k
        grads = random_gradients(fx + 1, fy + 1, generator=generator, dtype=dtype)
        out = out + persistence**k * perlin_noise(torch.stack([gx * fx, gy * fy], dim=-1), grads)
    return out


def bilinear_sample(grid: Tensor, extent: tuple[float, float, float, float], points: Tensor) -> Tensor:
    r"""Bilinear interpolation of a grid at arbitrary points, differentiable in the points.

    Grid node ``grid[i, j]`` sits at ``x = xmin + j (xmax - xmin) / (nx - 1)``,
    ``y = ymin + i (ymax - ymin) / (ny - 1)``. Points outside the extent take the value at the
    nearest edge (their gradient is then zero across the edge).

    Args:
        grid: ``ny x nx`` values.
        extent: ``(xmin, xmax, ymin, ymax)``.
        points: ``... x 2`` points ``(x, y)``.

    Returns:
        A tensor of shape ``...``.
    """
    if points.shape[-1] != 2:
        raise ValueError(f"points must have a last dimension of 2, got shape {tuple(points.shape)}.")
    ny, nx = grid.shape
    xmin, xmax, ymin, ymax = extent
    u = ((points[..., 0] - xmin) * ((nx - 1) / (xmax - xmin))).clamp(0, nx - 1)
    v = ((points[..., 1] - ymin) * ((ny - 1) / (ymax - ymin))).clamp(0, ny - 1)
    j0 = u.detach().floor().long().clamp(max=nx - 2)
    i0 = v.detach().floor().long().clamp(max=ny - 2)
    fu, fv = u - j0, v - i0
    flat = grid.reshape(-1)
    base = i0 * nx + j0
    g00, g01 = flat[base], flat[base + 1]
    g10, g11 = flat[base + nx], flat[base + nx + 1]
    return torch.lerp(torch.lerp(g00, g01, fu), torch.lerp(g10, g11, fu), fv)


class InformationField:
    r"""A scalar information field on a grid over a rectangle, sampled bilinearly.

    Args:
        grid: ``ny x nx`` field values (information per unit of path length).
        extent: ``(xmin, xmax, ymin, ymax)`` of the grid.
    """

    def __init__(self, grid: Tensor, extent: tuple[float, float, float, float]) -> None:
        grid = torch.as_tensor(grid)
        if grid.dim() != 2 or min(grid.shape) < 2:
            raise ValueError(f"grid must be a 2-D tensor of at least 2 x 2, got shape {tuple(grid.shape)}.")
        if not torch.isfinite(grid).all():
            raise ValueError("grid must be finite.")
        extent = tuple(float(e) for e in extent)  # type: ignore[assignment]
        if len(extent) != 4 or not (extent[0] < extent[1] and extent[2] < extent[3]):
            raise ValueError(f"extent must be (xmin, xmax, ymin, ymax) with xmin < xmax, ymin < ymax, got {extent}.")
        self.grid = grid
        self.extent = extent

    @property
    def max(self) -> float:
        """The largest value on the grid (an upper bound of the field everywhere)."""
        return float(self.grid.max())

    def __call__(self, points: Tensor) -> Tensor:
        """The field at ``... x 2`` points, a tensor of shape ``...`` (differentiable in the points)."""
        return bilinear_sample(self.grid, self.extent, points)

    def scaled(self, factor: float) -> InformationField:
        """The same field multiplied by a positive ``factor``."""
        if not factor > 0:
            raise ValueError(f"factor must be positive, got {factor}.")
        return InformationField(self.grid * factor, self.extent)

    @classmethod
    def random(
        cls,
        *,
        generator: torch.Generator | None = None,
        extent: tuple[float, float, float, float] = (-250.0, 250.0, -175.0, 175.0),
        shape: tuple[int, int] = (141, 201),
        num_gaussians: int = 8,
        amplitude: tuple[float, float] = (0.4, 1.0),
        width: tuple[float, float] = (25.0, 60.0),
        noise_amplitude: float = 0.4,
        noise_cells: int = 4,
        noise_octaves: int = 3,
        baseline: float = 0.05,
        saturation: float | None = 0.4,
        dtype: torch.dtype = torch.float64,
    ) -> InformationField:
        r"""A random field: ``baseline + sum_k a_k exp(-|p - c_k|^2 / (2 s_k^2)) + noise``, clamped at 0.

        Args:
            generator: the random source (centres, amplitudes, widths, Perlin gradients).
            extent: ``(xmin, xmax, ymin, ymax)``.
            shape: ``(ny, nx)`` grid shape.
            num_gaussians: number of Gaussian bumps.
            amplitude: range of the bumps' heights ``a_k`` (uniform).
            width: range of the bumps' standard deviations ``s_k`` (uniform).
            noise_amplitude: scale of the fractal Perlin noise.
            noise_cells: Perlin lattice cells across the shorter side in the first octave.
            noise_octaves: Perlin octaves.
            baseline: a constant added everywhere.
            saturation: if given, the field is capped at this quantile of its grid values,
                a sensor that saturates: high-information plateaus that planners seeking
                information follow, which makes long informative paths. ``None``: no cap.
        """
        if num_gaussians < 0:
            raise ValueError(f"num_gaussians must be non-negative, got {num_gaussians}.")
        for name, (lo, hi) in (("amplitude", amplitude), ("width", width)):
            if not 0 <= lo <= hi:
                raise ValueError(f"{name} must be a range 0 <= lo <= hi, got {(lo, hi)}.")
        if noise_amplitude < 0:
            raise ValueError(f"noise_amplitude must be non-negative, got {noise_amplitude}.")
        if saturation is not None and not 0 < saturation <= 1:
            raise ValueError(f"saturation must be in (0, 1], got {saturation}.")
        grid = baseline + _gaussian_bumps(extent, shape, num_gaussians, amplitude, width, generator, dtype)
        xmin, xmax, ymin, ymax = extent
        aspect = (xmax - xmin) / (ymax - ymin)
        cells = (
            (max(1, round(noise_cells * aspect)), noise_cells)
            if aspect >= 1
            else (noise_cells, max(1, round(noise_cells / aspect)))
        )
        noise = perlin_grid(shape, cells, octaves=noise_octaves, generator=generator, dtype=dtype)
        grid = (grid + noise_amplitude * noise).clamp_min(0.0)
        if saturation is not None:
            grid = grid.clamp_max(float(torch.quantile(grid, saturation)))
        return cls(grid, extent)


def _gaussian_bumps(
    extent: tuple[float, float, float, float],
    shape: tuple[int, int],
    num_gaussians: int,
    amplitude: tuple[float, float],
    width: tuple[float, float],
    generator: torch.Generator | None,
    dtype,
) -> Tensor:
    """``sum_k a_k exp(-|p - c_k|^2 / (2 s_k^2))`` on the ``shape`` grid over ``extent``, with centres
    ``c_k``, heights ``a_k`` and widths ``s_k`` drawn uniformly (in that order)."""
    xmin, xmax, ymin, ymax = extent
    ny, nx = shape
    ys = torch.linspace(ymin, ymax, ny, dtype=dtype)
    xs = torch.linspace(xmin, xmax, nx, dtype=dtype)
    pts = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1)  # ny x nx x 2

    def uniform(n: int, lo: float, hi: float) -> Tensor:
        return lo + (hi - lo) * torch.rand(n, generator=generator, dtype=dtype)

    centres = torch.stack([uniform(num_gaussians, xmin, xmax), uniform(num_gaussians, ymin, ymax)], -1)
    amps = uniform(num_gaussians, *amplitude)
    widths = uniform(num_gaussians, *width)
    d2 = (pts.unsqueeze(-2) - centres).pow(2).sum(-1)  # ny x nx x k
    return (amps * torch.exp(-0.5 * d2 / widths**2)).sum(-1)
