r"""Plan a path for a learned utility: gradient ascent on the utility of a path's objectives.

:func:`plan_with_utility` moves the interior waypoints of a few starting paths (the best pool
paths by the utility) with ``torch.optim.Adam`` to maximise

.. math::
    U\big(\mathrm{path\_objectives}(p)\big)
    - \lambda \sum_t \mathrm{relu}(\mathrm{sd}(p_t) + \mathrm{margin})^2,

where ``sd`` is :meth:`Lake.signed_distance` (negative on the water) and the start and goal
stay fixed. The penalty keeps waypoints ``margin`` inside the shore; whether the segments
between them stay on the water is checked exactly afterwards (:meth:`Lake.path_on_water`).
The returned path is the on-water candidate (planned or starting pool path) of largest
utility, so it is never worse than the best starting pool path.

The lake knows nothing of learning: ``U`` is any differentiable function of the objectives
``[distance, information]`` in the lake's own units. A model that works on normalised objectives
is wrapped by its user (see :mod:`torchpref.experiments.lake`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from .objectives import path_objectives
from .planners import resample_by_arc_length

__all__ = ["PlanResult", "plan_with_utility"]


@dataclass
class PlanResult:
    """The outcome of :func:`plan_with_utility`.

    Attributes:
        path: ``T x 2`` the returned path (on the water).
        objectives: ``2`` its ``[distance, information]``.
        utility: its utility.
        planned: whether it is an optimised path (``False``: a pool path was kept).
        start_path: ``T x 2`` the best starting pool path.
        start_objectives, start_utility: the same for the best starting pool path.
    """

    path: Tensor
    objectives: Tensor
    utility: float
    planned: bool
    start_path: Tensor
    start_objectives: Tensor
    start_utility: float


def plan_with_utility(
    scenario,
    utility: Callable[[Tensor], Tensor],
    *,
    pool_paths: Tensor | None = None,
    pool_X: Tensor | None = None,
    num_starts: int = 3,
    num_points: int = 30,
    steps: int = 150,
    lr: float = 1.0,
    penalty: float = 10.0,
    margin: float = 1.0,
    step: float = 2.0,
) -> PlanResult:
    r"""Optimise a path for a learned utility.

    Args:
        scenario: a :class:`~torchpref.lake.scenario.LakeScenario`, or a ``(lake, field)``
            pair (then give ``pool_paths``).
        utility: maps objectives ``n x 2`` (``[distance, information]``, the lake's units) to
            ``n`` utilities, differentiably.
        pool_paths: ``n x T x 2`` paths to start from (default the scenario's training paths).
        pool_X: their objectives (default: computed).
        num_starts: how many of the best pool paths to optimise.
        num_points: waypoints of the optimised paths (start and goal included).
        steps: Adam steps.
        lr: Adam's learning rate (in the lake's length units).
        penalty: weight of the shoreline penalty.
        margin: how far inside the shore waypoints are pushed.
        step: integration step of the information along the path while optimising.

    Returns:
        A :class:`PlanResult`.
    """
    if isinstance(scenario, tuple):
        lake, field = scenario
        if pool_paths is None:
            raise ValueError("give pool_paths with a (lake, field) pair.")
    else:
        lake, field = scenario.lake, scenario.field
        if pool_paths is None:
            pool_paths, pool_X = scenario.train_paths, scenario.train_X
    pool_paths = pool_paths.to(torch.float64)
    if pool_X is None:
        pool_X = path_objectives(pool_paths, field)
    if num_starts < 1 or steps < 0:
        raise ValueError(f"need num_starts >= 1 and steps >= 0, got {num_starts} and {steps}.")

    def u_of(X: Tensor) -> Tensor:
        return utility(X).reshape(X.shape[:-1])

    with torch.no_grad():
        u_pool = u_of(pool_X)
    order = u_pool.argsort(descending=True)[:num_starts]
    start = resample_by_arc_length(pool_paths[order], num_points)
    first, last = start[:, :1].clone(), start[:, -1:].clone()
    inner = start[:, 1:-1].clone().requires_grad_(True)
    opt = torch.optim.Adam([inner], lr=lr)
    for _ in range(steps):
        opt.zero_grad()
        paths = torch.cat([first, inner, last], dim=1)
        u = u_of(path_objectives(paths, field, step=step))
        sd = lake.signed_distance(inner)
        loss = -u.sum() + penalty * torch.relu(sd + margin).pow(2).sum()
        loss.backward()
        opt.step()
    with torch.no_grad():
        planned = torch.cat([first, inner.detach(), last], dim=1)
        X_planned = path_objectives(planned, field)
        u_planned = u_of(X_planned)
        ok = lake.path_on_water(planned)
    best_start = int(order[0])
    best = PlanResult(pool_paths[best_start], pool_X[best_start], float(u_pool[best_start]), False,
                      pool_paths[best_start], pool_X[best_start], float(u_pool[best_start]))
    for i in range(planned.shape[0]):
        if bool(ok[i]) and float(u_planned[i]) > best.utility:
            best.path, best.objectives, best.utility, best.planned = planned[i], X_planned[i], float(u_planned[i]), True
    return best
