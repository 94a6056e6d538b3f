r"""The items at which a population's mean utility is represented: all the people's distinct items
(the exact fit), or ``M`` inducing items chosen from them.

* ``"kmeans"`` (default): Lloyd's k-means on the items in the unit cube (k-means++ start, seeded),
  each cluster represented by its item nearest its centre: items where the people's items are
  dense, independent of the kernel.
* ``"variance"``: greedy posterior variance (a pivoted Cholesky factorisation of ``k_m`` at the
  items): each next item is the one ``k_m`` predicts worst from those already chosen, at the
  kernel's hyperparameters before the fit.

Either way the inducing items are people's items (rows of ``U``), so with ``M = N`` the
representation is the exact one.
"""

from __future__ import annotations

import torch
from gpytorch.kernels import Kernel
from torch import Tensor

from torchpref.population.prior import _dense

METHODS = ("kmeans", "variance")
#: Rows of items whose distances to the centres are formed at once (memory ``CHUNK x M``).
CHUNK = 8192


def _nearest(A: Tensor, B: Tensor) -> Tensor:
    """For each row of ``A``, the index of its nearest row of ``B`` (in chunks)."""
    return torch.cat([torch.cdist(A[i : i + CHUNK], B).argmin(-1) for i in range(0, A.shape[0], CHUNK)])


def _kmeans_pp(U: Tensor, M: int, g: torch.Generator) -> Tensor:
    """k-means++'s seeding: each next centre an item drawn with probability ``D(x)^2``."""
    picks = [int(torch.randint(U.shape[0], (1,), generator=g))]
    d2 = ((U - U[picks[0]]) ** 2).sum(-1)
    for _ in range(M - 1):
        total = d2.sum()
        i = int(torch.multinomial(d2 / total, 1, generator=g)) if total > 0 else int(d2.argmax())
        picks.append(i)
        d2 = torch.minimum(d2, ((U - U[i]) ** 2).sum(-1))
    return U[torch.tensor(picks)]


def _fill(U: Tensor, chosen: list[int], M: int) -> list[int]:
    """``chosen`` completed to ``M`` items by the items farthest from those chosen."""
    taken = torch.zeros(U.shape[0], dtype=torch.bool)
    taken[chosen] = True
    d2 = torch.cdist(U, U[chosen]).min(-1).values if chosen else torch.full((U.shape[0],), float("inf"))
    while len(chosen) < M:
        i = int(torch.where(taken, -1.0, d2).argmax())
        chosen.append(i)
        taken[i] = True
        d2 = torch.minimum(d2, (U - U[i]).norm(dim=-1))
    return chosen


def kmeans_items(U: Tensor, M: int, generator: torch.Generator, iterations: int = 25) -> Tensor:
    """``M`` rows of ``U``: each k-means cluster's item nearest its centre."""
    C = _kmeans_pp(U, M, generator)
    assign = _nearest(U, C)
    for _ in range(iterations):
        counts = torch.bincount(assign, minlength=M).to(U.dtype)
        sums = U.new_zeros(M, U.shape[-1]).index_add(0, assign, U)
        C = torch.where(counts.unsqueeze(-1) > 0, sums / counts.clamp(min=1).unsqueeze(-1), C)
        new = _nearest(U, C)
        if torch.equal(new, assign):
            break
        assign = new
    dist = (U - C[assign]).norm(dim=-1)
    best = torch.full((M,), float("inf"), dtype=U.dtype).scatter_reduce(0, assign, dist, "amin")
    chosen = [int(i) for i in ((dist == best[assign]).nonzero().squeeze(-1))]
    unique: dict[int, int] = {}
    for i in chosen:  # one item per cluster (the first of any exact ties)
        unique.setdefault(int(assign[i]), i)
    return torch.tensor(_fill(U, sorted(unique.values()), M))


def variance_items(U: Tensor, M: int, k_m: Kernel) -> Tensor:
    """``M`` rows of ``U`` by greedy variance: a pivoted Cholesky factorisation of ``k_m(U, U)``."""
    with torch.no_grad():
        residual = _dense(k_m, U, U, diag=True).clone()
        L = U.new_zeros(U.shape[0], M)
        picks: list[int] = []
        for m in range(M):
            i = int(residual.argmax())
            col = _dense(k_m, U, U[i : i + 1]).squeeze(-1) - L[:, :m] @ L[i, :m]
            col = col / residual[i].clamp(min=torch.finfo(U.dtype).tiny).sqrt()
            L[:, m] = col
            residual = residual - col * col
            picks.append(i)
            residual[picks] = -float("inf")
    return torch.tensor(picks)


def choose_items(U: Tensor, M: int, method: str, k_m: Kernel, seed: int = 0) -> Tensor:
    """The rows of ``U`` (``N x d``) at which the mean is represented: ``M`` of them by ``method``
    (:data:`METHODS`); every row, in order, where ``M >= N`` and the method is ``"kmeans"``.

    Raises:
        ValueError: an unknown ``method``.
    """
    if method not in METHODS:
        raise ValueError(f"inducing_method must be one of {list(METHODS)}, got {method!r}.")
    N = U.shape[0]
    if method == "variance":
        return variance_items(U, min(M, N), k_m)
    if M >= N:
        return torch.arange(N)
    return kmeans_items(U, M, torch.Generator().manual_seed(seed))
