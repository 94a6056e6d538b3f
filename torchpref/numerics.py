r"""Fragile numerics in one place: log-space normal ratios and a guarded Cholesky."""

from __future__ import annotations

import functools
import math
import warnings
from typing import Sequence

import torch
from linear_operator.utils.errors import NotPSDError as _LinearOperatorNotPSDError
from torch import Tensor

LOG_2PI_HALF = 0.5 * math.log(2 * math.pi)

#: The largest absolute diagonal jitter ever added to a kernel matrix (float64).
MAX_JITTER = 1e-6


class NotPSDError(_LinearOperatorNotPSDError):
    """A matrix that must be positive definite is not, even with the largest allowed jitter.

    A subclass of linear_operator's ``NotPSDError`` (itself a ``RuntimeError``), so BoTorch's
    ``fit_gpytorch_mll`` treats it as it treats GPyTorch's own: it retries the fit from
    resampled hyperparameters instead of failing (docs/botorch.md).
    """


class JitterWarning(UserWarning):
    """Diagonal jitter was added to a matrix to make its Cholesky factorisation succeed."""


def log_ndtr(z: Tensor) -> Tensor:
    r"""``log Phi(z)``, accurate in both tails."""
    return torch.special.log_ndtr(z)


def inv_mills(z: Tensor) -> Tensor:
    r"""``phi(z) / Phi(z)``, computed in log space (finite for all finite ``z``)."""
    return torch.exp(-0.5 * z * z - LOG_2PI_HALF - log_ndtr(z))


def normal_pdf(z: Tensor) -> Tensor:
    """The standard normal density ``phi(z)``, elementwise."""
    return torch.exp(-0.5 * z * z - LOG_2PI_HALF)


@functools.lru_cache(maxsize=16)
def _hermgauss(n: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    import numpy as np

    x, w = np.polynomial.hermite.hermgauss(n)
    return tuple(x.tolist()), tuple(w.tolist())


def gauss_hermite(n: int, like: Tensor, expectation: bool = True) -> tuple[Tensor, Tensor]:
    r"""Gauss-Hermite nodes ``x`` and weights ``w`` (``n`` each, ``like``'s dtype and device).

    ``expectation=True``: ``E[g(Z)]``, ``Z ~ N(m, v)``, is ``sum_k w_k g(m + sqrt(2 v) x_k)``
    (the weights sum to 1). ``expectation=False``: the physicists' rule,
    ``int exp(-x^2) g(x) dx ~ sum_k w_k g(x_k)``.
    """
    x, w = _hermgauss(int(n))
    x, w = like.new_tensor(x), like.new_tensor(w)
    return (x, w / math.sqrt(math.pi)) if expectation else (x, w)


def jitter_schedule(max_jitter: float = MAX_JITTER) -> list[float]:
    """The diagonal jitters tried in turn: 0, then ``1e-10`` growing tenfold up to ``max_jitter``."""
    return [0.0] + [10.0**e for e in range(-10, 1 + int(math.floor(math.log10(max_jitter))))]


def cholesky_batch(A: Tensor, jitters: Sequence[float] | Tensor) -> tuple[Tensor, Tensor, Tensor]:
    r"""Cholesky factors of a batch ``T x n x n``, each with the first diagonal jitter of
    ``jitters`` that succeeds; a later jitter is tried only on the matrices still failing.

    Args:
        A: ``T x n x n`` symmetric matrices.
        jitters: ``k`` amounts, or ``k x T``: a schedule per matrix.

    Returns:
        ``(L, jitter, failed)``: the factors (where ``failed``, of the last try), the ``T``
        amounts used and the ``T`` matrices that no jitter made positive definite.
    """
    T = A.shape[0]
    J = torch.as_tensor(jitters, dtype=A.dtype, device=A.device)
    J = J.unsqueeze(-1).expand(-1, T) if J.dim() == 1 else J
    eye = torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)
    L, info = torch.linalg.cholesky_ex(A + J[0].reshape(T, 1, 1) * eye)
    jitter = J[0].clone()
    for j in J[1:]:
        bad = info > 0
        if not bool(bad.any()):
            break
        L_bad, info_bad = torch.linalg.cholesky_ex(A[bad] + j[bad].reshape(-1, 1, 1) * eye)
        L[bad], jitter[bad] = L_bad, j[bad]
        info = info.clone()
        info[bad] = info_bad
    return L, jitter, info > 0


def batched_cholesky(A: Tensor, max_jitter: float = MAX_JITTER, name: str = "matrix") -> tuple[Tensor, Tensor]:
    r"""Cholesky factors of a batch ``T x n x n``, adding diagonal jitter (:func:`jitter_schedule`,
    as :func:`cholesky_jittered`) only to the matrices whose plain factorisation fails.

    Returns:
        ``(L, jitter)`` with ``jitter`` the ``T`` amounts used.

    Raises:
        NotPSDError: naming the matrices still not positive definite at ``max_jitter``.
    """
    L, jitter, failed = cholesky_batch(A, jitter_schedule(max_jitter))
    if bool(failed.any()):
        bad = failed.nonzero().reshape(-1).tolist()
        raise NotPSDError(f"the {name} of trials {bad} is not positive definite even with jitter {max_jitter:g}.")
    return L, jitter


def cholesky_jittered(
    A: Tensor, jitter: float | None = None, max_jitter: float = MAX_JITTER, name: str = "matrix"
) -> tuple[Tensor, float]:
    r"""Cholesky factor of ``A``, adding diagonal jitter only if plain factorisation fails.

    The jitter starts at ``jitter`` (or 0, then ``1e-10``) and grows tenfold up to ``max_jitter``
    (absolute). A :class:`JitterWarning` is issued when jitter above ``1e-8`` was needed.

    Returns:
        ``(L, jitter_used)`` with ``L L^T = A + jitter_used I``.

    Raises:
        NotPSDError: if ``A + max_jitter I`` is still not positive definite, or ``A`` has NaNs.
    """
    tries = ([] if jitter is None else [jitter]) + jitter_schedule(max_jitter)
    eye = None
    for j in tries:
        if j > max_jitter:
            continue
        if j == 0:
            L, info = torch.linalg.cholesky_ex(A)
        else:
            if eye is None:
                eye = torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)
            L, info = torch.linalg.cholesky_ex(A + j * eye)
        if not info.any():
            if j > 1e-8 and (jitter is None or j != jitter):
                warnings.warn(f"added jitter {j:.0e} to the diagonal of the {name}", JitterWarning, stacklevel=3)
            return L, j
    if not torch.isfinite(A).all():  # checked only on failure: it costs a pass over A
        raise NotPSDError(f"{name} has non-finite entries; cannot factorise it.")
    raise NotPSDError(f"{name} is not positive definite even with jitter {max_jitter:.0e} on its diagonal.")


def lower_t_matmul(L: Tensor, X: Tensor, blocks: int = 4, min_size: int = 256) -> Tensor:
    r"""``L^T X`` for a lower-triangular ``L`` (``n x n``), skipping most of its zero blocks.

    Block row ``r`` of the result is ``L[a:, a:b]^T X[a:]`` (the rows of ``L`` above ``a`` are zero
    in those columns), which costs ``(blocks + 1) / (2 blocks)`` of a full product: torch has no
    triangular matrix-matrix product (BLAS ``trmm``). Below ``min_size`` a plain product.
    """
    n = L.shape[-1]
    if n < min_size:
        return L.mT @ X
    out = X.new_empty(n, X.shape[-1])
    edges = [round(n * r / blocks) for r in range(blocks + 1)]
    for a, b in zip(edges[:-1], edges[1:]):
        torch.mm(L[a:, a:b].mT, X[a:], out=out[a:b])
    return out
