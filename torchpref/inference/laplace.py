r"""Laplace inference for the mixed ratings + comparisons GP: pure functions of tensors, batch-first.

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

``W`` is never formed on the solver's path: each observation ``k`` with row ``d_k`` adds
``w_k d_k^T d_k`` (:mod:`torchpref.inference.observations`), so ``L^T W L = sum_k w_k (d_k L)^T (d_k L)``.

Batch-first: every function takes ``b`` independent problems, ``L`` of shape ``b x n x n`` and
:class:`~torchpref.inference.observations.Observations` for ``b`` problems; a single problem is ``b = 1``
(or an unbatched ``n x n`` ``L``, which returns unbatched results). Problems of different sizes
are padded to common ones: a padded item has prior variance 1, no correlation and no
observation (its mode is 0 and it changes nothing), a padded observation has ``mask`` false.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, fields, replace
from typing import cast

import torch
from torch import Tensor

from torchpref.inference.fast_path import solve_mode
from torchpref.inference.newton import NewtonOptions, newton_mode
from torchpref.inference.numerics import LaplaceNumericalError, NotPSDError, default_tolerance
from torchpref.inference.observations import Observations, Term, item_term, pairwise_term  # noqa: F401  (re-exported)
from torchpref.inference.shapes import Latent, Matrices, ProblemMask, TermValues


class LaplaceConvergenceWarning(UserWarning):
    """Newton's method for the posterior mode did not converge within its iteration budget."""


@dataclass
class ModeResult:
    """Output of :func:`find_mode` (all detached), with the shapes of a batch of ``b``."""

    a: Latent  # whitened mode
    f: Latent  # mode, f = L a
    M: Matrices  # Cholesky factor of B = I + L^T W L at the mode (exact W)
    weights: tuple[TermValues, ...]  # per term: W = sum_k w_k d_k^T d_k at the mode
    iterations: int
    converged: ProblemMask
    fisher_fallback: ProblemMask  # exact B not PD at the mode, the Fisher W used instead
    solver: str = "torch"  # which solver found it: "compiled" (numba, fast_path) or "torch"

    def select(self, index: int | slice | Tensor) -> ModeResult:
        """The problems ``index`` (an int drops the batch dimension)."""

        def pick(v):
            return tuple(w[index] for w in v) if isinstance(v, tuple) else v[index] if isinstance(v, Tensor) else v

        return replace(self, **{fl.name: pick(getattr(self, fl.name)) for fl in fields(self)})

    def batched(self) -> ModeResult:
        """With a batch dimension (a no-op for a batched result)."""
        if self.f.dim() == 2:
            return self

        def add(v):
            return tuple(w[None] for w in v) if isinstance(v, tuple) else v[None] if isinstance(v, Tensor) else v

        return replace(self, **{fl.name: add(getattr(self, fl.name)) for fl in fields(self)})


def find_mode(
    L: Tensor,
    obs: Observations,
    f0: Tensor | tuple[Tensor, ...] | None = None,
    max_iter: int = 100,
    tol: float | None = None,
    max_chord: int = 3,
    single_precision_min_size: int = 256,
    chord_min_size: int = 128,
) -> ModeResult:
    r"""Newton's method with a backtracking line search for the posterior modes (eq. 2).

    Steps use the exact Hessian where ``B`` is positive definite and Fisher scoring for the
    terms that are not log-concave where it is not; the Armijo line search makes every step
    increase ``Psi``. Near the mode each factorisation of ``B`` also serves up to ``max_chord``
    further steps (the chord, or Shamanskii, method: a new gradient, the old ``B``), taken while
    they contract the Newton decrement at least fourfold. Large float64 problems take their
    steps far from the mode with ``B`` factorised in float32. Each problem stops moving once
    converged; convergence is judged, and the returned factor computed, at the final point with
    its own exact ``B``. See :mod:`torchpref.inference.newton` for the steps.

    Args:
        L: ``b x n x n`` (or ``n x n``) lower Cholesky factors of the (jittered) kernel matrices.
        obs: the observations of the ``b`` problems.
        f0: ``b x n`` (or ``n``) warm start (e.g. the previous mode), or a tuple of candidate
            starts, of which each problem starts from the one of highest ``Psi``; zeros by default.
        max_iter: iteration budget (factorisations).
        tol: a problem has converged when half its Newton decrement ``grad^T B^{-1} grad / 2``
            (an estimate of the distance to the optimum in log-posterior units) is below ``tol``;
            default :func:`~torchpref.inference.numerics.default_tolerance` of ``L``'s dtype.
        max_chord: chord steps per factorisation (0: plain Newton).
        single_precision_min_size: from this ``n`` on, float64 problems take their steps far
            from the mode (Newton decrement above 1) in float32, falling back to float64 if that
            factorisation fails or its step does not increase ``Psi``.
        chord_min_size: chord steps only from this ``n`` on (for small ``n`` a factorisation
            costs about as much as the gradient a chord step needs).

    Raises:
        NotPSDError: the Fisher-scoring ``B`` is not positive definite.
        LaplaceNumericalError: (a ``NotPSDError``) a non-finite Newton step or another
            arithmetic failure of the iteration; no bare ``FloatingPointError`` escapes.
    """
    single = L.dim() == 2
    if single:
        L = L[None]
    n = L.shape[-1]
    tol = default_tolerance(L.dtype) if tol is None else tol
    compiled = _compiled_mode(L, obs, f0, max_iter, tol)
    if compiled is not None:
        return compiled.select(0) if single else compiled
    opts = NewtonOptions(
        max_iter,
        tol,
        max_chord if n >= chord_min_size else 0,
        L.dtype == torch.float64 and n >= single_precision_min_size,
    )
    # inference mode: no autograd bookkeeping on the many small tensors of the iterations; the
    # results are cloned out of it, as later autograd passes may save them for backward
    with torch.inference_mode():
        starts = (
            ()
            if f0 is None
            else tuple(f.detach().to(L).reshape(L.shape[:-1]) for f in (f0 if isinstance(f0, tuple) else (f0,)))
        )
        try:
            out = newton_mode(L.detach(), obs, starts, opts)
        except NotPSDError:
            raise
        except (ArithmeticError, torch.linalg.LinAlgError) as err:  # FloatingPointError: a non-finite step
            raise LaplaceNumericalError(f"the Laplace mode could not be found: {err}") from err
    mode = ModeResult(
        out.point.a.clone(),
        cast(Tensor, out.point.f).clone(),  # set by newton_mode
        out.factor.M.clone(),
        tuple(w.clone() for w in out.factor.weights),
        out.iterations,
        out.converged.clone(),
        out.factor.fisher.clone(),
    )
    decrement = out.decrement.clone()
    _warn(mode, decrement)
    return mode.select(0) if single else mode


def _compiled_mode(
    L: Tensor, obs: Observations, f0: Tensor | tuple[Tensor, ...] | None, max_iter: int, tol: float
) -> ModeResult | None:
    """The mode from the compiled path (:func:`torchpref.inference.fast_path.solve_mode` decides
    whether it applies), or ``None``: then the torch solver runs (also where the compiled Newton did
    not converge or met a non-finite step, so that its warnings and errors are the torch solver's)."""
    out = solve_mode(L, obs, () if f0 is None else (f0 if isinstance(f0, tuple) else (f0,)), max_iter, tol)
    if out is None:
        return None
    one, no = torch.ones(1, dtype=torch.bool), torch.zeros(1, dtype=torch.bool)
    weights = tuple(w[None] for w in out.weights)
    return ModeResult(out.a[None], out.f[None], out.M[None], weights, out.iterations, one, no, solver="compiled")


def predicted_mode(f: Tensor, cache: PredictiveCache, L: Tensor) -> Tensor:
    r"""A start for the modes under new prior factors ``L`` (``b x n x n``, ``L L^T = K + jitter I``):
    the old modes ``f`` (``b x n``) moved to first order in the change of ``K`` (implicit function
    theorem, the likelihoods unchanged), ``f + (I + K_old W)^-1 (K - K_old) alpha`` with
    ``alpha = K_old^-1 f`` from the old modes' prediction ``cache``; computed as
    ``L_old B_old^-1 L_old^-1 (K alpha - f)``, since ``K_old alpha = f``. Where that is not finite, ``f``."""
    alpha = cache.alpha.unsqueeze(-1)
    change = L @ (L.mT @ alpha) - f.unsqueeze(-1)  # (K - K_old) alpha
    step = cache.L @ torch.cholesky_solve(torch.linalg.solve_triangular(cache.L, change, upper=False), cache.M)
    start = f + step.squeeze(-1)
    return torch.where(torch.isfinite(start).all(-1, keepdim=True), start, f)


def _warn(mode: ModeResult, decrement: Tensor) -> None:
    def which(mask: Tensor) -> str:
        return "" if mask.numel() == 1 else f" of problems {mask.nonzero().reshape(-1).tolist()}"

    if bool(mode.fisher_fallback.any()):
        warnings.warn(
            f"the Laplace Hessian is not positive definite at the returned mode{which(mode.fisher_fallback)}; "
            "the predictive covariance uses the Fisher (expected) W instead",
            LaplaceConvergenceWarning,
            stacklevel=3,
        )
    if not bool(mode.converged.all()):
        bad = ~mode.converged
        warnings.warn(
            f"Newton's method for the Laplace mode{which(bad)} did not converge in {mode.iterations} "
            f"iterations (Newton decrement {float(decrement[bad].max()):.3g})",
            LaplaceConvergenceWarning,
            stacklevel=3,
        )


def _eye(n: int, like: Tensor) -> Tensor:
    return torch.eye(n, dtype=like.dtype, device=like.device)


def laplace_evidence(
    K: Tensor, obs: Observations, mode: ModeResult, L: Tensor | None = None, jitter: float | Tensor = 0.0
) -> Tensor:
    r"""The Laplace evidence ``log q(Y)`` per problem, differentiable in the hyperparameters.

    Args:
        K: ``b x n x n`` (or ``n x n``) kernel matrices; may carry gradients.
        obs: the observations; the likelihoods' parameters may carry gradients.
        mode: the detached modes for the same values.
        L: ``chol(K + jitter I)`` (detached), if already computed.
        jitter: the diagonal jitter of ``L`` (a float or ``b`` values).

    Returns:
        ``b`` values (a scalar for an unbatched ``K``).

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
    single = K.dim() == 2
    K, mode = (K[None], mode.batched()) if single else (K, mode)
    n = K.shape[-1]
    jit = torch.as_tensor(jitter, dtype=K.dtype, device=K.device).reshape(-1, 1, 1)
    if bool(mode.fisher_fallback.any()):
        out = _laplace_evidence_traced(torch.linalg.cholesky(K + jit * _eye(n, K)), obs, mode)
        return out[0] if single else out
    ll, g, weights = obs.evaluate(mode.f)  # the likelihood parameters may carry gradients
    with torch.no_grad():
        L = torch.linalg.cholesky(K.detach() + jit * _eye(n, K)) if L is None else L.detach().reshape(K.shape)
        V = torch.linalg.solve_triangular(mode.M, L.mT, upper=False)  # M^-1 L^T: Sigma = V^T V
        P = obs.rows(V.mT)  # per term, the rows d_k V^T: d_k^T Sigma d_k = |d_k V^T|^2
        s = tuple((Pt * Pt).sum(-1) for Pt in P)
        h = obs.adjoint([dw * sk for dw, sk in zip(obs.curvature_slopes(mode.f), s)], n, like=K)
        Sigma_h = (V.mT @ (V @ h.unsqueeze(-1))).squeeze(-1)
        WV_t = obs.adjoint_rows([w.unsqueeze(-1) * Pt for w, Pt in zip(mode.weights, P)], n, like=V)  # W V^T
        G = _kernel_gradient(_solve_t(L, mode.a), WV_t, h, Sigma_h, obs, mode.weights)
        value = _second_order_value(ll.detach(), g.detach(), L, mode, h)
    # the likelihood parameters' part, at the fixed mode (constants unless they carry gradients)
    surrogate = (G * K).sum((-2, -1)) + ll - 0.5 * (Sigma_h * g).sum(-1)
    for w, sk in zip(weights, s):
        surrogate = surrogate - 0.5 * (w * sk).sum(-1)
    out = value + (surrogate - surrogate.detach())
    return out[0] if single else out


def _kernel_gradient(
    alpha: Tensor, WV_t: Tensor, h: Tensor, Sigma_h: Tensor, obs: Observations, weights: tuple[Tensor, ...]
) -> Tensor:
    r"""``d log q / d K = (alpha alpha^T - (W - W Sigma W) - (I - W Sigma) h alpha^T) / 2``
    (``b x n x n``; see :func:`laplace_evidence`), given ``W V^T`` (``Sigma = V^T V``), whose
    product with its transpose is ``W Sigma W``."""
    n = WV_t.shape[-1]
    W = obs.W_dense(n, weights, like=WV_t)
    b = h - obs.W_vector(weights, Sigma_h)  # (I - W Sigma) h
    return 0.5 * (
        alpha.unsqueeze(-1) * alpha.unsqueeze(-2) - W + WV_t @ WV_t.mT - b.unsqueeze(-1) * alpha.unsqueeze(-2)
    )


def _second_order_value(ll: Tensor, g: Tensor, L: Tensor, mode: ModeResult, h: Tensor) -> Tensor:
    r"""``log p(Y|f) - a^T a / 2 - log|B| / 2`` at the mode (``b`` values), plus the first-order
    change of one more Newton step: the mode is exact only to the solver's tolerance, and the
    corrected value is second-order accurate (smooth in the hyperparameters)."""
    a, M = mode.a, mode.M
    grad_a = (L.mT @ g.unsqueeze(-1)).squeeze(-1) - a
    step = torch.cholesky_solve(grad_a.unsqueeze(-1), M).squeeze(-1)
    return (
        ll
        - 0.5 * (a * a).sum(-1)
        - torch.log(torch.diagonal(M, dim1=-2, dim2=-1)).sum(-1)
        + 0.5 * (grad_a * step).sum(-1)
        - 0.5 * (h * (L @ step.unsqueeze(-1)).squeeze(-1)).sum(-1)
    )


def _solve_t(L: Tensor, a: Tensor) -> Tensor:
    """``L^-T a`` for ``b x n`` ``a``."""
    return torch.linalg.solve_triangular(L.mT, a.unsqueeze(-1), upper=True).squeeze(-1)


def traced_mode(
    L: Tensor, obs: Observations, mode: ModeResult, keep_value: bool = False
) -> tuple[Tensor, Tensor, Tensor]:
    r"""The mode as a differentiable function of ``L`` and the observations' targets.

    One Newton step from the detached mode, ``a~ = a + B^{-1} grad Psi(a)``, taken with autograd
    on: its value is the mode's (the gradient is zero there, up to the solver's tolerance) and its
    derivative is exactly the implicit-function derivative ``d a / d theta`` (with ``B`` fixed,
    ``d a~ = B^{-1} d(grad Psi)``, and ``grad Psi(a(theta), theta) = 0`` gives ``B da = d(grad Psi)``).

    Args:
        L: ``b x n x n`` ``chol(K + jitter I)``, carrying the gradients.
        obs: the observations (their likelihoods' parameters and targets may carry gradients).
        mode: the detached mode for the same values, batched.
        keep_value: return exactly the mode's value (only the derivative of the step); else the
            value after the step (second-order closer to the exact mode).

    Returns:
        ``a~`` (``b x n``), the log-likelihood at ``f~ = L a~`` (``b``) and ``M``, the Cholesky
        factor of ``B = I + L^T W L`` there (``b x n x n``; Fisher ``W`` where ``mode`` used it).

    Raises:
        NotPSDError: ``B`` is not positive definite.
    """
    a = mode.a
    g = obs.evaluate((L @ a.unsqueeze(-1)).squeeze(-1)).grad
    grad = (L.mT @ g.unsqueeze(-1)).squeeze(-1) - a
    step = torch.cholesky_solve(grad.unsqueeze(-1), mode.M).squeeze(-1)
    a_t = a + (step - step.detach() if keep_value else step)
    ll, _, weights = obs.evaluate((L @ a_t.unsqueeze(-1)).squeeze(-1), fisher=mode.fisher_fallback)
    M, info = torch.linalg.cholesky_ex(obs.whitened_hessian(L, weights))
    if bool((info > 0).any()):
        raise NotPSDError("B = I + L^T W L is not positive definite at the Laplace mode")
    return a_t, ll, M


def _laplace_evidence_traced(L: Tensor, obs: Observations, mode: ModeResult) -> Tensor:
    r"""The evidence with its gradient traced by autograd (``L``, ``b x n x n``, carries them)
    through :func:`traced_mode`, so that it includes the dependence of the mode on the
    hyperparameters, including through ``W``."""
    single = L.dim() == 2
    L, mode = (L[None], mode.batched()) if single else (L, mode)
    a_t, ll, M = traced_mode(L, obs, mode)
    out = ll - 0.5 * (a_t * a_t).sum(-1) - torch.log(torch.diagonal(M, dim1=-2, dim2=-1)).sum(-1)
    return out[0] if single else out


class PredictiveCache:
    """What prediction needs, computed once per mode (eqs. 9-10), for ``b`` problems.

    ``A = I - B^-1`` (``b x n x n`` inverses) is formed on first use only, so that re-solving the
    mode during a hyperparameter fit, where no prediction is made, does not pay for it.

    Args:
        L: ``b x n x n`` ``chol(K + jitter I)``.
        alpha: ``b x n`` vectors ``K^-1 f_hat``.
        M: ``b x n x n`` Cholesky factors of ``B`` at the modes.
    """

    def __init__(self, L: Tensor, alpha: Tensor, M: Tensor):
        self.L, self.alpha, self.M = L, alpha, M
        self._A: Tensor | None = None

    @classmethod
    def from_mode(cls, L: Tensor, mode: ModeResult) -> PredictiveCache:
        """The cache for ``mode``, the Laplace mode of the problems whose prior factors are ``L``."""
        mode = mode.batched()
        L = L.reshape(mode.M.shape)
        return cls(L, _solve_t(L, mode.a), mode.M)

    @classmethod
    def traced(cls, K: Tensor, jitter: float | Tensor, obs: Observations, mode: ModeResult) -> PredictiveCache:
        """The cache for ``mode`` as a differentiable function of ``K`` (``b x n x n``) and of the
        observations' targets (:func:`traced_mode`): predictions then have gradients with
        respect to the training items (e.g. a fantasy model's fantasy points) and targets. The
        values are those of :meth:`from_mode`."""
        mode = mode.batched()
        n = K.shape[-1]
        jit = torch.as_tensor(jitter, dtype=K.dtype, device=K.device).reshape(-1, 1, 1)
        L = torch.linalg.cholesky(K.reshape(mode.M.shape) + jit * _eye(n, K))
        a_t, _, M = traced_mode(L, obs, mode, keep_value=True)
        return cls(L, _solve_t(L, a_t), M)

    @property
    def A(self) -> Tensor:
        """``I - B^-1`` (``b x n x n``), so that ``cov = K** - v^T A v`` with ``v = L^-1 K_X*``."""
        A = self._A
        if A is None:
            A = _eye(self.L.shape[-1], self.L) - torch.cholesky_inverse(self.M)
            A = self._A = 0.5 * (A + A.mT)
        return A


def predictive_cache(L: Tensor, mode: ModeResult) -> PredictiveCache:
    """The prediction cache of ``mode`` (:meth:`PredictiveCache.from_mode`)."""
    return PredictiveCache.from_mode(L, mode)


def predict(cache: PredictiveCache, K_xs: Tensor, k_ss: Tensor) -> tuple[Tensor, Tensor]:
    r"""Predictive mean and covariance (eqs. 9-10) of ``t`` blocks of ``q`` test points per problem.

    Args:
        cache: from :func:`predictive_cache` (``b`` problems).
        K_xs: ``b x n x t x q`` cross-covariances between each problem's items and its test points.
        k_ss: ``b x t x q x q`` prior covariance of each block, or ``b x t x q`` prior variances
            (then the posterior variances are returned instead of the covariances).

    Returns:
        mean ``b x t x q`` and covariance ``b x t x q x q`` (or variance ``b x t x q``):
        ``mean = K_*X K^-1 f_hat`` (eq. 9) and ``cov = K_** - K_*X (I + W K)^-1 W K_X*`` (eq. 10),
        computed as ``K_** - v^T (I - B^-1) v`` with ``v = L^-1 K_X*``.
    """
    b, n, t, q = K_xs.shape
    flat = K_xs.reshape(b, n, t * q)
    mean = (cache.alpha.unsqueeze(-2) @ flat).reshape(b, t, q)
    v = torch.linalg.solve_triangular(cache.L, flat, upper=False)
    Av = cache.A @ v
    if k_ss.dim() == 3:
        return mean, k_ss - (v * Av).sum(-2).reshape(b, t, q)
    # v_t^T A v_t per block: (b x t x q x n) @ (b x t x n x q)
    cov = k_ss - v.reshape(b, n, t, q).permute(0, 2, 3, 1) @ Av.reshape(b, n, t, q).transpose(1, 2)
    return mean, cov
