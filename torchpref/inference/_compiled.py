r"""The compiled small-problem path (issue 33): the Laplace mode, evidence and its gradient, and a
whole hyperparameter-fit evaluation, each as one numba-compiled call, for one problem on the CPU in
float64 with probit comparisons (eq. 3).

The torch solver (:mod:`torchpref.inference.newton`, :mod:`torchpref.inference.laplace`) is the
reference: the same Newton iteration (exact ``B = I + L^T W L``, Armijo backtracking, the same
stopping tests; no chord or float32 steps, which the torch solver takes only from ``n = 128`` and
``256``), the same second-order corrected evidence and the same written-out gradient
(:func:`~torchpref.inference.laplace.laplace_evidence`). The stationary kernels of
:func:`kernel_matrix` are GPyTorch's ``RBFKernel`` and ``MaternKernel`` (``nu`` = 1/2, 3/2, 5/2),
ARD or shared lengthscale, times an outputscale.

This module imports numba; nothing imports it at ``import torchpref`` time:
the dispatch (:mod:`torchpref.inference.fast_path`) loads it on the first solve that uses it. Functions are
compiled with ``cache=True`` (numba's on-disk cache beside this file, or in
``NUMBA_CACHE_DIR``), so only the first process ever pays the compilation.

Status codes returned by the compiled calls: :data:`OK`, :data:`NOT_PD` (the kernel matrix is
not positive definite even with the torch solver's largest jitter),
:data:`NOT_FINITE` (a non-finite Newton step or evidence), :data:`NOT_CONVERGED`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from torchpref.inference.step_rule import STEP_RULE

OK, NOT_PD, NOT_FINITE, NOT_CONVERGED = 0, 1, 2, 3
#: kernel kinds: GPyTorch's RBF, and Matern with nu = 1/2, 3/2, 5/2
RBF, MATERN12, MATERN32, MATERN52 = 0, 1, 2, 3
#: prior kinds on a positive hyperparameter
NO_PRIOR, LOG_NORMAL, GAMMA = 0, 1, 2

LOG_2PI_HALF = 0.5 * math.log(2.0 * math.pi)
# the step rule of every Newton loop (numba freezes these module globals when it compiles)
ARMIJO = STEP_RULE.armijo
SHRINK = STEP_RULE.shrink
MIN_STEP = STEP_RULE.min_step
STUCK_TOL = STEP_RULE.stuck_tol
ROUNDOFF = 100.0 * 2.220446049250313e-16  # ROUNDOFF_EPS eps (float64)


@njit(cache=True)
def log_cdf_mills(z):
    """``(log Phi(z), phi(z) / Phi(z))``, accurate in both tails."""
    if z >= 0.0:
        q = 0.5 * math.erfc(z / math.sqrt(2.0))
        return math.log1p(-q), math.exp(-0.5 * z * z - LOG_2PI_HALF) / (1.0 - q)
    if z > -20.0:
        p = 0.5 * math.erfc(-z / math.sqrt(2.0))
        return math.log(p), math.exp(-0.5 * z * z - LOG_2PI_HALF) / p
    x = -z  # the Mills ratio (1 - Phi(x)) / phi(x) by its continued fraction
    t = x
    for k in range(60, 0, -1):
        t = x + k / t
    mills = 1.0 / t
    return -0.5 * z * z - LOG_2PI_HALF + math.log(mills), 1.0 / mills


@njit(cache=True)
def probit(eta, s):
    """``(log p, d log p / d eta, w = -d^2 log p / d eta^2, d w / d eta)`` of ``Phi(eta / s)``."""
    z = eta / s
    lp, r = log_cdf_mills(z)
    zr = z + r
    return lp, r / s, r * zr / (s * s), r * (1.0 - zr * (z + 2.0 * r)) / (s * s * s)


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
def cholesky(A):
    """``(L, ok)``: the lower Cholesky factor of ``A``, ``ok`` false where it is not positive definite."""
    try:
        return np.linalg.cholesky(A), True
    except Exception:  # numba's LinAlgError
        return np.zeros_like(A), False


@njit(cache=True)
def solve_lower(L, b):
    """``L^-1 b`` for lower-triangular ``L`` and a vector ``b``."""
    n = b.shape[0]
    x = np.empty(n)
    for i in range(n):
        acc = b[i]
        for j in range(i):
            acc -= L[i, j] * x[j]
        x[i] = acc / L[i, i]
    return x


@njit(cache=True)
def solve_lower_t(L, b):
    """``L^-T b`` for lower-triangular ``L`` and a vector ``b``."""
    n = b.shape[0]
    x = np.empty(n)
    for i in range(n - 1, -1, -1):
        acc = b[i]
        for j in range(i + 1, n):
            acc -= L[j, i] * x[j]
        x[i] = acc / L[i, i]
    return x


@njit(cache=True)
def chol_solve(M, b):
    """``(M M^T)^-1 b``."""
    return solve_lower_t(M, solve_lower(M, b))


@njit(cache=True)
def comparison_terms(f, C, s):
    """``(log p, d log p / d f, weights w, d w / d eta)`` of the comparisons ``C`` (``m x 2``) at ``f``."""
    n, m = f.shape[0], C.shape[0]
    gf = np.zeros(n)
    w = np.empty(m)
    dw = np.empty(m)
    ll = 0.0
    for k in range(m):
        i, j = C[k, 0], C[k, 1]
        lp, d1, wk, dwk = probit(f[i] - f[j], s)
        ll += lp
        gf[i] += d1
        gf[j] -= d1
        w[k] = wk
        dw[k] = dwk
    return ll, gf, w, dw


@njit(cache=True)
def evaluate(L, a, C, s):
    """``(Psi, grad Psi, weights, log p)`` at the whitened point ``a`` for comparisons ``C`` (``m x 2``)."""
    ll, gf, w, _ = comparison_terms(L @ a, C, s)
    grad = L.T @ gf - a
    return ll - 0.5 * (a @ a), grad, w, ll


@njit(cache=True)
def w_times(C, w, A):
    """``W A`` for ``W = sum_k w_k d_k d_k^T`` (``d_k = e_i - e_j``) and ``A`` (``n x k``)."""
    out = np.zeros_like(A)
    for k in range(C.shape[0]):
        i, j = C[k, 0], C[k, 1]
        for c in range(A.shape[1]):
            v = w[k] * (A[i, c] - A[j, c])
            out[i, c] += v
            out[j, c] -= v
    return out


@njit(cache=True)
def hessian(L, C, w):
    """``B = I + L^T W L``."""
    H = L.T @ w_times(C, w, L)
    for i in range(H.shape[0]):
        H[i, i] += 1.0
    return H


@njit(cache=True)
def line_search(L, C, s, a, psi, grad, w, ll, step, dec):
    """Armijo backtracking from ``a`` along ``step``: ``(a, Psi, grad, weights, log p, moved)``."""
    t = 1.0
    while True:
        trial = a + t * step
        psi_t, grad_t, w_t, ll_t = evaluate(L, trial, C, s)
        if np.isfinite(psi_t) and psi_t >= psi + ARMIJO * t * dec:
            return trial, psi_t, grad_t, w_t, ll_t, True
        t *= SHRINK
        if t <= MIN_STEP:
            return a, psi, grad, w, ll, False


@njit(cache=True)
def newton(L, C, s, starts, tol, max_iter):
    """The Laplace mode: ``(a, M, weights, iterations, status, decrement)`` with ``M`` the Cholesky
    factor of ``B`` at ``a`` (:func:`torchpref.inference.newton.newton_mode` for one problem)."""
    n = L.shape[0]
    a = np.zeros(n)
    psi, grad, w, ll = evaluate(L, a, C, s)
    if starts.shape[0]:
        first = True
        for r in range(starts.shape[0]):
            ar = solve_lower(L, starts[r].copy())
            if not np.all(np.isfinite(ar)):
                ar = np.zeros(n)
            pr, gr, wr, lr = evaluate(L, ar, C, s)
            if first or pr > psi:
                a, psi, grad, w, ll = ar, pr, gr, wr, lr
            first = False
    newton_dec = np.inf
    dec = np.inf
    for it in range(1, max_iter + 1):
        M, ok = cholesky(hessian(L, C, w))
        if not ok:
            return a, M, w, it, NOT_FINITE, dec
        step = chol_solve(M, grad)
        dec = grad @ step
        if not np.isfinite(dec):
            return a, M, w, it, NOT_FINITE, dec
        prior = 0.5 * (a @ a)
        stalled = dec > 0.25 * newton_dec and dec / 2 < ROUNDOFF * (abs(psi + prior) + prior)
        newton_dec = dec
        if dec / 2 < tol or stalled:
            return a, M, w, it, OK, dec
        a, psi, grad, w, ll, moved = line_search(L, C, s, a, psi, grad, w, ll, step, dec)
        if not moved:
            M, ok = cholesky(hessian(L, C, w))
            floor = ROUNDOFF * (abs(psi + prior) + prior)
            return a, M, w, it, (OK if dec / 2 < max(floor, STUCK_TOL) else NOT_CONVERGED), dec
    M, ok = cholesky(hessian(L, C, w))
    return a, M, w, max_iter, NOT_CONVERGED, dec


@njit(cache=True)
def w_dense(C, w, n):
    """``W`` (``n x n``) densely."""
    W = np.zeros((n, n))
    for k in range(C.shape[0]):
        i, j = C[k, 0], C[k, 1]
        W[i, i] += w[k]
        W[j, j] += w[k]
        W[i, j] -= w[k]
        W[j, i] -= w[k]
    return W


@njit(cache=True)
def evidence(L, C, s, a, M, w):
    r"""``(log q, G)``: the second-order corrected Laplace evidence at the mode ``a`` and its
    gradient in ``K``, ``G = (alpha alpha^T - (W - W Sigma W) - (I - W Sigma) h alpha^T) / 2``
    (:func:`torchpref.inference.laplace.laplace_evidence`)."""
    n, m = L.shape[0], C.shape[0]
    ll, g, _, dw = comparison_terms(L @ a, C, s)
    V = np.linalg.solve(M, np.ascontiguousarray(L.T))  # M^-1 L^T: Sigma = V^T V
    Sigma = V.T @ V
    h = np.zeros(n)
    for k in range(m):
        i, j = C[k, 0], C[k, 1]
        v = dw[k] * (Sigma[i, i] + Sigma[j, j] - 2.0 * Sigma[i, j])
        h[i] += v
        h[j] -= v
    Sigma_h = Sigma @ h
    WS = w_times(C, w, Sigma)
    WSW = w_times(C, w, np.ascontiguousarray(WS.T))
    b = h - w_times(C, w, Sigma_h.reshape(n, 1))[:, 0]
    alpha = solve_lower_t(L, a)
    W = w_dense(C, w, n)
    G = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            G[i, j] = 0.5 * (alpha[i] * alpha[j] - W[i, j] + WSW[i, j] - b[i] * alpha[j])
    grad_a = L.T @ g - a
    step = chol_solve(M, grad_a)
    logdet = 0.0
    for i in range(n):
        logdet += math.log(M[i, i])
    value = ll - 0.5 * (a @ a) - logdet + 0.5 * (grad_a @ step) - 0.5 * (h @ (L @ step))
    return value, G


@njit(cache=True)
def jittered_cholesky(K):
    """``(L, ok)`` with ``L L^T = K + j I`` for the first ``j`` of the torch solver's float64
    schedule that works (:func:`torchpref.inference.numerics.jitter_schedule`: 0, then ``1e-10``
    to ``1e-6`` of the mean diagonal, tenfold)."""
    L, ok = cholesky(K)
    if ok:
        return L, ok
    n = K.shape[0]
    scale = np.trace(K) / n
    if not (np.isfinite(scale) and scale > 0.0):
        scale = 1.0
    for e in range(-10, -5):
        Kj = K.copy()
        for i in range(n):
            Kj[i, i] += scale * 10.0**e
        L, ok = cholesky(Kj)
        if ok:
            return L, ok
    return L, False


@njit(cache=True)
def mode_and_evidence(X, C, s, kind, ls, outputscale, f_prev, tol, max_iter):
    """One fit evaluation: ``(log q, d log q / d ls, d log q / d outputscale, mode f, status)``,
    Newton warm-started from ``f_prev`` (``n``; a row of zeros-length ``0``: cold), cold if that fails."""
    n = X.shape[0]
    K = kernel_matrix(X, ls, outputscale, kind)
    L, ok = jittered_cholesky(K)
    if not ok:
        return 0.0, np.zeros(ls.shape[0]), 0.0, np.zeros(n), NOT_PD
    starts = f_prev.reshape(1, f_prev.shape[0]) if f_prev.shape[0] == n else np.empty((0, n))
    a, M, w, _, status, _ = newton(L, C, s, starts, tol, max_iter)
    if status == NOT_FINITE and starts.shape[0]:
        a, M, w, _, status, _ = newton(L, C, s, np.empty((0, n)), tol, max_iter)
    if status != OK:
        return 0.0, np.zeros(ls.shape[0]), 0.0, np.zeros(n), status
    value, G = evidence(L, C, s, a, M, w)
    if not np.isfinite(value):
        return 0.0, np.zeros(ls.shape[0]), 0.0, np.zeros(n), NOT_FINITE
    gls, gos = kernel_gradient(X, ls, outputscale, kind, G)
    return value, gls, gos, L @ a, OK


@njit(cache=True)
def softplus(x):
    """torch's ``softplus`` (threshold 20) and its derivative."""
    if x > 20.0:
        return x, 1.0
    return math.log1p(math.exp(x)), 1.0 / (1.0 + math.exp(-x))


@njit(cache=True)
def log_prior(x, kind, p1, p2, const):
    """``(log density, its derivative)`` at ``x > 0`` of a LogNormal(``p1``, ``p2``) or
    Gamma(concentration ``p1``, rate ``p2``) prior (0 for none), whose constant part is ``const``
    (``-log p2 - log(2 pi) / 2``, ``p1 log p2 - lgamma(p1)``: computed by the prior itself, in its
    own dtype, as GPyTorch's float32 prior parameters give it)."""
    if kind == LOG_NORMAL:
        lx = math.log(x)
        z = (lx - p1) / p2
        return const - lx - 0.5 * z * z, (-1.0 - z / p2) / x
    if kind == GAMMA:
        return const + (p1 - 1.0) * math.log(x) - p2 * x, (p1 - 1.0) / x - p2
    return 0.0, 0.0


@njit(cache=True)
def fit_loss(x, X, C, s, kind, spec, f_prev, tol, max_iter):
    """BoTorch's loss ``-(log q + log priors)`` and its gradient in the raw parameters ``x``.

    ``spec`` (floats): ``[ls_start, ls_count, os_index, ls_lower, os_lower, ls_prior kind, p1, p2,
    os_prior kind, p1, p2, fixed outputscale, ls_prior const, os_prior const]`` (:func:`log_prior`): the lengthscales are ``softplus(x[ls_start :
    ls_start + ls_count]) + ls_lower`` (one shared value when ``ls_count = 1``), the outputscale
    ``softplus(x[os_index]) + os_lower`` (the fixed value where ``os_index < 0``). ``f_prev`` is
    overwritten with the new mode (the next call's warm start). Returns ``(loss, grad, status)``."""
    d = X.shape[1]
    start, count, os_index = int(spec[0]), int(spec[1]), int(spec[2])
    ls = np.empty(d)
    dls = np.empty(count)
    lp = 0.0
    gprior_ls = np.zeros(count)
    for c in range(count):
        v, dv = softplus(x[start + c])
        v += spec[3]
        dls[c] = dv
        pr, dpr = log_prior(v, int(spec[5]), spec[6], spec[7], spec[12])
        lp += pr
        gprior_ls[c] = dpr
        for e in range(d):
            if count == 1 or e == c:
                ls[e] = v
    outputscale, dos, gprior_os = spec[11], 0.0, 0.0
    if os_index >= 0:
        outputscale, dos = softplus(x[os_index])
        outputscale += spec[4]
        pr, gprior_os = log_prior(outputscale, int(spec[8]), spec[9], spec[10], spec[13])
        lp += pr
    value, gls, gos, f, status = mode_and_evidence(X, C, s, kind, ls, outputscale, f_prev, tol, max_iter)
    grad = np.zeros(x.shape[0])
    if status != OK:
        return 0.0, grad, status
    if f_prev.shape[0] == f.shape[0]:
        f_prev[:] = f
    for c in range(count):
        total = gls.sum() if count == 1 else gls[c]
        grad[start + c] = -(total + gprior_ls[c]) * dls[c]
    if os_index >= 0:
        grad[os_index] = -(gos + gprior_os) * dos
    return -(value + lp), grad, OK


LINE_SEARCH_FAILED = 4
#: SciPy's L-BFGS-B defaults, which BoTorch's fit uses: memory, ``ftol``, ``gtol``, iteration limit
LBFGS_MEMORY, LBFGS_FTOL, LBFGS_GTOL, LBFGS_MAXITER = 10, 2.220446049250313e-09, 1e-5, 15000


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
def wolfe_search(x, fx, gx, d, t, X, C, s, kind, spec, f_prev, tol, max_iter):
    """A step along ``d`` satisfying the strong Wolfe conditions with L-BFGS-B's constants
    (sufficient decrease ``1e-3``, curvature ``0.9``), bracketed by bisection and extended by
    doubling: ``(x, loss, grad, status)``; :data:`LINE_SEARCH_FAILED` after 60 trials."""
    gd = gx @ d
    lo, hi = 0.0, np.inf
    for _ in range(60):
        xn = x + t * d
        fn, gn, status = fit_loss(xn, X, C, s, kind, spec, f_prev, tol, max_iter)
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
def fit_lbfgs(x0, X, C, s, kind, spec, f_prev, tol, max_iter):
    """The whole fit in one call: L-BFGS on :func:`fit_loss` from the raw parameters ``x0``, with
    SciPy's L-BFGS-B stopping rules, defaults, first step (unit length along the gradient) and
    line-search constants (unbounded, as BoTorch's softplus-constrained parameters are; the line
    search brackets by bisection where L-BFGS-B's interpolates): ``(x, loss, status, iterations)``."""
    k = x0.shape[0]
    x = x0.copy()
    fx, gx, status = fit_loss(x, X, C, s, kind, spec, f_prev, tol, max_iter)
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
        xn, fn, gn, status = wolfe_search(x, fx, gx, d, t, X, C, s, kind, spec, f_prev, tol, max_iter)
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
