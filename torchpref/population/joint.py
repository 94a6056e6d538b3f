r"""The hierarchical Laplace problem of a population, solved through its structure: one Newton
loop (:func:`newton`) over a small interface (:class:`JointProblem`), which the shards of people
implement wherever they live (:class:`Shards` over a :class:`~torchpref.population.hosts.Host`:
this process, an executor's workers, a Dask cluster).

Person ``p``'s utility is ``f_p(x) = m(x) + g_p(x)``: ``m ~ GP(0, k_m)`` the population's mean
utility, ``g_p ~ GP(0, k_g)`` the person's deviation, independent across people. ``m`` is
represented at ``M`` items ``Z`` (:mod:`torchpref.population.shards`): ``m(Z) = L_Z a``. In
whitened coordinates ``a`` (``M``) and ``b_p`` (``g_p = L_p b_p``) the log posterior is

.. math::
    \Psi(a, b) = \sum_p \log p(Y_p \mid \Phi_p a + L_p b_p) - \tfrac12 a^\top a - \tfrac12 \sum_p b_p^\top b_p .

Its negative Hessian is an arrow (per-person blocks ``H_p = I + L_p^T W_p L_p`` coupled through the
``M x M`` block of ``a``); Newton's steps and the log-determinant go through the Schur complement
``S = I + sum_p Phi_p^T W~_p Phi_p``, so ``log|H| = sum_p log|H_p| + log|S|``: per step
``P n^3`` for the people, ``M^3`` for ``S`` and ``N M^2`` to form it (``N^2 M`` through a scatter
where many people share few items), never ``(sum_p n_p)^3``. With ``Z`` every distinct item
(``M = N``) this is the exact hierarchical model given Laplace; with fewer, the mean is the GP
given its values at ``Z`` (the person's deviation stays exact).

The posterior of ``a`` is ``N(a*, S^{-1})`` (Laplace), so the population's mean utility at any
``x`` has mean ``k_m(x, Z) L_Z^{-T} a*`` (:class:`~torchpref.population.model.Population`).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Protocol

import torch
from torch import Tensor

from torchpref.inference.laplace import LaplaceConvergenceWarning
from torchpref.inference.numerics import NotPSDError, default_tolerance
from torchpref.inference.step_rule import STEP_RULE
from torchpref.population.hosts import Host, sum_or_none, summaries
from torchpref.population.shards import (
    Basis,
    ShardData,
    report,
    schur_of,
    shard_cotangent,
    shard_fisher,
    shard_gradient,
    shard_rest,
    shard_retry,
    shard_start,
    shard_step,
)


@dataclass(frozen=True)
class JointPoint:
    """An iterate of all shards: ``a`` (``M``), the shards' states (``handles``, where they live),
    ``psi``, its gradient ``ga`` in ``a``, whether every person's block is positive definite
    (``pd``), the summed couplings, ``sum_p log|H_p|``, whether the weights are Fisher's for
    everyone, ``dec`` (the shards' ``g_b^T db`` of the step that led here), and the Schur
    complement's factor ``S_chol`` once formed (:meth:`JointProblem.hessian`)."""

    a: Tensor
    handles: tuple[object, ...]
    psi: Tensor
    ga: Tensor
    pd: bool
    coupled: Tensor | None
    logdet_people: Tensor | None
    fisher: bool
    dec: Tensor
    S_chol: Tensor | None = None

    def logdet(self) -> Tensor:
        """``log|H| = sum_p log|H_p| + log|S|``."""
        if self.S_chol is None or self.logdet_people is None:
            raise NotPSDError("the population's Hessian is not factorised (or not positive definite) at this point")
        return self.logdet_people + 2 * torch.diagonal(self.S_chol).log().sum()


@dataclass(frozen=True)
class Mode:
    """The joint mode (``point``), the Hessian used there (``hessian``: the same point factorised,
    or it with Fisher weights where the exact Hessian is not positive definite), Newton's
    iterations and whether it converged."""

    point: JointPoint
    hessian: JointPoint
    iterations: int
    converged: bool

    def evidence(self) -> Tensor:
        """The Laplace evidence ``log p(Y | f) - |a|^2 / 2 - |b|^2 / 2 - log|H| / 2``."""
        return self.point.psi - 0.5 * self.hessian.logdet()


class JointProblem(Protocol):
    """What Newton's loop asks of the problem: a point's Hessian factorised (Fisher weights where
    the exact one is not positive definite), a step (the point at the step rule's first length
    along it) and a shorter one."""

    def hessian(self, p: JointPoint) -> JointPoint:
        """The point's Hessian factorised (Fisher weights where the exact one is not positive definite)."""

    def step(self, h: JointPoint, a: Tensor, da: Tensor) -> JointPoint:
        """The point at the step rule's first length along the Newton step ``da`` (and the shards' own)."""

    def retry(self, trial: JointPoint, a: Tensor, t: float) -> JointPoint:
        """The same step at the shorter length ``t``."""


def _at_convergence(problem: JointProblem, p: JointPoint, h: JointPoint, trial: JointPoint, it: int) -> Mode:
    """The end of the last step is the mode to round-off: taken where it is finite and its
    Hessian positive definite, else ``p``."""
    if math.isfinite(float(trial.psi)):
        try:
            return Mode(trial, problem.hessian(trial), it, True)
        except NotPSDError:
            pass
    return Mode(p, h, it, True)


def newton(problem: JointProblem, start: JointPoint, max_iter: int = 100) -> Mode:
    """Newton's method with the library's Armijo backtracking (:data:`STEP_RULE`) for the joint
    mode, from ``start``: the one loop of the population, in process and over shards."""
    p, tol = start, default_tolerance(start.a.dtype)
    first = next(STEP_RULE.lengths())
    for it in range(1, max_iter + 1):
        h = problem.hessian(p)
        assert h.S_chol is not None and h.coupled is not None  # hessian() factorised it
        da = torch.cholesky_solve((p.ga - h.coupled).unsqueeze(-1), h.S_chol).squeeze(-1)
        trial = problem.step(h, p.a + first * da, da)
        dec = float((p.ga * da).sum() + trial.dec)
        if 0.5 * dec < tol:
            return _at_convergence(problem, p, h, trial, it)

        def moved(t: float, p: JointPoint = p, da: Tensor = da, trial: JointPoint = trial) -> JointPoint:
            return trial if t == first else problem.retry(trial, p.a + t * da, t)

        q = STEP_RULE.backtrack(moved, lambda q: float(q.psi), float(p.psi), dec)
        if q is None:
            return Mode(p, h, it, 0.5 * dec < STEP_RULE.stuck_tol)
        p = q
    warnings.warn(
        f"Newton's method for the population's joint mode did not converge in {max_iter} iterations",
        LaplaceConvergenceWarning,
        stacklevel=2,
    )
    return Mode(p, problem.hessian(p), max_iter, False)


def _add(parts: Sequence[Tensor]) -> Tensor:
    """The sum of the shards' ``parts`` (at least one)."""
    out = parts[0]
    for p in parts[1:]:
        out = out + p
    return out


def _factor(S: Tensor | None, a: Tensor) -> Tensor | None:
    """The Cholesky factor of ``I + S`` (symmetrised), ``None`` where it is not positive definite."""
    if S is None:
        return None
    S = 0.5 * (S + S.mT) + torch.eye(a.shape[0], dtype=a.dtype, device=a.device)
    S_chol, info = torch.linalg.cholesky_ex(S)
    return None if bool(info > 0) else S_chol


@dataclass(frozen=True)
class Gradient:
    """The evidence's gradient, summed over the shards: in ``L_Z`` (``M x M``, chained through
    ``k_m`` by the master) and in ``k_m``'s and ``k_g``'s free parameters."""

    L_Z: Tensor
    k_m: tuple[Tensor, ...]
    k_g: tuple[Tensor, ...]


class Shards:
    """The population's joint problem over shards of people on a :class:`Host` (a
    :class:`JointProblem`); between evaluations each shard rests where the last mode left it."""

    def __init__(self, host: Host, data: Sequence[ShardData]):
        self.host = host
        self.handles: list[object] = host.place(data)

    def start(self, basis: Basis, a: Tensor) -> JointPoint:
        """All shards at new hyperparameters and ``a``, each from where it last rested."""
        return self._joint(a, self.host.map(shard_start, self.handles, basis, a), False)

    def keep(self, mode: Mode) -> None:
        """Rest the shards at this mode (their blocks freed) for the next evaluation's start."""
        self.handles = self.host.map(shard_rest, mode.point.handles)

    def hessian(self, p: JointPoint) -> JointPoint:
        """The point's Hessian factorised over the shards (Fisher weights where needed)."""
        if p.S_chol is not None:
            return p
        S_chol = self._schur(p) if p.pd else None
        if S_chol is not None:
            return replace(p, S_chol=S_chol)
        if p.fisher:
            raise NotPSDError("the population's Fisher-scoring Hessian is not positive definite")
        return self.hessian(self._joint(p.a, self.host.map(shard_fisher, p.handles), True))

    def step(self, h: JointPoint, a: Tensor, da: Tensor) -> JointPoint:
        """The point at the step rule's first length along the Newton step, over the shards."""
        return self._joint(a, self.host.map(shard_step, h.handles, a, da), False)

    def retry(self, trial: JointPoint, a: Tensor, t: float) -> JointPoint:
        """The same step at the shorter length ``t``, over the shards."""
        return self._joint(a, self.host.map(shard_retry, trial.handles, a, t), False)

    def _schur(self, p: JointPoint) -> Tensor | None:
        """The factor of ``S = I + sum_s S_s`` (the shards' parts summed as they arrive), or
        ``None`` where it is not positive definite."""
        return _factor(self.host.total(schur_of, p.handles), p.a)

    def _joint(self, a: Tensor, handles: list[object], fisher: bool) -> JointPoint:
        """The point of the shards' states ``handles``: their summaries summed; where the shards
        are remote, with the Schur complement's parts in the same round (:func:`report`)."""
        S_chol = None
        if self.host.remote:
            pairs = self.host.gather(report, handles)
            parts = [pair[0] for pair in pairs]
            S_chol = _factor(sum_or_none([pair[1] for pair in pairs]), a)
        else:
            parts = summaries(self.host, handles)
        psi = _add([s.psi for s in parts]) - 0.5 * (a * a).sum()
        ga = _add([s.ga for s in parts]) - a
        dec = _add([s.dec for s in parts])
        if not all(s.pd for s in parts):
            return JointPoint(a, tuple(handles), psi, ga, False, None, None, fisher, dec)
        coupled, logdet = _add([s.coupled for s in parts]), _add([s.logdet for s in parts])
        return JointPoint(a, tuple(handles), psi, ga, True, coupled, logdet, fisher, dec, S_chol)

    def gradient(self, mode: Mode) -> Gradient:
        """The evidence's gradient at ``mode`` (:mod:`torchpref.population.shards`): two rounds,
        ``h`` and its coupling, then each shard's partial derivatives given ``w_a``."""
        h = mode.hessian
        assert h.S_chol is not None  # a mode's Hessian is positive definite
        states = self.host.map(shard_cotangent, h.handles, h.S_chol)
        cot = summaries(self.host, states)
        rhs = _add([c.ha for c in cot]) - _add([c.coupled for c in cot])
        w_a = torch.cholesky_solve(rhs.unsqueeze(-1), h.S_chol).squeeze(-1)
        parts = self.host.gather(shard_gradient, states, w_a, h.S_chol)
        return Gradient(
            _add([g.L_Z for g in parts]),
            tuple(_add(list(gs)) for gs in zip(*(g.k_m for g in parts))),
            tuple(_add(list(gs)) for gs in zip(*(g.k_g for g in parts))),
        )
