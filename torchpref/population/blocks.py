r"""The people's side of a population's joint Laplace problem: their data laid out in padded
blocks, and each person's blocks of the arrow Hessian.

Person ``p``'s utility at their items is ``f_p = Phi_p a + L_p b_p`` in whitened coordinates:
``Phi_p`` (``n x M``) the population mean at their items (:mod:`torchpref.population.shards`),
``L_p = chol(k_g(X_p, X_p) + jitter I)`` their deviation's prior factor. The negative Hessian of
the log posterior in ``(a, b)`` is an arrow: per-person blocks ``H_p = I + L_p^T W_p L_p``, and
the ``M x M`` block of ``a`` coupling them through
``W~_p = W_p - W_p L_p H_p^{-1} L_p^T W_p`` (``= (W_p^{-1} + K_p)^{-1}``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from torchpref.inference.numerics import NotPSDError
from torchpref.inference.observations import Observations

#: ``kernel(X1, X2)``: a dense prior covariance.
KernelFn = Callable[[Tensor, Tensor], Tensor]


@dataclass(frozen=True)
class Layout:
    """People's data: their distinct items ``U`` (``N x d``), their items padded to ``n``
    (``X``: ``P x n x d``), each item's row of ``U`` (``index``: ``P x n``, 0 for padding), which
    items are real (``item_mask``, ``P x n``) and the observations of the ``P`` problems."""

    U: Tensor
    X: Tensor
    index: Tensor
    item_mask: Tensor
    obs: Observations

    @property
    def num_items(self) -> int:
        """``n``, the padded number of items per person."""
        return self.X.shape[-2]


@dataclass(frozen=True)
class Blocks:
    """Per person ``C = chol(I + L_p^T W_p L_p)``, ``W_p`` (dense, ``P x n x n``) and ``W~_p``."""

    C: Tensor
    W: Tensor
    Wt: Tensor

    def logdet(self) -> Tensor:
        """``sum_p log|H_p|``."""
        return 2 * torch.diagonal(self.C, dim1=-2, dim2=-1).log().sum()


def person_covariance(layout: Layout, k_g: KernelFn) -> Tensor:
    """Each person's ``k_g(X_p, X_p)``, padded items independent with unit variance."""
    K = k_g(layout.X, layout.X)
    m = layout.item_mask
    K = torch.where(m.unsqueeze(-1) & m.unsqueeze(-2), K, 0.0)
    return K + torch.diag_embed((~m).to(K))


def not_positive_definite(layout: Layout, L_P: Tensor, weights: tuple[Tensor, ...]) -> Tensor:
    """Which people's blocks ``I + L_p^T W_p L_p`` are not positive definite at ``weights`` (``P``)."""
    n = layout.num_items
    W = layout.obs.W_dense(n, weights, like=L_P)
    Hp = L_P.mT @ W @ L_P + torch.eye(n, dtype=L_P.dtype, device=L_P.device)
    return torch.linalg.cholesky_ex(Hp).info > 0


def person_blocks(layout: Layout, L_P: Tensor, weights: tuple[Tensor, ...]) -> Blocks:
    """The people's blocks of the Hessian at the likelihood ``weights`` (differentiable).

    Raises:
        NotPSDError: a person's block is not positive definite.
    """
    n = layout.num_items
    W = layout.obs.W_dense(n, weights, like=L_P)
    Hp = L_P.mT @ W @ L_P + torch.eye(n, dtype=L_P.dtype, device=L_P.device)
    C, info = torch.linalg.cholesky_ex(Hp)
    if bool((info > 0).any()):
        raise NotPSDError("a person's block I + L_p^T W_p L_p is not positive definite")
    V = torch.linalg.solve_triangular(C, L_P.mT @ W, upper=False)  # C^-1 L_p^T W_p
    return Blocks(C, W, W - V.mT @ V)


def scatter_vector(layout: Layout, r: Tensor, N: int) -> Tensor:
    """``sum_p S_p^T r_p`` (``N``) for per-person values ``r`` (``P x n``, zero on padding)."""
    return r.new_zeros(N).index_add(0, layout.index.reshape(-1), r.reshape(-1))


def scatter_blocks(layout: Layout, Wt: Tensor, N: int) -> Tensor:
    """``sum_p S_p^T W~_p S_p`` (``N x N``)."""
    flat = (layout.index.unsqueeze(-1) * N + layout.index.unsqueeze(-2)).reshape(-1)
    return Wt.new_zeros(N * N).index_add(0, flat, Wt.reshape(-1)).reshape(N, N)
