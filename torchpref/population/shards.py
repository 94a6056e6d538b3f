r"""A shard of a population's people: its part of the joint Laplace problem, computed where the
shard lives (this process, a pool's worker, a Dask worker), and what it sends back.

The population mean is represented at ``M`` items ``Z`` (every distinct item for the exact fit,
inducing items otherwise, :mod:`torchpref.population.inducing`): ``m(Z) = L_Z a`` with
``a ~ N(0, I)`` and ``L_Z = chol(k_m(Z, Z) + jitter I)``, and at any other item ``x`` the mean
given ``m(Z)``, ``k_m(x, Z) k_m(Z, Z)^{-1} m(Z)``. So ``m`` at a shard's distinct items is
``Phi_s a`` with ``Phi_s = k_m(U_s, Z) L_Z^{-T}`` (the rows of ``L_Z`` itself for the items that
are in ``Z``: with ``Z = U``, the exact hierarchical model). Person ``p`` has
``f_p = (Phi_s a)[idx_p] + L_p b_p`` (:mod:`torchpref.population.blocks`).

A shard's state (:class:`ShardState`) never leaves it; each function below takes one and returns
a new one, and the master reads only its :class:`Summary` (the shard's log-likelihood, its
gradient in ``a``, ``M``, its coupling ``Phi_s^T W L H^{-1} g_b``, ``M``, and ``sum_p log|H_p|``)
and, for the point a step is taken from, its part of the Schur complement
``S = I + sum_s Phi_s^T W~_s Phi_s`` (``M x M``, :func:`schur_of`): ``O(M^2)`` numbers per Newton
step, whatever the number of people or items in it. The shard's own
``b`` and its Newton step ``db`` stay with it. Work per step: ``P_s n^3`` for the people's
blocks plus ``P_s n M^2`` (or ``N_s^2 M`` where many people share few items) for its part of
``S``.

The evidence's gradient in the hyperparameters is the partial derivative, at the fixed mode
``z = (a, b)`` and ``w = H^{-1} h`` (``h`` the gradient of ``-log|H| / 2`` in ``z``), of
``T = Psi + w^T grad Psi - log|H| / 2`` (the implicit-function theorem), with ``log|S|``
linearised as ``tr(S^{-1} S_s)`` at the mode's ``S``: a sum of per-shard terms, so each shard
differentiates its own (in ``L_Z``, ``k_m``'s and ``k_g``'s parameters) and the master chains
``L_Z`` through ``k_m``. No autograd graph crosses a process.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from gpytorch.kernels import Kernel
from torch import Tensor

from torchpref.inference.numerics import NotPSDError, batched_cholesky
from torchpref.inference.step_rule import STEP_RULE
from torchpref.population.blocks import (
    Blocks,
    KernelFn,
    Layout,
    not_positive_definite,
    person_blocks,
    person_covariance,
    scatter_blocks,
    scatter_vector,
)
from torchpref.population.prior import _dense


@dataclass(frozen=True)
class ShardData:
    """A shard's people (:class:`~torchpref.population.blocks.Layout` over its own distinct items),
    each item's column among the mean's items ``Z`` (``z_col``, ``-1`` for an item not in ``Z``),
    and how its part of ``S`` is formed: per person's rows (``by_rows``, ``P_s n M^2``) or through
    an ``N_s x N_s`` scatter (``N_s^2 M``, where many people share few items)."""

    layout: Layout
    z_col: Tensor
    by_rows: bool


@dataclass(frozen=True)
class Basis:
    """What the master sends once per evaluation: the mean's items ``Z`` (``M x d``), their
    factor ``L_Z`` and the two kernels at the current hyperparameters."""

    Z: Tensor
    L_Z: Tensor
    k_m: Kernel
    k_g: Kernel


@dataclass(frozen=True)
class Prior:
    """A shard's prior factors: ``Phi_s`` (``N_s x M``), ``L_P`` (``P_s x n x n``) and its jitters."""

    Phi: Tensor
    L_P: Tensor
    jitter_P: Tensor


@dataclass(frozen=True)
class Summary:
    """What the master needs of a shard at a point: ``psi`` (log-likelihood less ``|b|^2 / 2``),
    ``ga`` (``Phi_s^T`` of its gradient, ``M``), ``pd`` (every person's block positive definite),
    ``coupled`` (``Phi_s^T W L H^{-1} g_b``, ``M``; ``None`` unless ``pd``), ``logdet``
    (``sum_p log|H_p|``) and ``dec`` (``g_b^T db`` of the step that led here). The shard's part of
    the Schur complement (``M x M``) is formed only when asked (:func:`schur_of`)."""

    psi: Tensor
    ga: Tensor
    pd: bool
    coupled: Tensor | None
    logdet: Tensor | None
    dec: Tensor


@dataclass(frozen=True)
class ShardState:
    """A shard at a point ``(a, b)``: its data and factors, the likelihood's gradient ``r`` and
    ``g_b``, the people's Hessian blocks (exact weights, or Fisher's for the people in ``fisher``,
    ``P_s``, where their exact block is not positive definite), the step it was moved along
    (``step``: the ``b`` it left and ``db``) and its :class:`Summary`."""

    data: ShardData
    basis: Basis
    prior: Prior
    a: Tensor
    b: Tensor
    fisher: Tensor | None
    r: Tensor
    gb: Tensor
    blocks: Blocks | None
    summary: Summary
    step: tuple[Tensor, Tensor] | None = None


@dataclass(frozen=True)
class Cotangent:
    """A shard's part of ``h`` (the gradient of ``-log|H| / 2``): in ``a`` (``M``), and the
    coupling of its part in ``b`` (``M``); the ``b`` part stays with the shard."""

    ha: Tensor
    coupled: Tensor


@dataclass(frozen=True)
class CotangentState:
    """A shard at the mode with its part of ``h`` in ``b`` (``hb``)."""

    state: ShardState
    hb: Tensor
    summary: Cotangent


@dataclass(frozen=True)
class ShardGradient:
    """A shard's ``T`` and its gradient in ``L_Z`` (``M x M``) and in ``k_m``'s and ``k_g``'s
    free parameters (in ``parameters()`` order)."""

    T: Tensor
    L_Z: Tensor
    k_m: tuple[Tensor, ...]
    k_g: tuple[Tensor, ...]


@dataclass(frozen=True)
class Resting:
    """What a shard keeps between evaluations: its data, its people's ``L_P`` and ``b`` (their
    deviations at their items, the next evaluation's start)."""

    data: ShardData
    L_P: Tensor
    b: Tensor


def summary_of(state: ShardState | CotangentState) -> Summary | Cotangent:
    """A state's summary (run where the state lives, so that only the summary travels)."""
    return state.summary


def schur_of(state: ShardState) -> Tensor | None:
    """The shard's part of the Schur complement, ``Phi_s^T (sum_p S_p^T W~_p S_p) Phi_s``
    (``M x M``; ``None`` where a person's block is not positive definite), formed where the
    shard lives when the master asks: a trial point the step rule rejects never forms it."""
    with torch.no_grad():
        return None if state.blocks is None else _schur_part(state.data, state.prior.Phi, state.blocks.Wt)


def report(state: ShardState) -> tuple[Summary, Tensor | None]:
    """The summary and the part of the Schur complement together: one round trip per Newton step
    where the shards are remote (a rejected trial's part is formed for nothing)."""
    return state.summary, schur_of(state)


def shard_rest(state: ShardState) -> Resting:
    """The state reduced to what the next evaluation starts from (its blocks and factors freed)."""
    return Resting(state.data, state.prior.L_P, state.b)


def _kg(k_g: Kernel) -> KernelFn:
    return lambda A, B: _dense(k_g, A, B)


def _free(k: Kernel) -> list[Tensor]:
    return [p for p in k.parameters() if p.requires_grad]


def mean_rows(data: ShardData, Z: Tensor, L_Z: Tensor, k_m: Kernel) -> Tensor:
    """``Phi_s = k_m(U_s, Z) L_Z^{-T}`` (``N_s x M``); an item of ``Z`` gets its row of ``L_Z``
    (what ``(k_m(Z, Z) + jitter I) L_Z^{-T}`` is), so that ``Z = U`` is the exact model."""
    z = data.z_col
    inside = z >= 0
    if bool(inside.all()):
        return L_Z[z]
    out = (~inside).nonzero().squeeze(-1)
    K = _dense(k_m, data.layout.U[out], Z)
    solved = torch.linalg.solve_triangular(L_Z, K.mT, upper=False).mT
    Phi = L_Z.new_zeros(z.shape[0], L_Z.shape[-1]).index_copy(0, out, solved)
    rows = inside.nonzero().squeeze(-1)
    return Phi.index_copy(0, rows, L_Z[z[rows]]) if rows.numel() else Phi


def _utilities(lay: Layout, Phi: Tensor, L_P: Tensor, a: Tensor, b: Tensor) -> Tensor:
    return (Phi @ a)[lay.index] + (L_P @ b.unsqueeze(-1)).squeeze(-1)


def _schur_part(data: ShardData, Phi: Tensor, Wt: Tensor) -> Tensor:
    """``Phi_s^T (sum_p S_p^T W~_p S_p) Phi_s`` (``M x M``)."""
    lay, M = data.layout, Phi.shape[-1]
    if data.by_rows:
        rows = Phi[lay.index]  # P x n x M
        return rows.reshape(-1, M).mT @ (Wt @ rows).reshape(-1, M)
    return Phi.mT @ (scatter_blocks(lay, Wt, Phi.shape[0]) @ Phi)


def _trace_q(data: ShardData, V: Tensor, Wt: Tensor) -> Tensor:
    """``tr(S^{-1} Phi_s^T W~ Phi_s)`` given ``V = Phi_s S_chol^{-T}``."""
    lay = data.layout
    if data.by_rows:
        rows = V[lay.index]
        return (rows * (Wt @ rows)).sum()
    Q = V @ V.mT
    return (Q[lay.index.unsqueeze(-1), lay.index.unsqueeze(-2)] * Wt).sum()


def _coupled(data: ShardData, prior: Prior, blocks: Blocks, g: Tensor) -> Tensor:
    """``Phi_s^T sum_p S_p^T W_p L_p H_p^{-1} g_p`` (``M``)."""
    t = torch.cholesky_solve(g.unsqueeze(-1), blocks.C)
    c = (blocks.W @ (prior.L_P @ t)).squeeze(-1)
    return prior.Phi.mT @ scatter_vector(data.layout, c, prior.Phi.shape[0])


def _blocks(
    lay: Layout, L_P: Tensor, f: Tensor, weights: tuple[Tensor, ...], fisher: Tensor | None
) -> tuple[Blocks | None, Tensor | None]:
    """The people's blocks, with Fisher weights for those whose exact block is not positive
    definite (``(None, fisher)`` if even those are not)."""
    try:
        return person_blocks(lay, L_P, weights), fisher
    except NotPSDError:
        fisher = not_positive_definite(lay, L_P, weights) | (False if fisher is None else fisher)
    try:
        return person_blocks(lay, L_P, lay.obs.evaluate(f, fisher).weights), fisher
    except NotPSDError:
        return None, fisher


def _point(
    data: ShardData,
    basis: Basis,
    prior: Prior,
    a: Tensor,
    b: Tensor,
    fisher: Tensor | None = None,
    step: tuple[Tensor, Tensor] | None = None,
    dec: Tensor | None = None,
) -> ShardState:
    """The shard at ``(a, b)`` (no autograd), Fisher weights for the people in ``fisher`` and
    for any whose exact block is not positive definite."""
    lay, Phi = data.layout, prior.Phi
    f = _utilities(lay, Phi, prior.L_P, a, b)
    ll, r, weights = lay.obs.evaluate(f, fisher)
    psi = ll.sum() - 0.5 * (b * b).sum()
    ga = Phi.mT @ scatter_vector(lay, r, Phi.shape[0])
    gb = (prior.L_P.mT @ r.unsqueeze(-1)).squeeze(-1) - b
    dec = ga.new_zeros(()) if dec is None else dec
    blocks, fisher = _blocks(lay, prior.L_P, f, weights, fisher)
    if blocks is None:
        summary = Summary(psi, ga, False, None, None, dec)
    else:
        summary = Summary(psi, ga, True, _coupled(data, prior, blocks, gb), blocks.logdet(), dec)
    return ShardState(data, basis, prior, a, b, fisher, r, gb, blocks, summary, step)


def prior_factors(data: ShardData, basis: Basis) -> Prior:
    """The shard's ``Phi_s`` and its people's ``L_P`` at the basis' hyperparameters."""
    L_P, jitter = batched_cholesky(person_covariance(data.layout, _kg(basis.k_g)), "a person's k_g")
    return Prior(mean_rows(data, basis.Z, basis.L_Z, basis.k_m), L_P, jitter)


def shard_start(source: ShardData | Resting, basis: Basis, a: Tensor) -> ShardState:
    """The shard at new hyperparameters (``basis``) and ``a``: each person's deviation at their
    items where ``source`` (a :class:`Resting` shard) left it (``b = L_p^{-1} g_p`` with the new
    ``L_p``), zero for a fresh shard."""
    with torch.no_grad():
        if isinstance(source, ShardData):
            prior = prior_factors(source, basis)
            return _point(source, basis, prior, a, prior.L_P.new_zeros(source.layout.index.shape))
        prior = prior_factors(source.data, basis)
        g = source.L_P @ source.b.unsqueeze(-1)
        b = torch.linalg.solve_triangular(prior.L_P, g, upper=False).squeeze(-1)
        return _point(source.data, basis, prior, a, b)


def shard_fisher(state: ShardState) -> ShardState:
    """The same point with Fisher weights for everyone (where the Schur complement of the exact
    weights is not positive definite)."""
    with torch.no_grad():
        s = state
        everyone = torch.ones(s.b.shape[0], dtype=torch.bool, device=s.b.device)
        return _point(s.data, s.basis, s.prior, s.a, s.b, everyone, s.step, s.summary.dec)


def shard_step(state: ShardState, a: Tensor, da: Tensor) -> ShardState:
    """The shard's part of Newton's step, ``db = H_p^{-1} (g_b - L_p^T W_p Phi_p da)``, from
    ``state``'s blocks, and the point at the step rule's first length (the master's ``a`` there)."""
    with torch.no_grad():
        s, prior = state, state.prior
        if s.blocks is None:
            raise NotPSDError("a shard was asked for a step at blocks that are not positive definite")
        z = (prior.Phi @ da)[s.data.layout.index]
        back = (prior.L_P.mT @ (s.blocks.W @ z.unsqueeze(-1))).squeeze(-1)
        db = torch.cholesky_solve((s.gb - back).unsqueeze(-1), s.blocks.C).squeeze(-1)
        t = next(STEP_RULE.lengths())
        return _point(s.data, s.basis, prior, a, s.b + t * db, None, (s.b, db), (s.gb * db).sum())


def shard_retry(trial: ShardState, a: Tensor, t: float) -> ShardState:
    """The point a shorter length ``t`` along the step that led to ``trial``."""
    with torch.no_grad():
        assert trial.step is not None  # a trial is always the end of a step
        b0, db = trial.step
        return _point(trial.data, trial.basis, trial.prior, a, b0 + t * db, None, trial.step, trial.summary.dec)


def shard_cotangent(state: ShardState, S_chol: Tensor) -> CotangentState:
    """The shard's part of ``h``, the gradient of ``-log|H| / 2`` in ``(a, b)`` at fixed
    hyperparameters (``log|S|`` linearised at ``S_chol``), and the coupling of its ``b`` part."""
    s, lay, prior = state, state.data.layout, state.prior
    if s.blocks is None:
        raise NotPSDError("the population's Hessian at the mode is not positive definite")
    with torch.no_grad():
        V = torch.linalg.solve_triangular(S_chol, prior.Phi.mT, upper=False).mT
    with torch.enable_grad():  # a worker may run this inside the master's no_grad block
        a = s.a.detach().requires_grad_(True)
        b = s.b.detach().requires_grad_(True)
        f = _utilities(lay, prior.Phi, prior.L_P, a, b)
        weights = lay.obs.evaluate(f, s.fisher).weights
        blocks = person_blocks(lay, prior.L_P, weights)
        phi = -0.5 * blocks.logdet() - 0.5 * _trace_q(s.data, V, blocks.Wt)
        grads = torch.autograd.grad(phi, (a, b), allow_unused=True) if phi.requires_grad else (None, None)
    ha = torch.zeros_like(s.a) if grads[0] is None else grads[0]
    hb = torch.zeros_like(s.b) if grads[1] is None else grads[1]
    with torch.no_grad():
        return CotangentState(s, hb, Cotangent(ha, _coupled(s.data, prior, s.blocks, hb)))


def shard_gradient(h: CotangentState, w_a: Tensor, S_chol: Tensor) -> ShardGradient:
    """The shard's ``T`` and its gradient (module docstring), given the master's ``w_a``; the
    shard's own ``w_b = H_p^{-1} (h_b - L_p^T W_p Phi_p w_a)``."""
    s, lay = h.state, h.state.data.layout
    assert s.blocks is not None  # checked by shard_cotangent
    with torch.no_grad():
        z = (s.prior.Phi @ w_a)[lay.index]
        back = (s.prior.L_P.mT @ (s.blocks.W @ z.unsqueeze(-1))).squeeze(-1)
        w_b = torch.cholesky_solve((h.hb - back).unsqueeze(-1), s.blocks.C).squeeze(-1)
    with torch.enable_grad():
        return _traced_gradient(s, w_a, w_b, S_chol)


def _traced_gradient(s: ShardState, w_a: Tensor, w_b: Tensor, S_chol: Tensor) -> ShardGradient:
    lay, basis = s.data.layout, s.basis
    L_Z = basis.L_Z.detach().requires_grad_(True)
    pm, pg = _free(basis.k_m), _free(basis.k_g)
    Phi = mean_rows(s.data, basis.Z, L_Z, basis.k_m)
    K = person_covariance(lay, _kg(basis.k_g))
    eye = torch.eye(K.shape[-1], dtype=K.dtype, device=K.device)
    L_P = torch.linalg.cholesky(K + s.prior.jitter_P.to(K).reshape(-1, 1, 1) * eye)
    f = _utilities(lay, Phi, L_P, s.a, s.b)
    ll, r, weights = lay.obs.evaluate(f, s.fisher)
    blocks = person_blocks(lay, L_P, weights)
    V = torch.linalg.solve_triangular(S_chol, Phi.mT, upper=False).mT
    lin = (_utilities(lay, Phi, L_P, w_a, w_b) * r).sum()
    T = ll.sum() + lin - 0.5 * blocks.logdet() - 0.5 * _trace_q(s.data, V, blocks.Wt)
    inputs = [L_Z, *pm, *pg]
    grads = torch.autograd.grad(T, inputs, allow_unused=True) if T.requires_grad else [None] * len(inputs)
    g = [torch.zeros_like(x) if d is None else d for x, d in zip(inputs, grads)]
    return ShardGradient(T.detach(), g[0], tuple(g[1 : 1 + len(pm)]), tuple(g[1 + len(pm) :]))
