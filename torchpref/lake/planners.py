r"""Two planners that trade distance for information: STOMP and RRT*.

Both minimise, for each weight ``w`` of a sweep, the cost of eq. ``cost = v_1 + w v_2`` of the
paper (Sec. IV.B) with ``v_1`` the path length and ``v_2 = \int (f_max - f(p)) ds`` the
information *missed* along the path, which is small where the field is high. A larger ``w``
gives longer paths that gather more information. Both planners handle the whole sweep at once:
STOMP as one ``n_w x K x T x 2`` tensor computation, RRT* by sharing one tree's vertices
(which do not depend on ``w``) and keeping a parent and a cost per weight.
"""

from __future__ import annotations

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


def path_cost(paths: Tensor, field: InformationField, weights: Tensor, *, step: float = 1.0) -> Tensor:
    r"""``cost = L + w (f_max L - I)`` for paths ``n_w x T x 2`` and weights ``n_w``; shape ``n_w``."""
    length = path_length(paths)
    info = path_information(paths, field, step=step)
    return length + weights * (field.max * length - info)


def shore_distance_grid(lake: Lake, margin: float, spacing: float = 3.0) -> tuple[Tensor, tuple[float, float, float, float]]:
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


def pad_paths(paths) -> Tensor:
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


def stomp(
    lake: Lake,
    field: InformationField,
    weights,
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
    n_w, T, K, n = w.numel(), num_waypoints, num_rollouts, num_waypoints - 2
    dt = torch.float64
    # A: second differences of the interior waypoints with fixed ends; R = A^T A
    A = torch.zeros(n + 2, n, dtype=dt)
    idx = torch.arange(n)
    A[idx, idx], A[idx + 1, idx], A[idx + 2, idx] = 1.0, -2.0, 1.0
    R_inv = torch.linalg.inv(A.T @ A)
    L = torch.linalg.cholesky(R_inv) / R_inv.diagonal().max().sqrt()  # largest noise std is 1

    xmin, xmax, ymin, ymax = lake.bounds
    sdf, sdf_extent = shore_distance_grid(lake, margin)
    fmax = field.max
    w4 = w.view(-1, 1, 1, 1)

    def rollout_costs(paths: Tensor) -> Tensor:  # n_w x K x T x 2 -> n_w x K
        mid, piece = segment_midpoints(paths, subdivisions)  # ... x T-1 x m x 2, ... x T-1
        f = field(mid)
        shore = torch.relu(bilinear_sample(sdf, sdf_extent, mid) + margin).pow(2)
        return (piece.unsqueeze(-1) * (1 + w4 * (fmax - f)) + penalty * shore / subdivisions).sum((-1, -2))

    s = torch.linspace(0, 1, T, dtype=dt).unsqueeze(-1)
    straight = (lake.start + s * (lake.goal - lake.start)).expand(n_w, T, 2).clone()

    def smooth_noise(*shape: int) -> Tensor:  # shape x n x 2, correlated along the path
        z = torch.randn(*shape, 2, n, generator=generator, dtype=dt)
        return (z @ L.T).transpose(-1, -2)

    theta = straight.clone()
    theta[:, 1:-1] += init_std * smooth_noise(n_w)
    best = straight.clone()
    best_cost = torch.full((n_w,), float("inf"), dtype=dt)

    def keep_best(paths: Tensor) -> None:
        nonlocal best_cost
        ok = lake.path_on_water(paths)
        c = torch.where(ok, path_cost(paths, field, w, step=2.0), torch.full_like(best_cost, float("inf")))
        better = c < best_cost
        best[better] = paths[better]
        best_cost = torch.where(better, c, best_cost)

    keep_best(theta)
    for it in tqdm(range(iterations), desc="STOMP", disable=not progress):
        sigma = noise_std * (1 - it / max(iterations, 1)) ** 2 + 1.0
        eps = sigma * smooth_noise(n_w, K)  # n_w x K x n x 2
        eps[:, 0] = 0.0  # the current path is a rollout too
        rollouts = theta.unsqueeze(1).repeat(1, K, 1, 1)
        rollouts[:, :, 1:-1] += eps
        S = rollout_costs(rollouts)  # n_w x K
        lo, hi = S.min(1, keepdim=True).values, S.max(1, keepdim=True).values
        P = torch.softmax(-temperature * (S - lo) / (hi - lo).clamp_min(1e-12), dim=1)
        theta = theta.clone()
        theta[:, 1:-1] += (P.view(n_w, K, 1, 1) * eps).sum(1)
        theta = resample_by_arc_length(theta, T)
        if it % 5 == 4 or it == iterations - 1:
            keep_best(theta)
    found = torch.isfinite(best_cost)
    if not found.all() and not bool(lake.path_on_water(straight[:1])):
        raise RuntimeError("STOMP found no path on the water for some weights; the straight start-goal line crosses land.")
    return best


def rrt_star(
    lake: Lake,
    field: InformationField,
    weights,
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
    dt = torch.float64
    n_w, N = w.numel(), num_samples + 1
    fmax = field.max
    wcol = w.unsqueeze(-1)
    # candidate samples on the water, drawn in one go
    xmin, xmax, ymin, ymax = lake.bounds
    lo = torch.tensor([xmin, ymin], dtype=dt)
    span = torch.tensor([xmax - xmin, ymax - ymin], dtype=dt)
    samples = torch.empty(0, 2, dtype=dt)
    while samples.shape[0] < num_samples:
        cand = lo + span * torch.rand(2 * num_samples, 2, generator=generator, dtype=dt)
        samples = torch.cat([samples, cand[lake.contains(cand)]])
    samples = samples[:num_samples]
    to_goal = torch.rand(num_samples, generator=generator, dtype=dt) < goal_bias
    samples[to_goal] = lake.goal

    X = torch.empty(N, 2, dtype=dt)
    X[0] = lake.start
    parent = torch.zeros(n_w, N, dtype=torch.long)
    cost = torch.zeros(n_w, N, dtype=dt)
    edge_len = torch.zeros(n_w, N, dtype=dt)  # length and information of the edge to the parent
    edge_info = torch.zeros(n_w, N, dtype=dt)
    count, goal_index = 1, -1

    def refresh() -> None:
        nonlocal cost
        e = edge_len[:, :count] + wcol * (fmax * edge_len[:, :count] - edge_info[:, :count])
        e[:, 0] = 0.0
        for _ in range(count):
            new = cost[:, :count].gather(1, parent[:, :count]) + e
            new[:, 0] = 0.0
            if torch.equal(new, cost[:, :count]):
                break
            cost[:, :count] = new

    for k in tqdm(range(num_samples), desc="RRT*", disable=not progress):
        s = samples[k]
        d = (X[:count] - s).norm(dim=-1)
        near = int(d.argmin())
        if float(d[near]) < 1e-9:
            continue
        new = s.clone() if float(d[near]) <= step else X[near] + (s - X[near]) * (step / float(d[near]))
        dn = (X[:count] - new).norm(dim=-1)
        nb = torch.nonzero(dn <= radius).squeeze(-1)
        ok = lake.segments_on_water(X[nb], new.expand(nb.numel(), 2))
        if not bool(ok.any()):
            continue
        nb = nb[ok]
        seg = torch.stack([X[nb], new.expand(nb.numel(), 2)], dim=-2)  # k x 2 x 2
        L = dn[nb]
        info = path_information(seg, field, step=info_step)
        ecost = L + wcol * (fmax * L - info)  # n_w x k
        via = cost[:, nb] + ecost
        best = via.argmin(-1)
        i = count
        X[i] = new
        parent[:, i] = nb[best]
        cost[:, i] = via.gather(1, best.unsqueeze(-1)).squeeze(-1)
        edge_len[:, i], edge_info[:, i] = L[best], info[best]
        count += 1
        if goal_index < 0 and torch.equal(new, lake.goal):
            goal_index = i
        # rewire: the neighbours that get cheaper through the new vertex
        through = cost[:, i : i + 1] + ecost
        rewire = through < cost[:, nb]
        if rewire.any():
            cols = nb.expand(n_w, -1)
            parent[:, nb] = torch.where(rewire, i, parent[:, nb])
            cost[:, nb] = torch.where(rewire, through, cost[:, nb])
            edge_len[:, nb] = torch.where(rewire, L.expand_as(cols), edge_len[:, nb])
            edge_info[:, nb] = torch.where(rewire, info.expand_as(cols), edge_info[:, nb])
        if (k + 1) % recompute_every == 0:
            refresh()
    if goal_index < 0:
        raise RuntimeError(f"RRT* did not reach the goal in {num_samples} samples; raise num_samples or goal_bias.")
    refresh()
    # backtrack from the goal for every weight
    chains = [torch.full((n_w,), goal_index, dtype=torch.long)]
    while bool((chains[-1] != 0).any()):
        chains.append(parent.gather(1, chains[-1].unsqueeze(-1)).squeeze(-1))
    order = torch.stack(chains[::-1], dim=-1)  # n_w x T_max, starting with repeated 0s
    # move the leading repeated starts to the end as repeated goals
    lead = (order == 0).sum(-1) - 1
    T = order.shape[-1]
    pos = (torch.arange(T).unsqueeze(0) + lead.unsqueeze(-1)).clamp(max=T - 1)
    return X[order.gather(1, pos)]
