r"""Path objectives: length and the path integral of the information field.

Paths are polylines ``... x T x 2``. Paths of different lengths share one tensor by repeating
their last point: zero-length segments add nothing to either objective.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

__all__ = ["path_length", "path_information", "path_objectives", "segment_midpoints"]


def _check_paths(paths: Tensor) -> None:
    if paths.dim() < 2 or paths.shape[-1] != 2 or paths.shape[-2] < 2:
        raise ValueError(f"paths must be ... x T x 2 with T >= 2, got shape {tuple(paths.shape)}.")


def path_length(paths: Tensor) -> Tensor:
    r"""Length of polylines, ``sum_t |p_{t+1} - p_t|``.

    Args:
        paths: ``... x T x 2``.

    Returns:
        A tensor of shape ``...``.
    """
    _check_paths(paths)
    seg2 = (paths[..., 1:, :] - paths[..., :-1, :]).pow(2).sum(-1)
    # the clamp keeps the gradient finite on zero-length (padding) segments
    return torch.where(seg2 > 0, seg2.clamp_min(1e-300).sqrt(), torch.zeros_like(seg2)).sum(-1)


def segment_midpoints(paths: Tensor, subdivisions: int) -> tuple[Tensor, Tensor]:
    r"""Split each segment into ``subdivisions`` equal pieces.

    Args:
        paths: ``... x T x 2``.
        subdivisions: pieces per segment, ``m``.

    Returns:
        ``(midpoints, lengths)``: the pieces' midpoints ``... x (T-1) x m x 2`` and each
        segment's piece length ``... x (T-1)`` (segment length / ``m``).
    """
    if subdivisions < 1:
        raise ValueError(f"subdivisions must be at least 1, got {subdivisions}.")
    p, q = paths[..., :-1, :], paths[..., 1:, :]
    s = (torch.arange(subdivisions, dtype=paths.dtype, device=paths.device) + 0.5) / subdivisions
    mid = p.unsqueeze(-2) + s.unsqueeze(-1) * (q - p).unsqueeze(-2)
    seg = (q - p).pow(2).sum(-1)
    length = torch.where(seg > 0, seg.clamp_min(1e-300).sqrt(), torch.zeros_like(seg))
    return mid, length / subdivisions


def path_information(paths: Tensor, field: Callable[[Tensor], Tensor], *, step: float = 1.0) -> Tensor:
    r"""Path integral of the field along polylines, ``\int_path f(p) ds`` (midpoint rule).

    Every segment is cut into ``ceil(max segment length / step)`` equal pieces (one number
    for the whole batch, so it vectorises), and the field is taken at the pieces' midpoints.
    Differentiable in the waypoints.

    Args:
        paths: ``... x T x 2``.
        field: maps ``... x 2`` points to ``...`` values (e.g. an ``InformationField``).
        step: the largest piece length.

    Returns:
        A tensor of shape ``...``.
    """
    _check_paths(paths)
    if not step > 0:
        raise ValueError(f"step must be positive, got {step}.")
    longest = float((paths[..., 1:, :] - paths[..., :-1, :]).detach().norm(dim=-1).max())
    m = max(1, int(-(-longest // step)))
    mid, piece = segment_midpoints(paths, m)
    return (field(mid).sum(-1) * piece).sum(-1)


def path_objectives(paths: Tensor, field: Callable[[Tensor], Tensor], *, step: float = 1.0) -> Tensor:
    r"""The objective vector ``[distance, information]`` of each path.

    Args:
        paths: ``... x T x 2``.
        field: the information field.
        step: the integration step of :func:`path_information`.

    Returns:
        A ``... x 2`` tensor.
    """
    return torch.stack([path_length(paths), path_information(paths, field, step=step)], dim=-1)
