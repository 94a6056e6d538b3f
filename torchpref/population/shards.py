r"""The population's evidence over shards of people, on any ``concurrent.futures.Executor``
(threads, processes, or Dask's ``Client.get_executor()``): the same value and gradient as
:func:`torchpref.population.joint.evidence` to the mode's tolerance, without one process holding
every person's blocks.

Each round sends every shard the shared vectors (``u = m(U)``, ...) and takes back what the
master needs: per Newton step its log-likelihood, its gradients scattered onto ``U``, its block of
``M = sum_p S_p^T W~_p S_p``, then its own back-substitution. The gradient in the hyperparameters
is the partial derivative, at the fixed mode ``z`` and ``w = H^{-1} h`` (``h``: the gradient of
``-log|H| / 2`` in ``z``), of ``T = Psi + w^T grad Psi - log|H| / 2`` (the implicit-function
theorem); ``T`` is a sum of per-shard terms given the master's ``Q = L_U S^{-1} L_U^T`` (the
cotangent of ``M``), so each shard differentiates its own terms (in ``k_g``, ``u`` and
``v = L_U w_a``) and the master chains ``u``, ``v`` and ``log|S|`` through ``k_m``.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, replace
from typing import Any

import torch
from gpytorch.kernels import Kernel
from torch import Tensor

from torchpref.data.preference_data import PreferenceData
from torchpref.inference.laplace import LaplaceConvergenceWarning
from torchpref.inference.numerics import NotPSDError, batched_cholesky, cholesky_jittered, default_tolerance
from torchpref.inference.step_rule import STEP_RULE
from torchpref.population.joint import Layout, _person_covariance, _scatter_vector, person_blocks, scatter_blocks, schur
from torchpref.population.prior import _dense


def shard_layouts(people: Sequence[PreferenceData], layout_of: Any, shards: int) -> tuple[Tensor, list[Layout]]:
    """The distinct items ``U`` of everyone and one :class:`Layout` per shard of consecutive
    people, its ``index`` into that ``U``. ``layout_of(people)``: a population's layout."""
    U = torch.unique(torch.cat([p.train_X for p in people]), dim=0)
    row = {tuple(x.tolist()): i for i, x in enumerate(U)}
    k = min(shards, len(people))
    bounds = [round(i * len(people) / k) for i in range(k + 1)]
    out = []
    for start, stop in zip(bounds[:-1], bounds[1:]):
        lay = layout_of(people[start:stop])
        remap = torch.tensor([row[tuple(x.tolist())] for x in lay.U], dtype=torch.long)
        out.append(replace(lay, U=U, index=remap[lay.index]))
    return U, out


def _kg(k_g: Kernel):
    return lambda A, B: _dense(k_g, A, B)


def _fisher(f: Tensor, fisher: bool) -> Tensor | None:
    return torch.ones(f.shape[0], dtype=torch.bool) if fisher else None


def shard_point(lay: Layout, k_g: Kernel, u: Tensor, b: Tensor | None, fisher: bool) -> dict:
    """A shard at ``(u, b)``: ``psi_s`` (its log-likelihood less ``|b|^2 / 2``), ``R`` (its
    gradients scattered onto ``U``), ``gb``, its blocks and ``M_s``; ``ok`` false where a block is
    not positive definite with these weights."""
    with torch.no_grad():
        L_P, jitter = batched_cholesky(_person_covariance(lay, _kg(k_g)), "a person's k_g")
        b = L_P.new_zeros(L_P.shape[:-1]) if b is None else b
        f = u[lay.index] + (L_P @ b.unsqueeze(-1)).squeeze(-1)
        ll, r, weights = lay.obs.evaluate(f, _fisher(f, fisher))
        out = dict(psi=ll.sum() - 0.5 * (b * b).sum(), R=_scatter_vector(lay, r, u.shape[0]), b=b, L_P=L_P)
        out["jitter"] = jitter
        out["gb"] = (L_P.mT @ r.unsqueeze(-1)).squeeze(-1) - b
        try:
            C, W, Wt = person_blocks(lay, L_P, weights)
        except NotPSDError:
            return dict(out, ok=False)
        return dict(
            out,
            ok=True,
            C=C,
            W=W,
            M=scatter_blocks(lay, Wt, u.shape[0]),
            logdet=2 * C.diagonal(dim1=-2, dim2=-1).log().sum(),
        )


def shard_coupled(lay: Layout, s: dict, gb: Tensor) -> Tensor:
    """``sum_p S_p^T W_p L_p H_p^{-1} gb_p`` (``N``)."""
    t = torch.cholesky_solve(gb.unsqueeze(-1), s["C"])
    return _scatter_vector(lay, (s["W"] @ (s["L_P"] @ t)).squeeze(-1), s["M"].shape[0])


def shard_back(lay: Layout, s: dict, gb: Tensor, z: Tensor) -> Tensor:
    """``H_p^{-1} (gb_p - L_p^T W_p z_p)`` with ``z = L_U da``."""
    back = (s["L_P"].mT @ (s["W"] @ z[lay.index].unsqueeze(-1))).squeeze(-1)
    return torch.cholesky_solve((gb - back).unsqueeze(-1), s["C"]).squeeze(-1)


def _terms(lay: Layout, L_P: Tensor, u: Tensor, b: Tensor, Q: Tensor, fisher: bool) -> tuple[Tensor, Tensor, Tensor]:
    """``(log-likelihood, r, -log|H_p|/2 - tr(Q M_s)/2)`` at ``f = u[idx] + L_p b`` (differentiable)."""
    f = u[lay.index] + (L_P @ b.unsqueeze(-1)).squeeze(-1)
    ll, r, weights = lay.obs.evaluate(f, _fisher(f, fisher))
    C, _, Wt = person_blocks(lay, L_P, weights)
    Qs = Q[lay.index.unsqueeze(-1), lay.index.unsqueeze(-2)]
    phi = -C.diagonal(dim1=-2, dim2=-1).log().sum() - 0.5 * (Qs * Wt).sum()
    return ll.sum(), r, phi


def shard_h(lay: Layout, s: dict, u: Tensor, Q: Tensor, fisher: bool) -> tuple[Tensor, Tensor]:
    """The gradient of ``-log|H| / 2`` in ``(u, b_s)`` from this shard (at fixed hyperparameters)."""
    with torch.enable_grad():  # a worker may have been forked inside the master's no_grad block
        u, b = u.detach().requires_grad_(True), s["b"].detach().requires_grad_(True)
        _, _, phi = _terms(lay, s["L_P"], u, b, Q, fisher)
        if not phi.requires_grad:  # no observations in this shard
            return torch.zeros_like(u), torch.zeros_like(b)
        gu, gb = torch.autograd.grad(phi, (u, b), allow_unused=True)
    return (torch.zeros_like(u) if gu is None else gu), (torch.zeros_like(b) if gb is None else gb)


def shard_gradient(
    lay: Layout, k_g: Kernel, s: dict, u: Tensor, v: Tensor, w_b: Tensor, Q: Tensor, fisher: bool
) -> dict:
    """This shard's part of ``T`` and its gradient in ``k_g``'s parameters, ``u`` and ``v``."""
    with torch.enable_grad():  # a worker may have been forked inside the master's no_grad block
        return _shard_gradient(lay, k_g, s, u, v, w_b, Q, fisher)


def _shard_gradient(
    lay: Layout, k_g: Kernel, s: dict, u: Tensor, v: Tensor, w_b: Tensor, Q: Tensor, fisher: bool
) -> dict:
    params = [p for p in k_g.parameters() if p.requires_grad]
    u, v = u.detach().requires_grad_(True), v.detach().requires_grad_(True)
    K = _person_covariance(lay, _kg(k_g))
    eye = torch.eye(K.shape[-1], dtype=K.dtype)
    L_P = torch.linalg.cholesky(K + s["jitter"].to(K).reshape(-1, 1, 1) * eye)
    b = s["b"]
    ll, r, phi = _terms(lay, L_P, u, b, Q, fisher)
    lin = ((v[lay.index] + (L_P @ w_b.unsqueeze(-1)).squeeze(-1)) * r).sum() - (w_b * b).sum()
    T = ll - 0.5 * (b * b).sum() + lin + phi
    inputs = [u, v, *params]
    grads = torch.autograd.grad(T, inputs, allow_unused=True) if T.requires_grad else [None] * len(inputs)
    gu, gv, *theta = [torch.zeros_like(x) if g is None else g for x, g in zip(inputs, grads)]
    return dict(T=T.detach(), gu=gu, gv=gv, theta=[t.detach() for t in theta])


@dataclass
class ShardedProblem:
    """A population's layout in shards, evaluated on ``executor``."""

    U: Tensor
    shards: list[Layout]
    executor: Executor

    def map(self, fn: Callable[..., Any], *per_shard: Sequence, shared: tuple = ()) -> list:
        """``fn(layout, per_shard[0][i], ..., *shared)`` for each shard ``i`` on the executor, in order."""
        futures = [
            self.executor.submit(fn, lay, *(x[i] for x in per_shard), *shared) for i, lay in enumerate(self.shards)
        ]
        return [f.result() for f in futures]

    def points(self, k_g: Kernel, u: Tensor, b: list | None, fisher: bool) -> tuple[list[dict], bool]:
        """:func:`shard_point` of every shard, and whether all their blocks were positive definite."""
        bs = b if b is not None else [None] * len(self.shards)
        pts = self.map(shard_point, [k_g] * len(self.shards), [u] * len(self.shards), bs, [fisher] * len(self.shards))
        return pts, all(p["ok"] for p in pts)

    def solve(
        self, L_U: Tensor, S_chol: Tensor, pts: list[dict], ga: Tensor, gbs: list[Tensor]
    ) -> tuple[Tensor, list[Tensor]]:
        """``H^{-1} (ga, gb)`` over the shards (two rounds)."""
        coupled = sum(self.map(shard_coupled, pts, gbs))
        da = torch.cholesky_solve((ga - L_U.mT @ coupled).unsqueeze(-1), S_chol).squeeze(-1)
        z = L_U @ da
        return da, self.map(shard_back, pts, gbs, [z] * len(self.shards))


def _assemble(L_U: Tensor, a: Tensor, pts: list[dict]) -> tuple[Tensor, Tensor, Tensor | None]:
    psi = sum(p["psi"] for p in pts) - 0.5 * (a * a).sum()
    ga = L_U.mT @ sum(p["R"] for p in pts) - a
    S_chol = schur(L_U, sum(p["M"] for p in pts)) if all(p["ok"] for p in pts) else None
    return psi, ga, S_chol


def sharded_mode(problem: ShardedProblem, L_U: Tensor, k_g: Kernel, start: Any = None, max_iter: int = 100) -> dict:
    """Newton with Armijo backtracking over the shards (as :func:`~torchpref.population.joint.find_mode`)."""
    a = L_U.new_zeros(L_U.shape[-1]) if start is None else start[0]
    b = None if start is None else start[1]
    tol = default_tolerance(L_U.dtype)
    pts, fisher = problem.points(k_g, L_U @ a, b, False)[0], False
    for _ in range(max_iter):
        psi, ga, S_chol = _assemble(L_U, a, pts)
        if S_chol is None:  # a block not positive definite: Fisher weights for the step
            fisher = True
            hp = problem.points(k_g, L_U @ a, [p["b"] for p in pts], True)[0]
            S_chol = _assemble(L_U, a, hp)[2]
            if S_chol is None:
                raise NotPSDError("the population's Fisher-scoring Hessian is not positive definite")
        else:
            hp = pts
        gbs = [p["gb"] for p in pts]
        da, dbs = problem.solve(L_U, S_chol, hp, ga, gbs)
        dec = float((ga * da).sum() + sum((g * d).sum() for g, d in zip(gbs, dbs)))
        if 0.5 * dec < tol:
            return dict(a=a, pts=hp, S_chol=S_chol, fisher=fisher, converged=True)

        def trial(t: float, a: Tensor = a, pts: list = pts, da: Tensor = da, dbs: list = dbs) -> tuple:
            moved = problem.points(k_g, L_U @ (a + t * da), [p["b"] + t * d for p, d in zip(pts, dbs)], False)[0]
            return a + t * da, moved, sum(m["psi"] for m in moved) - 0.5 * ((a + t * da) ** 2).sum()

        taken = STEP_RULE.backtrack(trial, lambda q: float(q[2]), float(psi), dec)
        if taken is None:
            return dict(a=a, pts=hp, S_chol=S_chol, fisher=fisher, converged=0.5 * dec < STEP_RULE.stuck_tol)
        a, pts, fisher = taken[0], taken[1], False
    warnings.warn(
        f"Newton's method for the population's joint mode did not converge in {max_iter} iterations",
        LaplaceConvergenceWarning,
        stacklevel=2,
    )
    S_chol, fisher = _assemble(L_U, a, pts)[2], False
    if S_chol is None:
        pts, fisher = problem.points(k_g, L_U @ a, [p["b"] for p in pts], True)[0], True
        S_chol = _assemble(L_U, a, pts)[2]
    return dict(a=a, pts=pts, S_chol=S_chol, fisher=fisher, converged=False)


def sharded_objective(problem: ShardedProblem, kernels: Any, state: dict) -> Tensor:
    """``-(evidence + log priors)`` over the shards, its gradient in every kernel parameter
    (module docstring); the mode re-solved, warm-started from ``state``."""
    k_m, k_g, U = kernels.k_m, kernels.k_g, problem.U
    with torch.no_grad():
        L_U, j_U = cholesky_jittered(_dense(k_m, U, U), state.get("jitter_U"), "k_m(U, U)")
        mode = sharded_mode(problem, L_U, k_g, state.get("start"))
        a, pts, S_chol, fisher = mode["a"], mode["pts"], mode["S_chol"], mode["fisher"]
        logdet = sum(p["logdet"] for p in pts) + 2 * S_chol.diagonal().log().sum()
        value = sum(p["psi"] for p in pts) - 0.5 * (a * a).sum() - 0.5 * logdet
        Q = L_U @ torch.cholesky_solve(L_U.mT, S_chol)
        u, k = L_U @ a, len(problem.shards)
        hs = problem.map(shard_h, pts, shared=(u, Q, fisher))
        w_a, w_bs = problem.solve(L_U, S_chol, pts, L_U.mT @ sum(h[0] for h in hs), [h[1] for h in hs])
        v = L_U @ w_a
        gs = problem.map(shard_gradient, [k_g] * k, pts, [u] * k, [v] * k, w_bs, [Q] * k, [fisher] * k)
    state.update(jitter_U=j_U, start=(a, [p["b"] for p in pts]), L_U=L_U, a=a, S_chol=S_chol, evidence=float(value))
    K_U = _dense(k_m, U, U)
    L_t = torch.linalg.cholesky(K_U + j_U * torch.eye(K_U.shape[-1], dtype=K_U.dtype))
    S_t = L_t.mT @ sum(p["M"] for p in pts) @ L_t
    S_t = 0.5 * (S_t + S_t.mT) + torch.eye(S_t.shape[-1], dtype=S_t.dtype)
    T = -torch.linalg.cholesky(S_t).diagonal().log().sum() + (L_t @ a) @ sum(g["gu"] for g in gs)
    T = T + (L_t @ w_a) @ sum(g["gv"] for g in gs)
    params = [p for p in k_g.parameters() if p.requires_grad]
    for i, p in enumerate(params):
        T = T + (p * sum(g["theta"][i] for g in gs)).sum()
    return -(value + (T - T.detach()) + kernels.log_prior())
