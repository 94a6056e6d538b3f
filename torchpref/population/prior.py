r"""A new person's prior from a fitted population, as a GPyTorch mean and kernel.

Given the population's answers ``D``, a new person's utility ``f = m + g`` has the prior
(Laplace) mean ``E[m(x) | D] = k_m(x, U) alpha`` and covariance ``k_g(x, x') + Cov[m(x), m(x') | D]``
with ``Cov[m(x), m(x') | D] = k_m(x, x') - v(x)^T A v(x')``, ``v(x) = L_U^{-1} k_m(U, x)`` and
``A = I - S^{-1}`` (:mod:`torchpref.population.joint`). Far from every population item this is
the hierarchical prior ``GP(0, k_m + k_g)``; where the population answered a lot, the mean is its
utility and only the person's deviation ``k_g`` (plus what is left of ``m``'s uncertainty) remains.

Both modules hold the population's tensors as buffers (so a model's posterior cache and ``.to``
see them) and their kernels' hyperparameters fixed (``requires_grad`` off): fitting a person
model's hyperparameters would make them inconsistent with the population's posterior.
"""

from __future__ import annotations

import copy

import torch
from gpytorch.kernels import Kernel
from gpytorch.means import Mean
from linear_operator.operators import LinearOperator
from torch import Tensor


def _dense(k: Kernel, x1: Tensor, x2: Tensor, diag: bool = False) -> Tensor:
    out = k.forward(x1, x2, diag=diag)
    return out.to_dense() if isinstance(out, LinearOperator) else out


def _frozen(k: Kernel) -> Kernel:
    k = copy.deepcopy(k)
    for p in k.parameters():
        p.requires_grad_(False)
    return k


def _cross(k_m: Kernel, x: Tensor, U: Tensor) -> Tensor:
    """``k_m(U, x)``: ``... x N x q`` for ``x`` ``... x q x d``."""
    Ue = U.to(x).expand(*x.shape[:-2], *U.shape)
    return _dense(k_m, Ue, x)


class PopulationMean(Mean):
    r"""``E[m(x) | D] = k_m(x, U) alpha``: the population's posterior mean utility."""

    def __init__(self, k_m: Kernel, U: Tensor, alpha: Tensor):
        super().__init__()
        self.k_m = _frozen(k_m)
        self.register_buffer("U", U.detach().clone())
        self.register_buffer("alpha", alpha.detach().clone())

    def forward(self, x: Tensor) -> Tensor:
        K = _cross(self.k_m, x, self.U)  # ... x N x q
        return (self.alpha.to(K).unsqueeze(-1) * K).sum(-2)


class PopulationCovariance(Kernel):
    r"""``k_g(x, x') + k_m(x, x') - v(x)^T A v(x')``: a new person's prior covariance (the
    person's deviation plus the population mean's remaining uncertainty)."""

    def __init__(self, k_m: Kernel, k_g: Kernel, U: Tensor, L_U: Tensor, A: Tensor):
        super().__init__()
        self.k_m, self.k_g = _frozen(k_m), _frozen(k_g)
        self.register_buffer("U", U.detach().clone())
        self.register_buffer("L_U", L_U.detach().clone())
        self.register_buffer("A", A.detach().clone())

    def _v(self, x: Tensor) -> Tensor:
        return torch.linalg.solve_triangular(self.L_U.to(x), _cross(self.k_m, x, self.U), upper=False)

    def forward(self, x1: Tensor, x2: Tensor, diag: bool = False, last_dim_is_batch: bool = False, **params) -> Tensor:
        if last_dim_is_batch:
            raise NotImplementedError("PopulationCovariance does not take last_dim_is_batch.")
        prior = _dense(self.k_g, x1, x2, diag) + _dense(self.k_m, x1, x2, diag)
        v1 = self._v(x1)
        A = self.A.to(v1)
        if diag:
            return prior - (v1 * (A @ v1)).sum(-2)
        v2 = v1 if (x2 is x1 or torch.equal(x1, x2)) else self._v(x2)
        return prior - v1.mT @ (A @ v2)
