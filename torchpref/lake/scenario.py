r"""The lake-monitoring scenario of the paper (Sec. IV.B): a lake, an information field and
training and test sets of planned paths with their objectives ``[distance, information]``."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .field import InformationField
from .geometry import Lake
from .objectives import path_objectives
from .planners import rrt_star, stomp

__all__ = ["LakeScenario", "make_scenario", "PLANNERS"]

PLANNERS = ("stomp", "rrt_star")
"""Planner names; ``LakeScenario.train_planner`` holds indices into this tuple."""


@dataclass
class LakeScenario:
    r"""A lake, its field and two sets of paths.

    Attributes:
        lake: the lake with start and goal.
        field: the information field (already scaled, see :func:`make_scenario`).
        train_paths: ``n x T x 2`` paths (shorter ones padded by repeating the goal).
        train_X: ``n x 2`` objectives ``[distance, information]`` of the training paths.
        train_planner: ``n`` planner indices into :data:`PLANNERS`.
        train_weights: ``n`` weights ``w`` the paths were planned with.
        test_paths, test_X, test_planner, test_weights: the same for the test set.
    """

    lake: Lake
    field: InformationField
    train_paths: Tensor
    train_X: Tensor
    train_planner: Tensor
    train_weights: Tensor
    test_paths: Tensor
    test_X: Tensor
    test_planner: Tensor
    test_weights: Tensor


def _pad_cat(a: Tensor, b: Tensor) -> Tensor:
    T = max(a.shape[1], b.shape[1])

    def pad(p: Tensor) -> Tensor:
        return torch.cat([p, p[:, -1:].expand(-1, T - p.shape[1], -1)], dim=1)

    return torch.cat([pad(a), pad(b)])


def make_scenario(
    seed: int | None = None,
    *,
    generator: torch.Generator | None = None,
    paths_per_planner: int = 100,
    weight_range: tuple[float, float] = (0.01, 1000.0),
    share_five: float | None = 0.1,
    lake: Lake | None = None,
    field: InformationField | None = None,
    stomp_options: dict | None = None,
    rrt_options: dict | None = None,
    progress: bool = False,
) -> LakeScenario:
    r"""Build a lake-monitoring scenario.

    Each set has ``paths_per_planner`` STOMP and as many RRT* paths, planned for weights drawn
    log-uniformly from ``weight_range`` (sorted) in the dimensionless cost
    ``L + w (L - I / f_max)``. That cost does not change when the field is scaled, so the
    paths are planned first and the field is then scaled so that a share ``share_five`` of
    the training paths gets the paper's operator's top rating (information >= 150 and
    distance < 500): the thresholds then mean the same whatever the seed.

    Args:
        seed: a seed for a fresh ``torch.Generator`` (give this or ``generator``).
        generator: the random source.
        paths_per_planner: paths per planner and set (paper: 100).
        weight_range: ``(w_min, w_max)`` of the weight sweep, ``0 < w_min <= w_max``.
        share_five: the share of training paths to be rated 5 by
            :class:`~torchpref.lake.operator.LakeOperator` after scaling the field;
            ``None`` leaves the field as it is.
        lake: a lake to use instead of a random one.
        field: a field to use instead of a random one.
        stomp_options: keyword arguments for :func:`~torchpref.lake.planners.stomp`.
        rrt_options: keyword arguments for :func:`~torchpref.lake.planners.rrt_star`.
        progress: show progress bars.
    """
    if (seed is None) == (generator is None):
        raise ValueError(f"give exactly one of seed and generator, got seed={seed}, generator={generator}.")
    if generator is None:
        generator = torch.Generator().manual_seed(int(seed))
    if paths_per_planner < 1:
        raise ValueError(f"paths_per_planner must be positive, got {paths_per_planner}.")
    w_min, w_max = weight_range
    if not 0 < w_min <= w_max:
        raise ValueError(f"weight_range must satisfy 0 < w_min <= w_max, got {weight_range}.")
    lake = Lake.random(generator=generator) if lake is None else lake
    if field is None:
        xmin, xmax, ymin, ymax = lake.bounds
        field = InformationField.random(generator=generator, extent=(xmin - 5, xmax + 5, ymin - 5, ymax + 5))
    if share_five is not None and not 0 < share_five < 1:
        raise ValueError(f"share_five must be in (0, 1), got {share_five}.")

    def one_set() -> tuple[Tensor, Tensor, Tensor, Tensor]:
        u = torch.rand(paths_per_planner, generator=generator, dtype=torch.float64)
        w = torch.exp(math.log(w_min) + u * (math.log(w_max) - math.log(w_min))).sort().values
        # the cost's information term is f_max L - I: scale w so that it means the same per unit field
        w_eff = w / field.max
        a = stomp(lake, field, w_eff, generator=generator, progress=progress, **(stomp_options or {}))
        b = rrt_star(lake, field, w_eff, generator=generator, progress=progress, **(rrt_options or {}))
        paths = _pad_cat(a, b)
        planner = torch.cat([torch.zeros(paths_per_planner), torch.ones(paths_per_planner)]).long()
        return paths, path_objectives(paths, field), planner, torch.cat([w, w])

    train = one_set()
    test = one_set()
    if share_five is not None:
        X = train[1]
        short = X[X[:, 0] < 500.0, 1].sort(descending=True).values
        k = min(max(1, round(share_five * X.shape[0])), short.numel())
        if k == 0 or not short[0] > 0:
            raise RuntimeError("no training path is short enough (< 500) to be rated 5.")
        # the k-th most informative short path lands halfway above 150
        edge = short[k - 1] if k == short.numel() else 0.5 * (short[k - 1] + short[k])
        scale = 150.0 / float(edge)
        field = field.scaled(scale)
        train = (train[0], train[1] * torch.tensor([1.0, scale], dtype=torch.float64), *train[2:])
        test = (test[0], test[1] * torch.tensor([1.0, scale], dtype=torch.float64), *test[2:])
    return LakeScenario(lake, field, *train, *test)
