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

import functools
import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

from torchpref.likelihoods import BetaRatingLikelihood, PairwiseProbitLikelihood
from torchpref.numerics import NotPSDError, default_tolerance, lower_t_matmul


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

    def adjoint(self, n: int, x: Tensor | None = None, y: Tensor | None = None) -> Tensor:
        r"""``D^T x + R^T y`` (``n``): per-comparison values ``x`` (``p``) added at the preferred
        item and subtracted at the other, per-rating values ``y`` (``q``) added at the rated item."""
        C, ri = self.comparisons, self.rating_index
        ref = x if x is not None else y
        out = ref.new_zeros(n)
        if x is not None and C.shape[0]:
            out = out.index_add(0, C[:, 0], x).index_add(0, C[:, 1], -x)
        if y is not None and ri.shape[0]:
            out = out.index_add(0, ri, y)
        return out

    def terms(self, f: Tensor, fisher: bool = False) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        r"""Log-likelihood and its derivatives at ``f`` (``n``).

        Returns:
            ``(log p(Y|f), grad_f log p, lambda (p), w (q))`` where ``W = D^T diag(lambda) D +
            R^T diag(w) R`` is the negative Hessian (eq. 8); with ``fisher=True`` the rating
            weights are their expected (Fisher) values, which are never negative.
        """
        C, u, ri = self.comparisons, self.ratings, self.rating_index
        ll = f.new_zeros(())
        d1c, lam = f.new_zeros(C.shape[0]), f.new_zeros(C.shape[0])
        d1r, w = f.new_zeros(u.shape[0]), f.new_zeros(u.shape[0])
        if C.shape[0]:
            lp, d1c, d2 = self.comparison_likelihood.derivatives(f[C[:, 0]] - f[C[:, 1]])
            ll = ll + lp.sum()
            lam = -d2
        if u.shape[0]:
            lp, d1r, d2 = self.rating_likelihood.derivatives(f[ri], u)
            ll = ll + lp.sum()
            w = self.rating_likelihood.fisher(f[ri]) if fisher else -d2
        return ll, self.adjoint(f.shape[0], d1c, d1r), lam, w

    def curvature_slopes(self, f: Tensor) -> tuple[Tensor, Tensor]:
        r"""``(d lambda / d eta, d w / d eta)``: how each term's weight in ``W`` changes with its
        predictor (minus the likelihoods' third derivatives), for the evidence's gradient."""
        C, u, ri = self.comparisons, self.ratings, self.rating_index
        dlam, dw = f.new_zeros(C.shape[0]), f.new_zeros(u.shape[0])
        if C.shape[0]:
            dlam = -self.comparison_likelihood.third_derivative(f[C[:, 0]] - f[C[:, 1]])
        if u.shape[0]:
            dw = -self.rating_likelihood.third_derivative(f[ri], u)
        return dlam, dw

    def pair_variances(self, S: Tensor) -> tuple[Tensor, Tensor]:
        r"""``(d_k^T S d_k, S_{ii})`` per comparison and per rating, for an ``n x n`` ``S``."""
        C, ri = self.comparisons, self.rating_index
        diag = S.diagonal()
        i, j = C[:, 0], C[:, 1]
        return diag[i] + diag[j] - 2 * S[i, j], diag[ri]

    @functools.cached_property
    def _W_pattern(self) -> tuple[Tensor, Tensor]:
        """``W``'s nonzero pattern, computed once: ``(2 x nnz indices, slot of each term)``."""
        C, ri = self.comparisons, self.rating_index
        i, j = C[:, 0], C[:, 1]
        rows, cols = torch.cat([i, j, i, j, ri]), torch.cat([i, j, j, i, ri])
        n = int(torch.cat([rows, cols.new_zeros(1)]).max()) + 1
        keys, slot = torch.unique(rows * n + cols, return_inverse=True)  # sorted: coalesced order
        return torch.stack([keys // n, keys % n]), slot

    def W_sparse(self, n: int, lam: Tensor, w: Tensor) -> Tensor:
        """The ``n x n`` matrix ``W`` (eq. 8) as a coalesced sparse COO tensor."""
        index, slot = self._W_pattern
        vals = lam.new_zeros(index.shape[-1]).index_add(0, slot, torch.cat([lam, lam, -lam, -lam, w]))
        return torch.sparse_coo_tensor(index, vals, (n, n), is_coalesced=True, check_invariants=False)

    def W_dense(self, n: int, lam: Tensor, w: Tensor) -> Tensor:
        """The ``n x n`` matrix ``W`` (eq. 8), for inspection and tests."""
        return self.W_sparse(n, lam, w).to_dense()

    def whitened_hessian(self, L: Tensor, lam: Tensor, w: Tensor) -> Tensor:
        r"""``B = I + L^T W L``.

        With many observations per item and no gradient to track, ``L^T (W L)`` with a sparse
        ``W`` (one ``n^3`` product); otherwise ``(D L)^T diag(lambda) (D L) + (R L)^T diag(w) (R L)``
        (``(p + q) n^2``, differentiable).
        """
        C, ri = self.comparisons, self.rating_index
        n = L.shape[-1]
        tracked = torch.is_grad_enabled() and (L.requires_grad or lam.requires_grad or w.requires_grad)
        if not tracked and 2 * (C.shape[0] + ri.shape[0]) > n:
            B = lower_t_matmul(L, torch.sparse.mm(self.W_sparse(n, lam, w), L))
        else:
            B = L.new_zeros(n, n)
            if C.shape[0]:
                DL = L[C[:, 0]] - L[C[:, 1]]  # p x n
                B = B + DL.mT @ (lam.unsqueeze(-1) * DL)
            if ri.shape[0]:
                RL = L[ri]  # q x n
                B = B + RL.mT @ (w.unsqueeze(-1) * RL)
        B.diagonal().add_(1.0)
        return B


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
    tol: float | None = None,
    max_chord: int = 3,
    single_precision_min_size: int = 256,
    chord_min_size: int = 128,
) -> ModeResult:
    r"""Newton's method with a backtracking line search for the posterior mode (eq. 2).

    Steps use the exact Hessian where ``B`` is positive definite and Fisher scoring for the
    rating terms where it is not; the Armijo line search makes every step increase ``Psi``.
    Near the mode each factorisation of ``B`` also serves up to ``max_chord`` further steps
    (the chord, or Shamanskii, method: a new gradient, the old ``B``), which cost a triangular
    solve instead of an ``n^3`` product and factorisation; they are taken while they contract
    the Newton decrement at least fourfold. Convergence is always judged, and the returned
    factor computed, at the final point with its own exact ``B``.

    Args:
        L: ``n x n`` lower Cholesky factor of the (jittered) kernel matrix.
        obs: the observations.
        f0: ``n`` warm start (e.g. the previous mode); zeros by default.
        max_iter: iteration budget (factorisations).
        tol: stop when half the Newton decrement ``grad^T B^{-1} grad / 2`` (an estimate of the
            distance to the optimum in log-posterior units) is below ``tol``; default
            :func:`~torchpref.numerics.default_tolerance` of ``L``'s dtype.
        max_chord: chord steps per factorisation (0: plain Newton).
        chord_min_size: chord steps only from this ``n`` on: for small ``n`` a factorisation
            costs about as much as the gradient a chord step needs, and plain Newton takes fewer
            steps.
        single_precision_min_size: from this ``n`` on, float64 problems take their steps far
            from the mode (Newton decrement above 1) with ``B`` factorised in float32, falling
            back to float64 if that factorisation fails or its step does not increase ``Psi``.
    """
    tol = default_tolerance(L.dtype) if tol is None else tol
    with torch.no_grad():
        L = L.detach()
        n = L.shape[-1]
        if f0 is None:
            a = L.new_zeros(n)
        else:
            a = torch.linalg.solve_triangular(L, f0.detach().to(L).unsqueeze(-1), upper=False).squeeze(-1)
            if not torch.isfinite(a).all():
                a = L.new_zeros(n)

        def evaluate(a_: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
            """``(a, Psi(a), f, grad Psi(a), lambda, w)``: one likelihood pass serves the line
            search's test and, if the point is accepted, the next Newton step."""
            f_ = L @ a_
            ll_, g_, lam_, w_ = obs.terms(f_)
            return a_, ll_ - 0.5 * (a_ * a_).sum(), f_, L.mT @ g_ - a_, lam_, w_

        def search(point_, step_: Tensor, decrement_: Tensor):
            """Armijo backtracking from ``point_`` along ``step_``: the accepted point or ``None``."""
            t = 1.0
            while t > 1e-12:
                new = evaluate(point_[0] + t * step_)
                if torch.isfinite(new[1]) and new[1] >= point_[1] + 1e-4 * t * decrement_:
                    return new
                t *= 0.5
            return None

        def single_precision_step(point_):
            """A Newton step factorised in float32: ``(new point, decrement)`` or ``None``."""
            nonlocal L32
            if L32 is None:
                L32 = L.float()
            _, _, _, grad_, lam_, w_ = point_
            M32, info32 = torch.linalg.cholesky_ex(obs.whitened_hessian(L32, lam_.float(), w_.float()))
            if info32:
                return None
            step_ = torch.cholesky_solve(grad_.float().unsqueeze(-1), M32).squeeze(-1).to(L.dtype)
            decrement_ = (grad_ * step_).sum()
            if not (torch.isfinite(decrement_) and decrement_ / 2 >= tol):
                return None
            found_ = search(point_, step_, decrement_)
            return None if found_ is None else (found_, decrement_)

        converged = False
        it = 0
        point = evaluate(a)
        last = None  # (f, lam, w, M, fisher) factorised at the current point
        # far from the mode (no step yet, or a Newton decrement above 1) a step's direction need
        # not be accurate: large float64 problems factorise B in float32 there, at half the cost
        far_allowed = L.dtype == torch.float64 and n >= single_precision_min_size
        far = far_allowed
        L32 = None
        for it in range(1, max_iter + 1):
            if far:
                taken = single_precision_step(point)
                if taken is not None:
                    point, decrement = taken
                    far = bool(decrement > 1.0)
                    continue
                far = far_allowed = False  # float32 does not suffice for this problem
            _, _, f, grad, lam, w = point
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
                last = (f, lam, w, M, fisher)  # the point is unchanged: reuse this factorisation
                break
            found = search(point, step, decrement)
            if found is None:
                # no ascent possible in floating point: at the optimum up to round-off
                converged = bool(decrement / 2 < 1e-6)
                break
            point = found
            if decrement > 1.0:  # far from the mode the old B is a poor model: refactorise
                far = far_allowed
                continue
            for _ in range(max_chord if n >= chord_min_size else 0):
                grad_c = point[3]
                step_c = torch.cholesky_solve(grad_c.unsqueeze(-1), M).squeeze(-1)
                decrement_c = (grad_c * step_c).sum()
                if not decrement_c < 0.25 * decrement:
                    break  # not contracting fast enough (or not finite): refactorise
                if decrement_c < 1e-8:  # Psi would change by less than its round-off: full step
                    found = evaluate(point[0] + step_c)
                else:
                    found = search(point, step_c, decrement_c)
                if found is None:
                    break
                point, decrement = found, decrement_c
                if decrement / 2 < tol:
                    break  # converged, to be confirmed with a fresh B
        a = point[0]
        if last is not None:
            f, lam, w, M, fisher_fallback = last
        else:
            _, _, f, _, lam, w = point
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


def laplace_evidence(K: Tensor, obs: Observations, mode: ModeResult, L: Tensor | None = None,
                     jitter: float = 0.0) -> Tensor:
    r"""The Laplace evidence ``log q(Y)``, differentiable in the hyperparameters.

    Args:
        K: ``n x n`` kernel matrix; may carry gradients (the kernel's hyperparameters).
        obs: the observations; the likelihoods' parameters may carry gradients.
        mode: the detached mode for the same values.
        L: ``chol(K + jitter I)`` (detached), if already computed.
        jitter: the diagonal jitter of ``L``.

    The value is ``log p(Y|f) - a^T a / 2 - log|B| / 2`` at the mode. Its gradient is written
    out rather than traced through the factorisations: with ``Sigma = (K^-1 + W)^-1 = L B^-1 L^T``,
    ``alpha = K^-1 f`` and ``h = d log|B| / d f`` (through ``W``'s dependence on ``f``, the
    likelihoods' third derivatives), the mode moves as ``df = (I + K W)^-1 (dK alpha + K
    d(grad log p))`` (implicit function theorem), which gives

    .. math::
        \frac{\partial \log q}{\partial K} = \tfrac12 \alpha\alpha^\top
            - \tfrac12 (W - W \Sigma W) - \tfrac12 (I - W\Sigma) h\, \alpha^\top

    and, for a likelihood parameter ``phi``, ``d log p / d phi - tr(Sigma dW/d phi) / 2 -
    (Sigma h)^T d(grad log p)/d phi / 2`` at the fixed mode. Both are applied through a
    surrogate whose autograd gradient is exactly this and whose value is zero. Where ``mode``
    fell back to Fisher weights (``B`` not positive definite at the mode), the evidence is
    traced through the factorisations instead (:func:`_laplace_evidence_traced`).
    """
    n = K.shape[-1]
    if mode.fisher_fallback:
        eye = torch.eye(n, dtype=K.dtype, device=K.device)
        return _laplace_evidence_traced(torch.linalg.cholesky(K + jitter * eye), obs, mode)
    ll, g, lam, w = obs.terms(mode.f)  # the likelihood parameters may carry gradients
    with torch.no_grad():
        if L is None:
            L = torch.linalg.cholesky(K.detach() + jitter * torch.eye(n, dtype=K.dtype, device=K.device))
        L, a, f, M = L.detach(), mode.a, mode.f, mode.B_chol
        alpha = torch.linalg.solve_triangular(L.mT, a.unsqueeze(-1), upper=True).squeeze(-1)
        V = torch.linalg.solve_triangular(M, L.mT, upper=False)  # M^-1 L^T
        Sigma = V.mT @ V
        s_c, s_r = obs.pair_variances(Sigma)
        dlam, dw = obs.curvature_slopes(f)
        h = obs.adjoint(n, dlam * s_c, dw * s_r)
        W = obs.W_sparse(n, mode.lam, mode.w)
        Sigma_h = Sigma @ h
        b = h - torch.sparse.mm(W, Sigma_h.unsqueeze(-1)).squeeze(-1)  # (I - W Sigma) h
        W_Sigma_W = torch.sparse.mm(W, torch.sparse.mm(W, Sigma).mT)
        G = 0.5 * torch.outer(alpha, alpha) - 0.5 * (W.to_dense() - W_Sigma_W) - 0.5 * torch.outer(b, alpha)
        # the mode is exact only to the solver's tolerance: one more Newton step's first-order
        # change of the value makes it second-order accurate (smooth in the hyperparameters)
        grad_a = L.mT @ g.detach() - a
        step = torch.cholesky_solve(grad_a.unsqueeze(-1), M).squeeze(-1)
        value = (ll.detach() - 0.5 * (a * a).sum() - torch.log(torch.diagonal(M)).sum()
                 + 0.5 * (grad_a * step).sum() - 0.5 * (h * (L @ step)).sum())
    # the likelihood parameters' part, at the fixed mode (constants unless they carry gradients)
    surrogate = (G * K).sum() + ll - 0.5 * (lam * s_c).sum() - 0.5 * (w * s_r).sum() - 0.5 * (Sigma_h * g).sum()
    return value + (surrogate - surrogate.detach())


def _laplace_evidence_traced(L: Tensor, obs: Observations, mode: ModeResult) -> Tensor:
    r"""The evidence with its gradient traced by autograd (``L`` carries the gradients).

    One Newton step from the detached mode, ``a~ = a + B^{-1} grad Psi(a)``, leaves the value
    unchanged (the gradient is zero at the mode) while its derivative is exactly the
    implicit-function derivative ``d a / d theta``, so autograd of the result includes the
    dependence of the mode on the hyperparameters, including through ``W``.
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
