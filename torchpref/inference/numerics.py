r"""Fragile numerics in one place: log-space normal ratios and a guarded Cholesky."""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Sequence

import torch
from linear_operator.utils.errors import NotPSDError as _LinearOperatorNotPSDError
from torch import Tensor

LOG_2PI_HALF = 0.5 * math.log(2 * math.pi)

#: Diagonal jitter relative to the matrix's mean diagonal, per dtype: ``(first, largest)``.
#: float64 tries ``1e-10`` up to ``1e-6``; float32 starts where linear_operator's
#: ``psd_safe_cholesky`` does (``1e-6``, about eight float32 epsilons) and goes one tenfold step
#: beyond its largest (``1e-4``), since a kernel matrix of 1,000 items accumulates ``n eps`` of
#: round-off in its factorisation.
RELATIVE_JITTER = {torch.float64: (1e-10, 1e-6), torch.float32: (1e-6, 1e-3)}


class NotPSDError(_LinearOperatorNotPSDError):
    """A matrix that must be positive definite is not, even with the largest allowed jitter.

    A subclass of linear_operator's ``NotPSDError`` (itself a ``RuntimeError``), so BoTorch's
    ``fit_gpytorch_mll`` treats it as it treats GPyTorch's own: it retries the fit from
    resampled hyperparameters instead of failing (docs/botorch.md).
    """


class LaplaceNumericalError(NotPSDError, FloatingPointError):
    """The Laplace solve met numbers it cannot go on from: a non-finite Newton step, a
    factorisation that failed, a non-finite evidence at the hyperparameters asked for.

    A :class:`NotPSDError` (so BoTorch's ``fit_gpytorch_mll`` retries the fit from resampled
    hyperparameters, as for GPyTorch's own numerical failures) and a ``FloatingPointError``
    (what the Newton solver raised before it had a name of its own).
    """


class JitterWarning(UserWarning):
    """Diagonal jitter was added to a matrix to make its Cholesky factorisation succeed."""


def default_tolerance(dtype: torch.dtype) -> float:
    r"""Newton's stopping tolerance for the Laplace mode in ``dtype``: ``1e-11`` (log-posterior
    units) in float64; ten epsilons of ``dtype`` where that is coarser (``1.2e-6`` in float32,
    whose round-off keeps the Newton decrement near ``1e-8`` at ``n`` = 1,500, so that
    ``1e-11`` is never reached)."""
    return max(1e-11, 10 * torch.finfo(dtype).eps)


#: Newton's decrement is at round-off once below this many epsilons of the log posterior's scale
#: (:func:`roundoff_floor`); the stalled float32 solves of the fuzz (docs/precision.md) stopped at
#: up to about 20.
ROUNDOFF_EPS = 100.0


def roundoff_floor(log_lik: Tensor, prior_term: Tensor) -> Tensor:
    r"""The smallest half Newton decrement (log-posterior units) that ``log_lik``'s dtype can
    resolve: ``ROUNDOFF_EPS eps (|log p(Y|f)| + a^T a / 2)`` per problem (``b`` each).

    ``Psi = log p - a^T a / 2`` is a sum of terms much larger than itself (a Beta log density
    holds ``lgamma(nu)``), so its round-off, and that of its gradient, grows with the size of
    its parts, not with ``Psi``: a float32 solve of a log posterior of ``1e4`` cannot see a
    change of ``1e-6``. In float64 the floor is below the default tolerance (``1e-11``) until the
    parts reach about ``450``, and is only used once the decrement has stopped contracting
    (:func:`torchpref.inference.newton.newton_mode`).
    """
    return ROUNDOFF_EPS * torch.finfo(log_lik.dtype).eps * (log_lik.abs() + prior_term)


def log_ndtr(z: Tensor) -> Tensor:
    r"""``log Phi(z)``, accurate in both tails."""
    return torch.special.log_ndtr(z)


def inv_mills(z: Tensor, log_cdf: Tensor | None = None) -> Tensor:
    r"""``phi(z) / Phi(z)``, computed in log space (finite for all finite ``z``); ``log_cdf``:
    ``log Phi(z)`` if already computed."""
    return torch.exp(-0.5 * z * z - LOG_2PI_HALF - (log_ndtr(z) if log_cdf is None else log_cdf))


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
    nodes, weights = _hermgauss(int(n))
    x, w = like.new_tensor(nodes), like.new_tensor(weights)
    return (x, w / math.sqrt(math.pi)) if expectation else (x, w)


def relative_jitter(dtype: torch.dtype) -> tuple[float, float]:
    """``(first, largest)`` diagonal jitter for ``dtype``, relative to the diagonal's scale
    (:data:`RELATIVE_JITTER`; other dtypes start at eight of their epsilons)."""
    if dtype in RELATIVE_JITTER:
        return RELATIVE_JITTER[dtype]
    first = 10.0 ** math.ceil(math.log10(8 * torch.finfo(dtype).eps))
    return first, min(1e3 * first, 1e-1)


def diagonal_scale(A: Tensor) -> Tensor:
    """The mean of the diagonal of ``A`` (``... x n x n`` -> ``...``), or 1 where that is not a
    positive finite number: the scale that jitter is relative to (the outputscale of a
    stationary kernel)."""
    s = A.diagonal(dim1=-2, dim2=-1).mean(-1)
    return torch.where(torch.isfinite(s) & (s > 0), s, torch.ones_like(s))


def jitter_schedule(dtype: torch.dtype = torch.float64, scale: float = 1.0) -> list[float]:
    """The diagonal jitters tried in turn: 0, then :func:`relative_jitter`'s first amount growing
    tenfold up to its largest (as ``psd_safe_cholesky`` escalates), each times ``scale``."""
    first, largest = (round(math.log10(v)) for v in relative_jitter(dtype))
    return [0.0] + [scale * 10.0**e for e in range(first, largest + 1)]


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


def batched_cholesky(A: Tensor, name: str = "matrix") -> tuple[Tensor, Tensor]:
    r"""Cholesky factors of a batch ``T x n x n``, adding diagonal jitter (:func:`jitter_schedule`,
    relative to each matrix's :func:`diagonal_scale`, as :func:`cholesky_jittered`) only to the
    matrices whose plain factorisation fails.

    Returns:
        ``(L, jitter)`` with ``jitter`` the ``T`` amounts used.

    Raises:
        NotPSDError: naming the matrices still not positive definite at the largest jitter.
    """
    rel = torch.tensor(jitter_schedule(A.dtype), dtype=A.dtype, device=A.device)
    L, jitter, failed = cholesky_batch(A, rel.unsqueeze(-1) * diagonal_scale(A).unsqueeze(0))
    if bool(failed.any()):
        bad = failed.nonzero().reshape(-1).tolist()
        raise NotPSDError(
            f"the {name} of trials {bad} is not positive definite even with jitter "
            f"{relative_jitter(A.dtype)[1]:g} times its mean diagonal."
        )
    return L, jitter


def cholesky_jittered(A: Tensor, jitter: float | None = None, name: str = "matrix") -> tuple[Tensor, float]:
    r"""Cholesky factor of ``A``, adding diagonal jitter only if plain factorisation fails.

    The jitter tried first is ``jitter`` (e.g. the amount an earlier factorisation of a similar
    matrix needed), then :func:`jitter_schedule`: 0, then growing tenfold from the first to the
    largest amount of :func:`relative_jitter` for ``A``'s dtype, times ``A``'s
    :func:`diagonal_scale`. A :class:`JitterWarning` is issued when more than a hundred times the
    first amount was needed.

    Returns:
        ``(L, jitter_used)`` with ``L L^T = A + jitter_used I``.

    Raises:
        NotPSDError: if ``A`` plus the largest jitter is still not positive definite, or ``A``
        has non-finite entries.
    """
    scale = float(diagonal_scale(A))
    first, largest = relative_jitter(A.dtype)
    tries = ([] if jitter is None else [jitter]) + jitter_schedule(A.dtype, scale)
    eye = None
    for j in tries:
        if j > largest * scale:
            continue
        if j == 0:
            L, info = torch.linalg.cholesky_ex(A)
        else:
            if eye is None:
                eye = torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)
            L, info = torch.linalg.cholesky_ex(A + j * eye)
        if not info.any():
            if j > 100 * first * scale and (jitter is None or j != jitter):
                warnings.warn(
                    f"added jitter {j:.1e} ({j / scale:.0e} of its mean diagonal) to the diagonal of the {name}",
                    JitterWarning,
                    stacklevel=3,
                )
            return L, j
    if not torch.isfinite(A).all():  # checked only on failure: it costs a pass over A
        raise NotPSDError(f"{name} has non-finite entries; cannot factorise it.")
    raise NotPSDError(
        f"{name} ({A.dtype}, n = {A.shape[-1]}) is not positive definite even with jitter "
        f"{largest * scale:.1e} ({largest:.0e} of its mean diagonal {scale:.3g}) on its diagonal."
    )


def pin_coincident(K: Tensor, X1: Tensor, X2: Tensor, k_same: Tensor) -> Tensor:
    r"""``K`` with its entries at coincident points (``X1[i] == X2[j]``) set to ``k(x, x)``.

    GPyTorch computes squared distances as ``|x|^2 - 2 x^T y + |y|^2`` and zeroes those of a
    point with itself only when no input requires a gradient, so with autograd on (inside
    ``optimize_acqf``, or through a lengthscale being fitted) ``k(x, x)`` comes back off by
    round-off, about ``1e-4`` relative in float32 at a lengthscale of 0.01; the kernel's
    ``diag=True`` path (``x - x = 0``) is exact. The result stays differentiable.

    Args:
        K: ``... x n x m`` kernel matrix ``k(X1, X2)``.
        X1: ``... x n x d`` points.
        X2: ``... x m x d`` points.
        k_same: ``... x n`` values ``k(X1[i], X1[i])``.
    """
    same = (X1.unsqueeze(-2) == X2.unsqueeze(-3)).all(-1)
    return torch.where(same, k_same.unsqueeze(-1).to(K), K)


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


def normal_interval(upper: Tensor, lower: Tensor, scale: Tensor | float, third: bool = False) -> tuple[Tensor, ...]:
    r"""``log P(m)`` and its derivatives in the location ``m`` at ``m = 0``, for the probability
    that a Gaussian ``N(m, s^2)`` falls in ``(lower, upper)``:

    .. math::
        P(m) = \Phi(a) - \Phi(b), \qquad a = (\mathrm{upper} - m) / s, \quad b = (\mathrm{lower} - m) / s.

    With ``r_a = phi(a) / P`` and ``r_b = phi(b) / P`` (computed in log space):
    ``d log P / dm = (r_b - r_a) / s``, ``P'' / P = (b r_b - a r_a) / s^2`` and
    ``P''' / P = ((1 - a^2) r_a - (1 - b^2) r_b) / s^3``, so ``d^2 log P = P''/P - (d log P)^2`` and
    ``d^3 log P = P'''/P - 3 (d log P) P''/P + 2 (d log P)^3``. ``log P`` and the ratios are accurate in
    both tails (a tail interval is mirrored below zero and written ``Phi(hi) (1 - Phi(lo)/Phi(hi))``
    with the scaled complementary error function) and for short intervals around zero (``erf``).
    The second and third derivatives cancel terms of order ``z^2`` and ``z^3`` (``z`` the
    standardised distance of the interval, as for the probit), so far in a tail their absolute
    error is about ``1e-16 z^k / s^k``. ``lower`` may be ``-inf`` and ``upper`` ``+inf``
    (one-sided intervals: the probit); values and gradients stay finite. An interval probability
    is log-concave in ``m``, so the second derivative is never positive.

    Args:
        upper, lower: bounds minus the location (broadcast together), ``upper > lower``.
        scale: ``s > 0``.
        third: also return the third derivative.

    Returns:
        ``(log P, d log P / dm, d^2 log P / dm^2)`` and, with ``third``, ``d^3 log P / dm^3``.
    """
    a, b, a_inf, b_inf = _standardised_bounds(upper, lower, scale)
    middle, log_mid, r_a_mid, r_b_mid = _central_interval(a, b, a_inf, b_inf)
    mirror, log_tail, r_hi, e = _tail_interval(a, b, a_inf, b_inf)
    log_p = torch.where(middle, log_mid, log_tail)
    r_a = torch.where(middle, r_a_mid, torch.where(mirror, e * r_hi, r_hi))
    r_b = torch.where(middle, r_b_mid, torch.where(mirror, r_hi, e * r_hi))
    s = torch.as_tensor(scale, dtype=a.dtype, device=a.device)
    d1 = (r_b - r_a) / s
    p2 = (b * r_b - a * r_a) / s**2  # P'' / P
    d2 = p2 - d1 * d1
    if not third:
        return log_p, d1, d2
    p3 = ((1 - a * a) * r_a - (1 - b * b) * r_b) / s**3  # P''' / P
    return log_p, d1, d2, p3 - 3 * d1 * p2 + 2 * d1**3


def _standardised_bounds(upper: Tensor, lower: Tensor, scale: Tensor | float):
    """``(a, b, a_inf, b_inf)``: :func:`normal_interval`'s bounds over ``scale``, with finite
    stand-ins where a bound is infinite (``a_inf`` / ``b_inf`` say where)."""
    upper, lower = torch.broadcast_tensors(upper, lower)
    a_inf, b_inf = torch.isinf(upper), torch.isinf(lower)
    a = torch.where(a_inf, lower.detach() + 1, upper) / scale
    b = torch.where(b_inf, upper.detach() - 1, lower) / scale
    a = torch.where(a_inf & b_inf, torch.ones_like(a), a)
    b = torch.where(a_inf & b_inf, -torch.ones_like(b), b)
    return a, b, a_inf, b_inf


def _central_interval(a: Tensor, b: Tensor, a_inf: Tensor, b_inf: Tensor):
    """``(middle, log P, r_a, r_b)`` for the intervals across zero (``middle``): no tail to lose,
    but ``0.5 - 0.5`` cancels for short ones; ``erf`` does not."""
    mirror = b > 0
    hi, hi_inf = torch.where(mirror, -b, a), torch.where(mirror, b_inf, a_inf)
    middle = (hi > 0) | hi_inf
    a_m = torch.where(middle & ~a_inf, a, torch.ones_like(a))
    b_m = torch.where(middle & ~b_inf, b, -torch.ones_like(b))
    P_mid = 0.5 * (
        torch.where(a_inf, torch.ones_like(a), torch.erf(a_m / math.sqrt(2)))
        - torch.where(b_inf, -torch.ones_like(b), torch.erf(b_m / math.sqrt(2)))
    )
    log_mid = torch.log(P_mid)
    r_a_mid = torch.where(a_inf, torch.zeros_like(a), torch.exp(-0.5 * a_m * a_m - LOG_2PI_HALF - log_mid))
    r_b_mid = torch.where(b_inf, torch.zeros_like(b), torch.exp(-0.5 * b_m * b_m - LOG_2PI_HALF - log_mid))
    return middle, log_mid, r_a_mid, r_b_mid


def _tail_interval(a: Tensor, b: Tensor, a_inf: Tensor, b_inf: Tensor):
    """``(mirror, log P, r_hi, e)`` for the intervals in a tail. An upper-tail one (``mirror``)
    is mirrored below zero, ``P = Phi(-b) - Phi(-a)``; the ratios ``phi / P`` are ``r_hi`` at the
    upper bound of the (mirrored) interval and ``e r_hi`` at its lower one."""
    mirror = b > 0
    hi, lo = torch.where(mirror, -b, a), torch.where(mirror, -a, b)
    hi_inf, lo_inf = torch.where(mirror, b_inf, a_inf), torch.where(mirror, a_inf, b_inf)
    # a lower-tail interval (hi <= 0): Phi(z) = erfcx(-z / sqrt 2) exp(-z^2 / 2) / 2 keeps the ratios
    # phi / Phi free of exp(-z^2 / 2) over exp(-z^2 / 2); with q = Phi(lo) / Phi(hi) and
    # e = phi(lo) / phi(hi) = exp(-(lo - hi)(lo + hi) / 2): r_hi = (phi / Phi)(hi) / (1 - q), r_lo = e r_hi
    hi_t = torch.where(hi_inf, torch.zeros_like(hi), torch.clamp(hi, max=0.0))
    lo_t = torch.where(lo_inf, hi_t - 1, torch.minimum(lo, hi_t - 1e-300))
    cx_hi = torch.special.erfcx(-hi_t / math.sqrt(2))
    e = torch.where(lo_inf, torch.zeros_like(lo), torch.exp(-0.5 * (lo_t - hi_t) * (lo_t + hi_t)))
    q = e * torch.special.erfcx(-lo_t / math.sqrt(2)) / cx_hi
    log_tail = log_ndtr(hi_t) + torch.log1p(-q)
    r_hi = math.sqrt(2 / math.pi) / cx_hi / (1 - q)
    return mirror, log_tail, r_hi, e
