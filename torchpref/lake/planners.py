r"""Two planners that trade distance for information: STOMP and RRT*.

Both minimise, for each weight ``w`` of a sweep, the cost of eq. ``cost = v_1 + w v_2`` of the
paper (Sec. IV.B) with ``v_1`` the path length and ``v_2 = \int (f_max - f(p)) ds`` the
information *missed* along the path, which is small where the field is high. A larger ``w``
gives longer paths that gather more information. Both planners handle the whole sweep at once:
STOMP as one ``n_w x K x T x 2`` tensor computation, RRT* by sharing one tree's vertices
(which do not depend on ``w``) and keeping a parent and a cost per weight.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor
from tqdm.auto import tqdm

from .field import InformationField, bilinear_sample
from .geometry import Lake
from .objectives import path_information, path_length, segment_midpoints

__all__ = ["stomp", "rrt_star", "path_cost", "pad_paths", "resample_by_arc_length", "shore_distance_grid"]


def _check_weights(weights) -> Tensor:
    w = torch.as_tensor(weights, dtype=torch.float64).reshape(-1)
    if w.numel() == 0 or not torch.isfinite(w).all() or (w < 0).any():
        raise ValueError(f"weights must be a non-empty set of finite non-negative numbers, got {w.tolist()[:5]}.")
    return w


def _weighted_cost(length: Tensor, info: Tensor, weights: Tensor, fmax: float) -> Tensor:
    r"""``v_1 + w v_2 = L + w (f_max L - I)``: a path's (or an edge's) length ``L`` and information
    ``I`` with weights ``w`` (broadcast)."""
    return length + weights * (fmax * length - info)


def path_cost(paths: Tensor, field: InformationField, weights: Tensor, *, step: float = 1.0) -> Tensor:
    r"""``cost = L + w (f_max L - I)`` for paths ``n_w x T x 2`` and weights ``n_w``; shape ``n_w``."""
    return _weighted_cost(path_length(paths), path_information(paths, field, step=step), weights, field.max)


def shore_distance_grid(
    lake: Lake, margin: float, spacing: float = 3.0
) -> tuple[Tensor, tuple[float, float, float, float]]:
    """:meth:`Lake.signed_distance` tabulated on a grid of ``spacing`` over the lake's bounds padded
    by ``2 margin + 10``: ``(grid, extent)`` for :func:`bilinear_sample`, a cheap differentiable
    shore penalty for optimisers (the exact test stays :meth:`Lake.path_on_water`)."""
    xmin, xmax, ymin, ymax = lake.bounds
    pad = 2 * margin + 10.0
    extent = (xmin - pad, xmax + pad, ymin - pad, ymax + pad)
    nx = int((extent[1] - extent[0]) / spacing) + 2
    ny = int((extent[3] - extent[2]) / spacing) + 2
    xs = torch.linspace(extent[0], extent[1], nx, dtype=torch.float64)
    ys = torch.linspace(extent[2], extent[3], ny, dtype=torch.float64)
    pts = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1)
    return lake.signed_distance(pts), extent


def pad_paths(paths: Sequence[Tensor]) -> Tensor:
    """Stack paths (each ``T_i x 2``, or batches ``n_i x T_i x 2``) into one ``n x T x 2`` tensor,
    the shorter ones padded by repeating their last point (which changes neither their length
    nor their information)."""
    batches = [p.unsqueeze(0) if p.dim() == 2 else p for p in paths]
    T = max(p.shape[1] for p in batches)
    return torch.cat([torch.cat([p, p[:, -1:].expand(-1, T - p.shape[1], -1)], dim=1) for p in batches])


def resample_by_arc_length(paths: Tensor, num_points: int) -> Tensor:
    r"""Waypoints spaced equally along polylines.

    Args:
        paths: ``... x T x 2``.
        num_points: waypoints wanted, ``>= 2``.

    Returns:
        ``... x num_points x 2``, with the same first and last points.
    """
    seg = (paths[..., 1:, :] - paths[..., :-1, :]).norm(dim=-1)
    cum = torch.cat([torch.zeros_like(seg[..., :1]), seg.cumsum(-1)], dim=-1)  # ... x T
    target = torch.linspace(0, 1, num_points, dtype=paths.dtype) * cum[..., -1:]
    j = torch.searchsorted(cum.contiguous(), target.contiguous(), right=True).clamp(1, paths.shape[-2] - 1)
    c0, c1 = cum.gather(-1, j - 1), cum.gather(-1, j)
    t = ((target - c0) / (c1 - c0).clamp_min(1e-12)).clamp(0, 1).unsqueeze(-1)
    idx = (j - 1).unsqueeze(-1).expand(*j.shape, 2)
    p0, p1 = paths.gather(-2, idx), paths.gather(-2, idx + 1)
    out = p0 + t * (p1 - p0)
    out[..., 0, :], out[..., -1, :] = paths[..., 0, :], paths[..., -1, :]
    return out


def _smooth_noise_factor(n: int) -> Tensor:
    """``L`` with ``L L^T`` proportional to ``R^{-1}``, ``R = A^T A`` and ``A`` the second differences
    of ``n`` interior waypoints with fixed ends, scaled so that the largest noise std is 1."""
    A = torch.zeros(n + 2, n, dtype=torch.float64)
    idx = torch.arange(n)
    A[idx, idx], A[idx + 1, idx], A[idx + 2, idx] = 1.0, -2.0, 1.0
    R_inv = torch.linalg.inv(A.T @ A)
    return torch.linalg.cholesky(R_inv) / R_inv.diagonal().max().sqrt()


class _StompState:
    """STOMP's path per weight, its smooth noise, the rollouts' cost and the best iterate on the water."""

    def __init__(
        self,
        lake: Lake,
        field: InformationField,
        w: Tensor,
        T: int,
        margin: float,
        penalty: float,
        subdivisions: int,
        generator: torch.Generator | None,
    ):
        self.lake, self.field, self.w, self.generator = lake, field, w, generator
        self.margin, self.penalty, self.subdivisions = margin, penalty, subdivisions
        self.L = _smooth_noise_factor(T - 2)
        self.sdf, self.sdf_extent = shore_distance_grid(lake, margin)
        s = torch.linspace(0, 1, T, dtype=torch.float64).unsqueeze(-1)
        self.straight = (lake.start + s * (lake.goal - lake.start)).expand(w.numel(), T, 2).clone()
        self.best = self.straight.clone()
        self.best_cost = torch.full((w.numel(),), float("inf"), dtype=torch.float64)

    def smooth_noise(self, *shape: int) -> Tensor:
        """``shape x n x 2`` noise, correlated along the path (``n`` interior waypoints)."""
        z = torch.randn(*shape, 2, self.L.shape[0], generator=self.generator, dtype=torch.float64)
        return (z @ self.L.T).transpose(-1, -2)

    def rollout_costs(self, paths: Tensor) -> Tensor:
        """``n_w x K x T x 2`` -> ``n_w x K``: the weighted cost plus the shore penalty."""
        mid, piece = segment_midpoints(paths, self.subdivisions)  # ... x T-1 x m x 2, ... x T-1
        f = self.field(mid)
        shore = torch.relu(bilinear_sample(self.sdf, self.sdf_extent, mid) + self.margin).pow(2)
        w4 = self.w.view(-1, 1, 1, 1)
        return (piece.unsqueeze(-1) * (1 + w4 * (self.field.max - f)) + self.penalty * shore / self.subdivisions).sum(
            (-1, -2)
        )

    def keep_best(self, paths: Tensor) -> None:
        """Keep, per weight, ``paths`` where it is on the water and cheaper than the best so far."""
        ok = self.lake.path_on_water(paths)
        c = torch.where(
            ok, path_cost(paths, self.field, self.w, step=2.0), torch.full_like(self.best_cost, float("inf"))
        )
        better = c < self.best_cost
        self.best[better] = paths[better]
        self.best_cost = torch.where(better, c, self.best_cost)


def _stomp_step(state: _StompState, theta: Tensor, sigma: float, K: int, temperature: float) -> Tensor:
    """One STOMP iteration: ``K`` rollouts of noise ``sigma`` around ``theta`` (``n_w x T x 2``, the
    first rollout unperturbed), moved by the cost-weighted noise and re-spaced along the path."""
    n_w, T = theta.shape[0], theta.shape[1]
    eps = sigma * state.smooth_noise(n_w, K)  # n_w x K x n x 2
    eps[:, 0] = 0.0  # the current path is a rollout too
    rollouts = theta.unsqueeze(1).repeat(1, K, 1, 1)
    rollouts[:, :, 1:-1] += eps
    S = state.rollout_costs(rollouts)  # n_w x K
    lo, hi = S.min(1, keepdim=True).values, S.max(1, keepdim=True).values
    P = torch.softmax(-temperature * (S - lo) / (hi - lo).clamp_min(1e-12), dim=1)
    theta = theta.clone()
    theta[:, 1:-1] += (P.view(n_w, K, 1, 1) * eps).sum(1)
    return resample_by_arc_length(theta, T)


def stomp(
    lake: Lake,
    field: InformationField,
    weights: Tensor | Sequence[float],
    *,
    generator: torch.Generator | None = None,
    num_waypoints: int = 40,
    num_rollouts: int = 16,
    iterations: int = 50,
    noise_std: float = 30.0,
    init_std: float = 200.0,
    temperature: float = 10.0,
    margin: float = 3.0,
    penalty: float = 50.0,
    subdivisions: int = 3,
    progress: bool = False,
) -> Tensor:
    r"""STOMP (Kalakrishnan et al. 2011) batched over a sweep of weights.

    Each iteration draws ``K`` smooth noisy rollouts ``theta + eps`` per weight, with
    ``eps ~ N(0, R^{-1})`` and ``R = A^T A`` the finite-difference acceleration metric (so
    the noise bends the path without kinks), scores each rollout by its cost
    ``sum_segments length (1 + w (f_max - f))`` plus a shore penalty
    ``penalty * relu(sd + margin)^2`` at the segment pieces, and moves the path by the
    cost-weighted noise ``sum_k P_k eps_k`` with ``P_k ~ exp(-h (S_k - min S) / (max S - min S))``
    (trajectory-level weights, as in PI^2; the unperturbed path is one of the rollouts).
    The waypoints are then re-spaced equally along the path, and the noise shrinks over the
    iterations. The best iterate per weight whose every segment is on the water (exact test)
    is returned, a local optimum near the random initial bend; the straight start-goal line is
    the fallback if no iterate was on the water.

    Args:
        lake: the lake; the straight line from start to goal should be on the water
            (true for :meth:`Lake.random`), else a ``RuntimeError`` may follow.
        field: the information field.
        weights: ``n_w`` non-negative weights ``w``.
        generator: the random source.
        num_waypoints: ``T``, waypoints including start and goal.
        num_rollouts: ``K`` noisy rollouts per iteration and weight.
        iterations: STOMP iterations.
        noise_std: the rollout noise's largest standard deviation at the first iteration.
        init_std: the standard deviation of a smooth random bend of the initial straight
            line (different bends reach different local optima, for diversity).
        temperature: ``h`` of the rollout weights.
        margin: distance to keep from the shore in the penalty.
        penalty: weight of the shore penalty.
        subdivisions: pieces per segment for the rollouts' cost integrals.
        progress: show a progress bar.

    Returns:
        Paths ``n_w x T x 2``, every segment on the water.
    """
    w = _check_weights(weights)
    if num_waypoints < 3:
        raise ValueError(f"num_waypoints must be at least 3, got {num_waypoints}.")
    if num_rollouts < 1:
        raise ValueError(f"num_rollouts must be positive, got {num_rollouts}.")
    if iterations < 0:
        raise ValueError(f"iterations must be non-negative, got {iterations}.")
    state = _StompState(lake, field, w, num_waypoints, margin, penalty, subdivisions, generator)
    theta = state.straight.clone()
    theta[:, 1:-1] += init_std * state.smooth_noise(w.numel())
    state.keep_best(theta)
    for it in tqdm(range(iterations), desc="STOMP", disable=not progress):
        sigma = noise_std * (1 - it / max(iterations, 1)) ** 2 + 1.0
        theta = _stomp_step(state, theta, sigma, num_rollouts, temperature)
        if it % 5 == 4 or it == iterations - 1:
            state.keep_best(theta)
    found = torch.isfinite(state.best_cost)
    if not found.all() and not bool(lake.path_on_water(state.straight[:1])):
        raise RuntimeError(
            "STOMP found no path on the water for some weights; the straight start-goal line crosses land."
        )
    return state.best


def _water_samples(lake: Lake, num_samples: int, goal_bias: float, generator: torch.Generator | None) -> Tensor:
    """``num_samples x 2`` points on the water drawn uniformly in the lake's bounds, each replaced by
    the goal with probability ``goal_bias``."""
    xmin, xmax, ymin, ymax = lake.bounds
    lo = torch.tensor([xmin, ymin], dtype=torch.float64)
    span = torch.tensor([xmax - xmin, ymax - ymin], dtype=torch.float64)
    samples = torch.empty(0, 2, dtype=torch.float64)
    while samples.shape[0] < num_samples:
        cand = lo + span * torch.rand(2 * num_samples, 2, generator=generator, dtype=torch.float64)
        samples = torch.cat([samples, cand[lake.contains(cand)]])
    samples = samples[:num_samples]
    to_goal = torch.rand(num_samples, generator=generator, dtype=torch.float64) < goal_bias
    samples[to_goal] = lake.goal
    return samples


class _Tree:
    """RRT*'s tree for ``n_w`` weights: shared vertices ``X``, and per weight each vertex's parent,
    cost from the start, and the length and information of the edge to its parent."""

    def __init__(self, start: Tensor, w: Tensor, fmax: float, size: int):
        n_w = w.numel()
        self.wcol, self.fmax = w.unsqueeze(-1), fmax
        self.X = torch.empty(size, 2, dtype=torch.float64)
        self.X[0] = start
        self.parent = torch.zeros(n_w, size, dtype=torch.long)
        self.cost = torch.zeros(n_w, size, dtype=torch.float64)
        self.edge_len = torch.zeros(n_w, size, dtype=torch.float64)
        self.edge_info = torch.zeros(n_w, size, dtype=torch.float64)
        self.count = 1

    def edge_cost(self, length: Tensor, info: Tensor) -> Tensor:
        """The weighted cost of edges, ``n_w x k`` from ``k`` lengths and informations."""
        return _weighted_cost(length, info, self.wcol, self.fmax)

    def refresh(self) -> None:
        """Recompute every vertex's cost from its parent's (after rewires left them stale)."""
        n = self.count
        e = self.edge_cost(self.edge_len[:, :n], self.edge_info[:, :n])
        e[:, 0] = 0.0
        for _ in range(n):
            new = self.cost[:, :n].gather(1, self.parent[:, :n]) + e
            new[:, 0] = 0.0
            if torch.equal(new, self.cost[:, :n]):
                break
            self.cost[:, :n] = new

    def add(self, new: Tensor, nb: Tensor, length: Tensor, info: Tensor) -> int:
        """Add vertex ``new`` with, per weight, the cheapest parent among the neighbours ``nb`` (edge
        lengths and informations ``length``, ``info``), rewire the neighbours that get cheaper
        through it, and return its index."""
        ecost = self.edge_cost(length, info)  # n_w x k
        via = self.cost[:, nb] + ecost
        best = via.argmin(-1)
        i = self.count
        self.X[i] = new
        self.parent[:, i] = nb[best]
        self.cost[:, i] = via.gather(1, best.unsqueeze(-1)).squeeze(-1)
        self.edge_len[:, i], self.edge_info[:, i] = length[best], info[best]
        self.count += 1
        through = self.cost[:, i : i + 1] + ecost
        rewire = through < self.cost[:, nb]
        if rewire.any():
            cols = nb.expand(self.parent.shape[0], -1)
            self.parent[:, nb] = torch.where(rewire, i, self.parent[:, nb])
            self.cost[:, nb] = torch.where(rewire, through, self.cost[:, nb])
            self.edge_len[:, nb] = torch.where(rewire, length.expand_as(cols), self.edge_len[:, nb])
            self.edge_info[:, nb] = torch.where(rewire, info.expand_as(cols), self.edge_info[:, nb])
        return i

    def paths_to(self, goal_index: int) -> Tensor:
        """``n_w x T_max x 2``: the path from the start to vertex ``goal_index`` for every weight,
        shorter ones padded by repeating the goal."""
        chains = [torch.full((self.parent.shape[0],), goal_index, dtype=torch.long)]
        while bool((chains[-1] != 0).any()):
            chains.append(self.parent.gather(1, chains[-1].unsqueeze(-1)).squeeze(-1))
        order = torch.stack(chains[::-1], dim=-1)  # n_w x T_max, starting with repeated 0s
        # move the leading repeated starts to the end as repeated goals
        lead = (order == 0).sum(-1) - 1
        T = order.shape[-1]
        pos = (torch.arange(T).unsqueeze(0) + lead.unsqueeze(-1)).clamp(max=T - 1)
        return self.X[order.gather(1, pos)]


def _extend(
    tree: _Tree, lake: Lake, field: InformationField, s: Tensor, step: float, radius: float, info_step: float
) -> Tensor | None:
    """Steer from the nearest vertex towards sample ``s`` and add the new vertex to ``tree`` from
    the neighbours within ``radius`` it can reach on the water: the vertex, or ``None`` if none."""
    X = tree.X[: tree.count]
    d = (X - s).norm(dim=-1)
    near = int(d.argmin())
    if float(d[near]) < 1e-9:
        return None
    new = s.clone() if float(d[near]) <= step else X[near] + (s - X[near]) * (step / float(d[near]))
    dn = (X - new).norm(dim=-1)
    nb = torch.nonzero(dn <= radius).squeeze(-1)
    ok = lake.segments_on_water(X[nb], new.expand(nb.numel(), 2))
    if not bool(ok.any()):
        return None
    nb = nb[ok]
    seg = torch.stack([X[nb], new.expand(nb.numel(), 2)], dim=-2)  # k x 2 x 2
    tree.add(new, nb, dn[nb], path_information(seg, field, step=info_step))
    return new


def rrt_star(
    lake: Lake,
    field: InformationField,
    weights: Tensor | Sequence[float],
    *,
    generator: torch.Generator | None = None,
    num_samples: int = 600,
    step: float = 30.0,
    radius: float = 45.0,
    goal_bias: float = 0.05,
    info_step: float = 2.0,
    recompute_every: int = 100,
    progress: bool = False,
) -> Tensor:
    r"""RRT* (Karaman and Frazzoli 2011) for a sweep of weights on one shared tree.

    Sampling, nearest-vertex steering and edge validity do not depend on ``w``, so all
    weights share the vertices; each weight keeps its own parent and cost per vertex, chooses
    the cheapest parent among the neighbours within ``radius`` and rewires them, vectorised
    over ``w``. After a rewire the descendants' costs are refreshed lazily (every
    ``recompute_every`` samples and at the end); stale costs are upper bounds, so no cycle can
    form. Every edge is checked exactly against the shoreline.

    Args:
        lake: the lake.
        field: the information field.
        weights: ``n_w`` non-negative weights ``w``.
        generator: the random source.
        num_samples: samples drawn (vertices added at most).
        step: steering distance.
        radius: neighbourhood radius for choosing parents and rewiring.
        goal_bias: probability of sampling the goal.
        info_step: integration step for the edges' information.
        recompute_every: samples between exact cost refreshes.
        progress: show a progress bar.

    Returns:
        Paths ``n_w x T_max x 2`` from start to goal, shorter ones padded by repeating the goal.
    """
    w = _check_weights(weights)
    if num_samples < 1:
        raise ValueError(f"num_samples must be positive, got {num_samples}.")
    if not (step > 0 and radius >= step):
        raise ValueError(f"need step > 0 and radius >= step, got step={step}, radius={radius}.")
    if not 0 <= goal_bias < 1:
        raise ValueError(f"goal_bias must be in [0, 1), got {goal_bias}.")
    samples = _water_samples(lake, num_samples, goal_bias, generator)
    tree = _Tree(lake.start, w, field.max, num_samples + 1)
    goal_index = -1
    for k in tqdm(range(num_samples), desc="RRT*", disable=not progress):
        new = _extend(tree, lake, field, samples[k], step, radius, info_step)
        if new is None:  # no vertex added: nothing to refresh either
            continue
        if goal_index < 0 and torch.equal(new, lake.goal):
            goal_index = tree.count - 1
        if (k + 1) % recompute_every == 0:
            tree.refresh()
    if goal_index < 0:
        raise RuntimeError(f"RRT* did not reach the goal in {num_samples} samples; raise num_samples or goal_bias.")
    tree.refresh()
    return tree.paths_to(goal_index)
