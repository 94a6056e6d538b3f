r"""Laplace inference for the mixed ratings + comparisons GP: pure functions of tensors.

Notation (paper Sec. III.B): ``K`` the kernel matrix of the ``n`` items, ``L L^T = K + jitter I``
its Cholesky factor, ``f`` the latent utilities. We work in whitened coordinates ``f = L a``,
where the log posterior (eq. 2) is

.. math::
    \Psi(a) = \log p(Y \mid L a) - \tfrac12 a^\top a,

its negative Hessian is ``B = I + L^T W L`` with ``W`` the negative Hessian of the
log-likelihood (eq. 8), and the Laplace evidence is

.. math::
    \log q(Y) = \log p(Y \mid \hat f) - \tfrac12 \hat f^\top K^{-1} \hat f - \tfrac12 \log|I + W K|,

using ``f^T K^{-1} f = a^T a`` and ``|I + W K| = |B|`` (Sylvester). The whitened form needs no
square root of ``W``, so it stays valid where the Beta part of ``W`` is negative (far from
the data); it only needs ``B`` positive definite, which holds at a mode.

``W`` is never formed: a comparison ``[i, j]`` contributes ``lambda_k (e_i - e_j)(e_i - e_j)^T``
and a rating of item ``i`` contributes ``w_k e_i e_i^T``, so
``L^T W L = (D L)^T diag(lambda) (D L) + (R L)^T diag(w) (R L)``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

from torchpref.likelihoods import BetaRatingLikelihood, PairwiseProbitLikelihood
from torchpref.numerics import NotPSDError


class LaplaceConvergenceWarning(UserWarning):
    """Newton's method for the posterior mode did not converge within its iteration budget."""


@dataclass(frozen=True)
class Observations:
    """Index structure of the observations and the likelihoods that score them."""

    comparisons: Tensor  # p x 2 long
    ratings: Tensor  # q
    rating_index: Tensor  # q long
    comparison_likelihood: PairwiseProbitLikelihood
    rating_likelihood: BetaRatingLikelihood

    def terms(self, f: Tensor, fisher: bool = False) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        r"""Log-likelihood and its derivatives at ``f`` (``n``).

        Returns:
            ``(log p(Y|f), grad_f log p, lambda (p), w (q))`` where ``W = D^T diag(lambda) D +
            R^T diag(w) R`` is the negative Hessian (eq. 8); with ``fisher=True`` the rating
            weights are their expected (Fisher) values, which are never negative.
        """
        C, u, ri = self.comparisons, self.ratings, self.rating_index
        ll = f.new_zeros(())
        grad = torch.zeros_like(f)
        lam = f.new_zeros(C.shape[0])
        w = f.new_zeros(u.shape[0])
        if C.shape[0]:
            lp, d1, d2 = self.comparison_likelihood.derivatives(f[C[:, 0]] - f[C[:, 1]])
            ll = ll + lp.sum()
            grad = grad.index_add(0, C[:, 0], d1).index_add(0, C[:, 1], -d1)
            lam = -d2
        if u.shape[0]:
            lp, d1, d2 = self.rating_likelihood.derivatives(f[ri], u)
            ll = ll + lp.sum()
            grad = grad.index_add(0, ri, d1)
            w = self.rating_likelihood.fisher(f[ri]) if fisher else -d2
        return ll, grad, lam, w

    def log_likelihood(self, f: Tensor) -> Tensor:
        C, u, ri = self.comparisons, self.ratings, self.rating_index
        ll = f.new_zeros(())
        if C.shape[0]:
            ll = ll + self.comparison_likelihood.log_prob(f[C[:, 0]] - f[C[:, 1]]).sum()
        if u.shape[0]:
            ll = ll + self.rating_likelihood.log_prob(f[ri], u).sum()
        return ll

    def whitened_hessian(self, L: Tensor, lam: Tensor, w: Tensor) -> Tensor:
        r"""``B = I + L^T W L``."""
        C, ri = self.comparisons, self.rating_index
        B = torch.eye(L.shape[-1], dtype=L.dtype, device=L.device)
        if C.shape[0]:
            DL = L[C[:, 0]] - L[C[:, 1]]  # p x n
            B = B + DL.mT @ (lam.unsqueeze(-1) * DL)
        if ri.shape[0]:
            RL = L[ri]  # q x n
            B = B + RL.mT @ (w.unsqueeze(-1) * RL)
        return B

    def W_dense(self, n: int, lam: Tensor, w: Tensor) -> Tensor:
        """The ``n x n`` matrix ``W`` (eq. 8), for inspection and tests."""
        C, ri = self.comparisons, self.rating_index
        W = lam.new_zeros(n, n)
        if C.shape[0]:
            i, j = C[:, 0], C[:, 1]
            rows = torch.cat([i, j, i, j])
            cols = torch.cat([i, j, j, i])
            W = W.index_put((rows, cols), torch.cat([lam, lam, -lam, -lam]), accumulate=True)
        if ri.shape[0]:
            W = W.index_put((ri, ri), w, accumulate=True)
        return W


@dataclass
class ModeResult:
    """Output of :func:`find_mode` (all detached)."""

    a: Tensor  # whitened mode, n
    f: Tensor  # mode, n
    B_chol: Tensor  # Cholesky factor of B = I + L^T W L at the mode (exact W)
    lam: Tensor
    w: Tensor
    iterations: int
    converged: bool
    fisher_fallback: bool  # True when the exact B was not PD at the mode and Fisher W was used


def find_mode(
    L: Tensor,
    obs: Observations,
    f0: Tensor | None = None,
    max_iter: int = 100,
    tol: float = 1e-11,
) -> ModeResult:
    r"""Newton's method with a backtracking line search for the posterior mode (eq. 2).

    Steps use the exact Hessian where ``B`` is positive definite and Fisher scoring for the
    rating terms where it is not; the Armijo line search makes every step increase ``Psi``.

    Args:
        L: ``n x n`` lower Cholesky factor of the (jittered) kernel matrix.
        obs: the observations.
        f0: ``n`` warm start (e.g. the previous mode); zeros by default.
        max_iter: iteration budget.
        tol: stop when half the Newton decrement ``grad^T B^{-1} grad / 2`` (an estimate of the
            distance to the optimum in log-posterior units) is below ``tol``.
    """
    with torch.no_grad():
        L = L.detach()
        n = L.shape[-1]
        if f0 is None:
            a = L.new_zeros(n)
        else:
            a = torch.linalg.solve_triangular(L, f0.detach().to(L).unsqueeze(-1), upper=False).squeeze(-1)
            if not torch.isfinite(a).all():
                a = L.new_zeros(n)

        def psi(a_: Tensor) -> Tensor:
            return obs.log_likelihood(L @ a_) - 0.5 * (a_ * a_).sum()

        converged = False
        it = 0
        current = psi(a)
        last = None  # (f, lam, w, M, fisher) factorised at the current ``a``
        for it in range(1, max_iter + 1):
            f = L @ a
            _, g, lam, w = obs.terms(f)
            grad = L.mT @ g - a
            M, info = torch.linalg.cholesky_ex(obs.whitened_hessian(L, lam, w))
            fisher = bool(info)
            if fisher:  # exact Hessian not negative definite here: Fisher scoring step
                _, _, lam, w = obs.terms(f, fisher=True)
                M, info = torch.linalg.cholesky_ex(obs.whitened_hessian(L, lam, w))
                if info:
                    raise NotPSDError("the Fisher-scoring Newton matrix B is not positive definite")
            step = torch.cholesky_solve(grad.unsqueeze(-1), M).squeeze(-1)
            decrement = (grad * step).sum()
            if not torch.isfinite(decrement):
                raise FloatingPointError("non-finite Newton step while finding the Laplace mode")
            if decrement / 2 < tol:
                converged = True
                last = (f, lam, w, M, fisher)  # ``a`` is unchanged: reuse this factorisation
                break
            t = 1.0
            accepted = False
            while t > 1e-12:
                a_new = a + t * step
                new = psi(a_new)
                if torch.isfinite(new) and new >= current + 1e-4 * t * decrement:
                    accepted = True
                    break
                t *= 0.5
            if not accepted:
                # no ascent possible in floating point: at the optimum up to round-off
                converged = bool(decrement / 2 < 1e-6)
                break
            a, current = a_new, new
        if last is not None:
            f, lam, w, M, fisher_fallback = last
        else:
            f = L @ a
            _, g, lam, w = obs.terms(f)
            M, info = torch.linalg.cholesky_ex(obs.whitened_hessian(L, lam, w))
            fisher_fallback = bool(info)
            if fisher_fallback:
                _, _, lam, w = obs.terms(f, fisher=True)
                M = torch.linalg.cholesky(obs.whitened_hessian(L, lam, w))
        if fisher_fallback:
            warnings.warn(
                "the Laplace Hessian is not positive definite at the returned mode; the predictive "
                "covariance uses the Fisher (expected) W for the ratings instead",
                LaplaceConvergenceWarning,
                stacklevel=2,
            )
        if not converged:
            warnings.warn(
                f"Newton's method for the Laplace mode did not converge in {it} iterations "
                f"(Newton decrement {float(decrement):.3g})",
                LaplaceConvergenceWarning,
                stacklevel=2,
            )
    return ModeResult(a, f, M, lam, w, it, converged, fisher_fallback)


def laplace_evidence(L: Tensor, obs: Observations, mode: ModeResult) -> Tensor:
    r"""The Laplace evidence ``log q(Y)``, differentiable in the hyperparameters.

    ``L`` (and the likelihoods' parameters) may carry gradients; ``mode`` is the detached mode
    for the same values. One Newton step from the detached mode, ``a~ = a + B^{-1} grad Psi(a)``,
    leaves the value unchanged (the gradient is zero at the mode) while its derivative is
    exactly the implicit-function derivative ``d a / d theta``, so autograd of the result
    includes the dependence of the mode on the hyperparameters, including through ``W``.
    """
    a = mode.a
    _, g, _, _ = obs.terms(L @ a)
    grad = L.mT @ g - a
    a_t = a + torch.cholesky_solve(grad.unsqueeze(-1), mode.B_chol).squeeze(-1)
    f_t = L @ a_t
    ll, _, lam, w = obs.terms(f_t, fisher=mode.fisher_fallback)
    B = obs.whitened_hessian(L, lam, w)
    M, info = torch.linalg.cholesky_ex(B)
    if info:
        raise NotPSDError("B = I + L^T W L is not positive definite at the Laplace mode")
    return ll - 0.5 * (a_t * a_t).sum() - torch.log(torch.diagonal(M)).sum()


class PredictiveCache:
    """What prediction needs, computed once per mode (eqs. 9-10).

    ``A = I - B^-1`` (an ``n x n`` inverse) is formed on first use only, so that re-solving the
    mode during a hyperparameter fit, where no prediction is made, does not pay for it.

    Args:
        L: ``n x n`` ``chol(K + jitter I)``.
        alpha: ``n`` vector ``K^-1 f_hat``.
        A: ``n x n`` matrix ``I - B^-1`` (``cov = K** - v^T A v`` with ``v = L^-1 K_X*``); or
            ``None`` with ``B_chol`` given, to compute it lazily.
        B_chol: ``n x n`` Cholesky factor of ``B`` at the mode.
    """

    def __init__(self, L: Tensor, alpha: Tensor, A: Tensor | None = None, *, B_chol: Tensor | None = None):
        if A is None and B_chol is None:
            raise ValueError("give A or B_chol.")
        self.L, self.alpha, self.B_chol, self._A = L, alpha, B_chol, A

    @property
    def A(self) -> Tensor:
        if self._A is None:
            n = self.L.shape[-1]
            Binv = torch.cholesky_inverse(self.B_chol)
            A = torch.eye(n, dtype=self.L.dtype, device=self.L.device) - Binv
            self._A = 0.5 * (A + A.mT)
        return self._A


def predictive_cache(L: Tensor, mode: ModeResult) -> PredictiveCache:
    alpha = torch.linalg.solve_triangular(L.mT, mode.a.unsqueeze(-1), upper=True).squeeze(-1)
    return PredictiveCache(L, alpha, B_chol=mode.B_chol)


def predict(cache: PredictiveCache, K_xs: Tensor, k_ss: Tensor) -> tuple[Tensor, Tensor]:
    r"""Predictive mean and covariance (eqs. 9-10).

    Args:
        cache: from :func:`predictive_cache`.
        K_xs: ``n x b x q`` cross-covariances between the training items and ``b`` batches of
            ``q`` test points.
        k_ss: ``b x q x q`` prior covariance of each batch.

    Returns:
        mean ``b x q`` and covariance ``b x q x q``:
        ``mean = K_*X K^-1 f_hat`` (eq. 9) and ``cov = K_** - K_*X (I + W K)^-1 W K_X*`` (eq. 10),
        computed as ``K_** - v^T (I - B^-1) v`` with ``v = L^-1 K_X*``.
    """
    n, b, q = K_xs.shape
    flat = K_xs.reshape(n, b * q)
    mean = (cache.alpha @ flat).reshape(b, q)
    v = torch.linalg.solve_triangular(cache.L, flat, upper=False)
    Av = (cache.A @ v).reshape(n, b, q)
    v = v.reshape(n, b, q)
    cov = k_ss - torch.einsum("nbq,nbr->bqr", v, Av)
    return mean, cov
