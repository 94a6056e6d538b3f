r"""The compiled hyperparameter fit (issues 33 and 42): a whole fit evaluation, and the whole
L-BFGS fit, each one numba-compiled call, on :mod:`torchpref.inference._compiled`'s mode and
evidence.

The stationary kernels of :func:`kernel_matrix` are GPyTorch's ``RBFKernel`` and ``MaternKernel``
(``nu`` = 1/2, 3/2, 5/2), ARD or shared lengthscale, times an outputscale. What is fitted crosses
the boundary as named structures: :class:`~torchpref.inference.fast_types.FitSpec` (the kernel, which raw parameters are its
lengthscales and outputscale, their constraints and priors) and
:class:`~torchpref.inference.fast_types.FitState` (the
buffers the last successful evaluation leaves its mode and factors in: the fit's warm start, and at
the end what :meth:`~torchpref.models.preference_gp.PreferenceGP` keeps as its posterior cache).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from torchpref.inference._compiled import evidence, jittered_cholesky, newton
from torchpref.inference.fast_types import (
    GAMMA,
    LINE_SEARCH_FAILED,
    LOG_NORMAL,
    MATERN12,
    MATERN32,
    NOT_FINITE,
    NOT_PD,
    OK,
    RBF,
)

#: SciPy's L-BFGS-B defaults, which BoTorch's fit uses: memory, ``ftol``, ``gtol``, iteration limit
LBFGS_MEMORY, LBFGS_FTOL, LBFGS_GTOL, LBFGS_MAXITER = 10, 2.220446049250313e-09, 1e-5, 15000


@njit(cache=True)
def kernel_profile(r2, kind):
    """``k(r) / outputscale`` and ``phi = (d k / d l_k) l_k^3 / (outputscale diff_k^2)`` at the
    squared scaled distance ``r2``, so that ``d k / d l_k = outputscale phi diff_k^2 / l_k^3``."""
    if kind == RBF:
        k = math.exp(-0.5 * r2)
        return k, k
    r = math.sqrt(r2)
    if kind == MATERN12:
        e = math.exp(-r)
        return e, (e / r if r > 0.0 else 0.0)
    if kind == MATERN32:
        c = math.sqrt(3.0) * r
        e = math.exp(-c)
        return (1.0 + c) * e, 3.0 * e
    c = math.sqrt(5.0) * r
    e = math.exp(-c)
    return (1.0 + c + 5.0 / 3.0 * r2) * e, 5.0 / 3.0 * (1.0 + c) * e


@njit(cache=True)
def kernel_matrix(X, ls, outputscale, kind):
    """``K`` (``n x n``) of the items ``X`` (``n x d``) with lengthscales ``ls`` (``d``)."""
    n, d = X.shape
    K = np.empty((n, n))
    for i in range(n):
        K[i, i] = outputscale
        for j in range(i):
            r2 = 0.0
            for c in range(d):
                diff = (X[i, c] - X[j, c]) / ls[c]
                r2 += diff * diff
            k, _ = kernel_profile(r2, kind)
            K[i, j] = outputscale * k
            K[j, i] = K[i, j]
    return K


@njit(cache=True)
def kernel_gradient(X, ls, outputscale, kind, G):
    """``(sum G dK/dl_c for each c, sum G dK/doutputscale)`` for ``G`` (``n x n``, not necessarily
    symmetric)."""
    n, d = X.shape
    gls = np.zeros(d)
    gos = 0.0
    for i in range(n):
        gos += G[i, i]
        for j in range(i):
            r2 = 0.0
            for c in range(d):
                diff = (X[i, c] - X[j, c]) / ls[c]
                r2 += diff * diff
            k, phi = kernel_profile(r2, kind)
            g = G[i, j] + G[j, i]
            gos += g * k
            for c in range(d):
                diff = X[i, c] - X[j, c]
                gls[c] += g * outputscale * phi * diff * diff / (ls[c] * ls[c] * ls[c])
    return gls, gos


@njit(cache=True)
def mode_and_evidence(X, ans, kind, ls, outputscale, state, tol, max_iter):
    """One fit evaluation: ``(log q, d log q / d ls, d log q / d outputscale, status)``, Newton
    warm-started from ``state.f`` (:func:`~torchpref.inference._compiled.newton` retries cold if that fails); on success ``state`` holds the new mode and factors."""
    n = X.shape[0]
    K = kernel_matrix(X, ls, outputscale, kind)
    L, jitter, ok = jittered_cholesky(K)
    if not ok:
        return 0.0, np.zeros(ls.shape[0]), 0.0, NOT_PD
    starts = state.f.reshape(1, state.f.shape[0]) if state.f.shape[0] == n else np.empty((0, n))
    a, M, w, its, status, _ = newton(L, ans, starts, tol, max_iter)  # retried cold if the warm start fails
    if status != OK:
        return 0.0, np.zeros(ls.shape[0]), 0.0, status
    value, G = evidence(L, ans, a, M, w)
    if not np.isfinite(value):
        return 0.0, np.zeros(ls.shape[0]), 0.0, NOT_FINITE
    gls, gos = kernel_gradient(X, ls, outputscale, kind, G)
    if state.f.shape[0] == n:
        state.f[:] = L @ a
        state.a[:] = a
        state.L[:, :] = L
        state.M[:, :] = M
        state.w[:] = w
        state.jitter[0] = jitter
        state.iterations[0] = its
    return value, gls, gos, OK


@njit(cache=True)
def softplus(x):
    """torch's ``softplus`` (threshold 20) and its derivative."""
    if x > 20.0:
        return x, 1.0
    return math.log1p(math.exp(x)), 1.0 / (1.0 + math.exp(-x))


@njit(cache=True)
def log_prior(x, prior):
    """``(log density, its derivative)`` of ``prior`` at ``x > 0`` (0 for none)."""
    if prior.kind == LOG_NORMAL:
        lx = math.log(x)
        z = (lx - prior.p1) / prior.p2
        return prior.const - lx - 0.5 * z * z, (-1.0 - z / prior.p2) / x
    if prior.kind == GAMMA:
        return prior.const + (prior.p1 - 1.0) * math.log(x) - prior.p2 * x, (prior.p1 - 1.0) / x - prior.p2
    return 0.0, 0.0


@njit(cache=True)
def fit_loss(x, X, ans, spec, state, tol, max_iter):
    """BoTorch's loss ``-(log q + log priors)`` and its gradient in the raw parameters ``x``
    (:class:`~torchpref.inference.fast_types.FitSpec`): ``(loss, grad, status)``; ``state`` takes the new mode and factors."""
    d = X.shape[1]
    count = spec.ls_count
    ls = np.empty(d)
    dls = np.empty(count)
    lp = 0.0
    gprior_ls = np.zeros(count)
    for c in range(count):
        v, dv = softplus(x[spec.ls_start + c])
        v += spec.ls_lower
        dls[c] = dv
        pr, dpr = log_prior(v, spec.ls_prior)
        lp += pr
        gprior_ls[c] = dpr
        for e in range(d):
            if count == 1 or e == c:
                ls[e] = v
    outputscale, dos, gprior_os = spec.fixed_outputscale, 0.0, 0.0
    if spec.os_index >= 0:
        outputscale, dos = softplus(x[spec.os_index])
        outputscale += spec.os_lower
        pr, gprior_os = log_prior(outputscale, spec.os_prior)
        lp += pr
    value, gls, gos, status = mode_and_evidence(X, ans, spec.kernel, ls, outputscale, state, tol, max_iter)
    grad = np.zeros(x.shape[0])
    if status != OK:
        return 0.0, grad, status
    for c in range(count):
        total = gls.sum() if count == 1 else gls[c]
        grad[spec.ls_start + c] = -(total + gprior_ls[c]) * dls[c]
    if spec.os_index >= 0:
        grad[spec.os_index] = -(gos + gprior_os) * dos
    return -(value + lp), grad, OK


@njit(cache=True)
def two_loop(g, S, Y, rho, count, head):
    """The L-BFGS product ``H g`` from the last ``count`` pairs ``(s, y)`` (ring buffer ending at ``head``)."""
    q = g.copy()
    m = S.shape[0]
    alpha = np.zeros(m)
    for back in range(count):
        i = (head - 1 - back) % m
        alpha[i] = rho[i] * (S[i] @ q)
        q -= alpha[i] * Y[i]
    if count:
        last = (head - 1) % m
        q *= (S[last] @ Y[last]) / (Y[last] @ Y[last])
    for fwd in range(count):
        i = (head - count + fwd) % m
        beta = rho[i] * (Y[i] @ q)
        q += (alpha[i] - beta) * S[i]
    return q


@njit(cache=True)
def wolfe_search(x, fx, gx, d, t, X, ans, spec, state, tol, max_iter):
    """A step along ``d`` satisfying the strong Wolfe conditions with L-BFGS-B's constants
    (sufficient decrease ``1e-3``, curvature ``0.9``), bracketed by bisection and extended by
    doubling: ``(x, loss, grad, status)``; :data:`LINE_SEARCH_FAILED` after 60 trials. On success
    the last evaluation was at the returned point (``state`` holds its mode)."""
    gd = gx @ d
    lo, hi = 0.0, np.inf
    for _ in range(60):
        xn = x + t * d
        fn, gn, status = fit_loss(xn, X, ans, spec, state, tol, max_iter)
        if status != OK:
            return x, fx, gx, status
        gnd = gn @ d
        if not fn <= fx + 1e-3 * t * gd or gnd > -0.9 * gd:
            hi = t  # not enough decrease, or past the minimum along d
        elif gnd < 0.9 * gd:
            lo = t  # still descending steeply: a longer step
        else:
            return xn, fn, gn, OK
        t = 0.5 * (lo + hi) if hi < np.inf else 2.0 * t
    return x, fx, gx, LINE_SEARCH_FAILED


@njit(cache=True)
def fit_lbfgs(x0, X, ans, spec, state, tol, max_iter):
    """The whole fit in one call: L-BFGS on :func:`fit_loss` from the raw parameters ``x0``, with
    SciPy's L-BFGS-B stopping rules, defaults, first step (unit length along the gradient) and
    line-search constants (unbounded, as BoTorch's softplus-constrained parameters are; the line
    search brackets by bisection where L-BFGS-B's interpolates): ``(x, loss, status, iterations)``.
    On success ``state`` holds the mode and factors at the returned ``x``."""
    k = x0.shape[0]
    x = x0.copy()
    fx, gx, status = fit_loss(x, X, ans, spec, state, tol, max_iter)
    if status != OK:
        return x, fx, status, 0
    S, Y = np.zeros((LBFGS_MEMORY, k)), np.zeros((LBFGS_MEMORY, k))
    rho = np.zeros(LBFGS_MEMORY)
    count, head = 0, 0
    for it in range(LBFGS_MAXITER):
        if np.max(np.abs(gx)) <= LBFGS_GTOL:
            return x, fx, OK, it
        d = -two_loop(gx, S, Y, rho, count, head)
        if not gx @ d < 0.0:
            d, count = -gx, 0
        t = 1.0 if count else 1.0 / math.sqrt(d @ d)  # L-BFGS-B's first step: unit length
        xn, fn, gn, status = wolfe_search(x, fx, gx, d, t, X, ans, spec, state, tol, max_iter)
        if status != OK:
            return x, fx, status, it
        sv, yv = xn - x, gn - gx
        sy = sv @ yv
        if sy > 2.220446049250313e-16 * (yv @ yv):
            S[head], Y[head], rho[head] = sv, yv, 1.0 / sy
            head = (head + 1) % LBFGS_MEMORY
            count = min(count + 1, LBFGS_MEMORY)
        done = (fx - fn) <= LBFGS_FTOL * max(abs(fx), abs(fn), 1.0)
        x, fx, gx = xn, fn, gn
        if done:
            return x, fx, OK, it + 1
    return x, fx, OK, LBFGS_MAXITER
