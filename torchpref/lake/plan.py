r"""Plan a path for a utility of its objectives: gradient ascent from several starting paths.

:func:`plan_with_utility` moves the interior waypoints of a few starting paths with
``torch.optim.Adam`` to maximise

.. math::
    U\big(\mathrm{path\_objectives}(p)\big)
    - \lambda \sum_t \mathrm{relu}(\mathrm{sd}(p_t) + \mathrm{margin})^2,

where ``sd`` is the signed distance to the shore (negative on the water; tabulated by
:func:`~torchpref.lake.planners.shore_distance_grid`) and the start and goal stay fixed. The penalty keeps waypoints ``margin`` inside the shore; whether the segments
between them stay on the water is checked exactly afterwards (:meth:`Lake.path_on_water`).

The candidates are the optimised paths, the starting paths as they were and a *fallback* path;
the one of largest ``U`` among those on the water is returned, and the fallback is kept unless
another candidate's ``U`` is strictly larger. With ``U`` a risk-aware criterion (a lower
confidence bound of the improvement over the fallback, say) the plan therefore never leaves
the fallback unless the criterion says so.

The lake knows nothing of learning: ``U`` is any differentiable function of the objectives
``[distance, information]`` in the lake's own units. A model that works on normalised objectives
is wrapped by its user (see :mod:`torchpref.experiments.lake`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from .field import bilinear_sample
from .objectives import path_objectives
from .planners import pad_paths, resample_by_arc_length, shore_distance_grid

if TYPE_CHECKING:
    from torchpref.lake.scenario import LakeScenario

__all__ = ["PlanResult", "plan_with_utility", "SOURCES"]

SOURCES = ("fallback", "start", "planned")
"""Where a :class:`PlanResult`'s path comes from."""


@dataclass
class PlanResult:
    """The outcome of :func:`plan_with_utility`.

    Attributes:
        path: ``T x 2`` the returned path (on the water).
        objectives: ``2`` its ``[distance, information]``.
        utility: its utility.
        source: ``"planned"`` (an optimised path), ``"start"`` (a starting path as it was) or
            ``"fallback"`` (the fallback path was kept).
        fallback_path: ``T' x 2`` the fallback path.
        fallback_objectives, fallback_utility: its objectives and utility.
    """

    path: Tensor
    objectives: Tensor
    utility: float
    source: str
    fallback_path: Tensor
    fallback_objectives: Tensor
    fallback_utility: float

    @property
    def planned(self) -> bool:
        """Whether the returned path is an optimised one."""
        return self.source == "planned"


def _optimise(
    lake, field, utility, start: Tensor, steps: int, lr: float, penalty: float, margin: float, step: float
) -> Tensor:
    """Adam on the interior waypoints of ``start`` (``k x T x 2``); returns the final paths."""
    sdf, extent = shore_distance_grid(lake, margin)
    first, last = start[:, :1].clone(), start[:, -1:].clone()
    inner = start[:, 1:-1].clone().requires_grad_(True)
    opt = torch.optim.Adam([inner], lr=lr)
    for _ in range(steps):
        opt.zero_grad()
        paths = torch.cat([first, inner, last], dim=1)
        u = utility(path_objectives(paths, field, step=step))
        sd = bilinear_sample(sdf, extent, inner)
        loss = -u.sum() + penalty * torch.relu(sd + margin).pow(2).sum()
        loss.backward()
        opt.step()
    return torch.cat([first, inner.detach(), last], dim=1)


def plan_with_utility(
    scenario: LakeScenario,
    utility: Callable[[Tensor], Tensor],
    *,
    starts: Tensor | None = None,
    fallback: Tensor | None = None,
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
    r"""Optimise paths for a utility of their objectives and keep the best candidate.

    Args:
        scenario: a :class:`~torchpref.lake.scenario.LakeScenario`, or a ``(lake, field)``
            pair (then give ``starts`` and ``fallback``, or ``pool_paths``).
        utility: maps objectives ``n x 2`` (``[distance, information]``, the lake's units) to
            ``n`` utilities, differentiably. The same function optimises the paths and
            chooses among the candidates.
        starts: ``k x T x 2`` paths to optimise (any ``T``; they are resampled to
            ``num_points`` waypoints). Default: the ``num_starts`` pool paths of largest utility.
        fallback: ``T' x 2`` the path returned unless a candidate has a strictly larger
            utility. Default: the pool path of largest utility.
        pool_paths: ``n x T x 2`` pool paths for the defaults (default: the scenario's
            training paths).
        pool_X: their objectives (default: computed).
        num_starts: how many pool paths to start from when ``starts`` is not given.
        num_points: waypoints of the optimised paths (start and goal included).
        steps: Adam steps.
        lr: Adam's learning rate (in the lake's length units).
        penalty: weight of the shoreline penalty.
        margin: how far inside the shore waypoints are pushed.
        step: integration step of the information along the path while optimising.

    Returns:
        A :class:`PlanResult`; its path is on the water whenever the fallback is.
    """
    if num_starts < 1 or steps < 0 or num_points < 2:
        raise ValueError(
            f"need num_starts >= 1, steps >= 0 and num_points >= 2, got {num_starts}, {steps} and {num_points}."
        )
    if isinstance(scenario, tuple):
        lake, field = scenario
    else:
        lake, field = scenario.lake, scenario.field
        if pool_paths is None:
            pool_paths, pool_X = scenario.train_paths, scenario.train_X

    def u_of(X: Tensor) -> Tensor:
        return utility(X).reshape(X.shape[:-1])

    starts, fallback = _starts_and_fallback(field, u_of, starts, fallback, pool_paths, pool_X, num_starts)
    planned = _optimise(lake, field, u_of, resample_by_arc_length(starts, num_points), steps, lr, penalty, margin, step)
    return _best_candidate(lake, field, u_of, fallback, starts, planned)


def _starts_and_fallback(
    field,
    u_of: Callable[[Tensor], Tensor],
    starts: Tensor | None,
    fallback: Tensor | None,
    pool_paths: Tensor | None,
    pool_X: Tensor | None,
    num_starts: int,
) -> tuple[Tensor, Tensor]:
    """The starting paths and the fallback path, float64, checked; those not given are the
    pool paths of largest utility."""
    if starts is None or fallback is None:
        if pool_paths is None:
            raise ValueError("give starts and fallback, or pool_paths, with a (lake, field) pair.")
        pool_paths = pool_paths.to(torch.float64)
        pool_X = path_objectives(pool_paths, field) if pool_X is None else pool_X
        with torch.no_grad():
            order = u_of(pool_X).argsort(descending=True)
        starts = pool_paths[order[:num_starts]] if starts is None else starts
        fallback = pool_paths[order[0]] if fallback is None else fallback
    starts = torch.as_tensor(starts, dtype=torch.float64)
    fallback = torch.as_tensor(fallback, dtype=torch.float64)
    if starts.dim() != 3 or starts.shape[0] < 1 or starts.shape[-1] != 2 or fallback.dim() != 2:
        raise ValueError(
            f"starts must be k x T x 2 (k >= 1) and fallback T x 2, got shapes {tuple(starts.shape)} "
            f"and {tuple(fallback.shape)}."
        )
    return starts, fallback


def _best_candidate(
    lake, field, u_of: Callable[[Tensor], Tensor], fallback: Tensor, starts: Tensor, planned: Tensor
) -> PlanResult:
    """The candidate of largest utility among those on the water; the fallback unless another's is
    strictly larger."""
    with torch.no_grad():
        # one batch, so that equal paths get equal objectives (the quadrature follows the batch)
        candidates = pad_paths([fallback, starts, planned])
        X = path_objectives(candidates, field)
        u = u_of(X)
        ok = lake.path_on_water(candidates)
    source = ["fallback"] + ["start"] * starts.shape[0] + ["planned"] * planned.shape[0]
    best = 0
    for i in range(1, candidates.shape[0]):
        if bool(ok[i]) and float(u[i]) > float(u[best]):
            best = i
    path = fallback if best == 0 else candidates[best]
    return PlanResult(path, X[best], float(u[best]), source[best], fallback, X[0], float(u[0]))
