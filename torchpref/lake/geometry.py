r"""The lake: a closed shoreline polygon with a start and a goal on the water.

Point-in-polygon is the even-odd ray-crossing rule; "a segment stays on the water" is exact:
both ends inside and no proper crossing with a shoreline edge. The signed distance to the
shore (negative on the water) gives the planners a differentiable penalty.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["Lake"]


def _cross(a: Tensor, b: Tensor) -> Tensor:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


class Lake:
    r"""A lake bounded by a simple closed polygon.

    Args:
        vertices: ``n x 2`` shoreline vertices in order (the polygon closes itself; do not
            repeat the first vertex), ``n >= 3``.
        start: ``2`` start position, on the water.
        goal: ``2`` goal position, on the water.
    """

    def __init__(self, vertices: Tensor, start: Tensor, goal: Tensor) -> None:
        vertices = torch.as_tensor(vertices, dtype=torch.float64)
        if vertices.dim() != 2 or vertices.shape[-1] != 2 or vertices.shape[0] < 3:
            raise ValueError(f"vertices must be n x 2 with n >= 3, got shape {tuple(vertices.shape)}.")
        if not torch.isfinite(vertices).all():
            raise ValueError("vertices must be finite.")
        self.vertices = vertices
        self.start = self._check_point("start", start)
        self.goal = self._check_point("goal", goal)

    def _check_point(self, name: str, p) -> Tensor:
        p = torch.as_tensor(p, dtype=torch.float64)
        if p.shape != (2,) or not torch.isfinite(p).all():
            raise ValueError(f"{name} must be a finite 2-vector, got {p.tolist()}.")
        if not bool(self.contains(p)):
            raise ValueError(f"{name} {p.tolist()} is not on the water.")
        return p

    @property
    def edges(self) -> tuple[Tensor, Tensor]:
        """Shoreline edges as ``(a, b)``, each ``n x 2``: edge ``k`` runs from ``a[k]`` to ``b[k]``."""
        return self.vertices, self.vertices.roll(-1, dims=0)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, xmax, ymin, ymax)`` of the shoreline."""
        lo, hi = self.vertices.min(0).values, self.vertices.max(0).values
        return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])

    def contains(self, points: Tensor) -> Tensor:
        r"""Even-odd point-in-polygon test.

        Args:
            points: ``... x 2``.

        Returns:
            A bool tensor of shape ``...``.
        """
        a, b = self.edges
        p = points.unsqueeze(-2)  # ... x 1 x 2
        ay, by = a[:, 1], b[:, 1]
        straddles = (ay > p[..., 1]) != (by > p[..., 1])
        # x of the edge at the point's height; only used where the edge straddles
        t = (p[..., 1] - ay) / torch.where(by == ay, torch.ones_like(by), by - ay)
        x_cross = a[:, 0] + t * (b[:, 0] - a[:, 0])
        crossings = (straddles & (p[..., 0] < x_cross)).sum(-1)
        return crossings % 2 == 1

    def segments_cross_shore(self, p: Tensor, q: Tensor) -> Tensor:
        r"""Whether segments ``p -> q`` intersect a shoreline edge (touching counts).

        Args:
            p: ``... x 2`` segment starts.
            q: ``... x 2`` segment ends.

        Returns:
            A bool tensor of shape ``...``.
        """
        a, b = self.edges
        p, q = p.unsqueeze(-2), q.unsqueeze(-2)
        d, e = q - p, b - a
        denom = _cross(d, e)  # ... x n
        ap = a - p
        t_num, u_num = _cross(ap, e), _cross(ap, d)
        parallel = denom.abs() < 1e-12
        safe = torch.where(parallel, torch.ones_like(denom), denom)
        t, u = t_num / safe, u_num / safe
        hit = ~parallel & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)
        # collinear overlap: parallel and on the same line, with overlapping projections
        collinear = parallel & (t_num.abs() < 1e-9)
        if collinear.any():
            dd = (d * d).sum(-1).clamp_min(1e-300)
            s0 = (ap * d).sum(-1) / dd
            s1 = ((b - p) * d).sum(-1) / dd
            overlap = (torch.minimum(s0, s1) <= 1) & (torch.maximum(s0, s1) >= 0)
            hit = hit | (collinear & overlap)
        return hit.any(-1)

    def segments_on_water(self, p: Tensor, q: Tensor) -> Tensor:
        """Exact test that segments ``p -> q`` (``... x 2`` each) lie on the water; shape ``...``."""
        zero = (p == q).all(-1)
        return self.contains(p) & self.contains(q) & (zero | ~self.segments_cross_shore(p, q))

    def path_on_water(self, paths: Tensor) -> Tensor:
        r"""Whether every segment of polylines stays on the water.

        Args:
            paths: ``... x T x 2`` waypoints (repeated points, zero-length segments, are fine).

        Returns:
            A bool tensor of shape ``...``.
        """
        if paths.shape[-1] != 2 or paths.dim() < 2:
            raise ValueError(f"paths must be ... x T x 2, got shape {tuple(paths.shape)}.")
        return self.segments_on_water(paths[..., :-1, :], paths[..., 1:, :]).all(-1)

    def signed_distance(self, points: Tensor) -> Tensor:
        r"""Signed distance to the shoreline: negative on the water, positive on land.

        Differentiable in the points (almost everywhere).

        Args:
            points: ``... x 2``.

        Returns:
            A tensor of shape ``...``.
        """
        a, b = self.edges
        e = b - a
        p = points.unsqueeze(-2)
        t = (((p - a) * e).sum(-1) / (e * e).sum(-1).clamp_min(1e-300)).clamp(0, 1)
        closest = a + t.unsqueeze(-1) * e
        dist = (p - closest).pow(2).sum(-1).clamp_min(1e-300).sqrt().min(-1).values
        inside = self.contains(points.detach())
        return torch.where(inside, -dist, dist)

    @classmethod
    def random(
        cls,
        *,
        generator: torch.Generator | None = None,
        num_vertices: int = 96,
        radii: tuple[float, float] = (230.0, 160.0),
        roughness: float = 0.12,
        harmonics: int = 5,
        start_fraction: float = 0.82,
        span: float | None = 390.0,
    ) -> Lake:
        r"""A smooth random lake, star-shaped about the origin.

        The radius at angle ``theta`` is an ellipse's, ``radii = (rx, ry)``, times
        ``1 + sum_{k=2}^{harmonics+1} c_k cos(k theta + phi_k)`` with ``c_k`` uniform in
        ``roughness * [-1, 1] / k``. Start and goal sit at ``start_fraction`` of the radius on
        opposite ends of the long axis, so the straight line between them runs through the
        origin and, the lake being star-shaped, lies on the water. If ``span`` is given, the
        lake is scaled so that start and goal are ``span`` apart.
        """
        if num_vertices < 8:
            raise ValueError(f"num_vertices must be at least 8, got {num_vertices}.")
        if not 0 <= roughness < 0.5:
            raise ValueError(f"roughness must be in [0, 0.5), got {roughness}.")
        if not 0 < start_fraction < 1:
            raise ValueError(f"start_fraction must be in (0, 1), got {start_fraction}.")
        rx, ry = radii
        if not (rx > 0 and ry > 0):
            raise ValueError(f"radii must be positive, got {radii}.")
        dt = torch.float64
        theta = torch.arange(num_vertices, dtype=dt) * (2 * math.pi / num_vertices)
        ks = torch.arange(2, harmonics + 2, dtype=dt)
        coef = roughness * (2 * torch.rand(harmonics, generator=generator, dtype=dt) - 1) / ks * 2
        phase = 2 * math.pi * torch.rand(harmonics, generator=generator, dtype=dt)

        def radius(th: Tensor) -> Tensor:
            wobble = 1 + (coef * torch.cos(ks * th.unsqueeze(-1) + phase)).sum(-1)
            ellipse = rx * ry / torch.sqrt((ry * th.cos()) ** 2 + (rx * th.sin()) ** 2)
            return ellipse * wobble

        r = radius(theta)
        vertices = torch.stack([r * theta.cos(), r * theta.sin()], -1)
        ends = torch.tensor([math.pi, 0.0], dtype=dt)
        re = start_fraction * radius(ends)
        start = torch.stack([re[0] * ends[0].cos(), re[0] * ends[0].sin()])
        goal = torch.stack([re[1] * ends[1].cos(), re[1] * ends[1].sin()])
        if span is not None:
            if not span > 0:
                raise ValueError(f"span must be positive, got {span}.")
            scale = span / float((goal - start).norm())
            vertices, start, goal = vertices * scale, start * scale, goal * scale
        return cls(vertices, start, goal)
