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
    SIGMOID,
    STALLED,
    WEAK_STEP,
    Answers,
)

#: SciPy's L-BFGS-B defaults, which BoTorch's fit uses: memory, ``ftol``, ``gtol``, iteration limit
LBFGS_MEMORY, LBFGS_FTOL, LBFGS_GTOL, LBFGS_MAXITER = 10, 2.220446049250313e-09, 1e-5, 15000
#: L-BFGS-B's strong Wolfe constants (``dcsrch``'s ``ftol`` and ``gtol``), its relative bracket
#: width at which a line search stops (``xtol``), and the trials one search may take
WOLFE_DECREASE, WOLFE_CURVATURE, LINE_SEARCH_XTOL, LINE_SEARCH_TRIALS = 1e-3, 0.9, 0.1, 20


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
    """One fit evaluation: ``(log q, d log q / d ls, d log q / d outputscale, d log q / d nu, status)``, Newton
    warm-started from ``state.f`` (:func:`~torchpref.inference._compiled.newton` retries cold if that fails); on success ``state`` holds the new mode and factors."""
    n = X.shape[0]
    K = kernel_matrix(X, ls, outputscale, kind)
    L, jitter, ok = jittered_cholesky(K)
    if not ok:
        return 0.0, np.zeros(ls.shape[0]), 0.0, 0.0, NOT_PD
    starts = state.f.reshape(1, state.f.shape[0]) if state.f.shape[0] == n else np.empty((0, n))
    a, M, w, its, status, _ = newton(L, ans, starts, tol, max_iter)  # retried cold if the warm start fails
    if status != OK:
        return 0.0, np.zeros(ls.shape[0]), 0.0, 0.0, status
    value, G, gnu = evidence(L, ans, a, M, w)
    if not (np.isfinite(value) and np.isfinite(gnu)):
        return 0.0, np.zeros(ls.shape[0]), 0.0, 0.0, NOT_FINITE
    gls, gos = kernel_gradient(X, ls, outputscale, kind, G)
    if state.f.shape[0] == n:
        state.f[:] = L @ a
        state.a[:] = a
        state.L[:, :] = L
        state.M[:, :] = M
        state.w[:] = w
        state.jitter[0] = jitter
        state.iterations[0] = its
    return value, gls, gos, gnu, OK


@njit(cache=True)
def softplus(x):
    """torch's ``softplus`` (threshold 20) and its derivative."""
    if x > 20.0:
        return x, 1.0
    return math.log1p(math.exp(x)), 1.0 / (1.0 + math.exp(-x))


@njit(cache=True)
def constrained(x, transform, lower, upper):
    """GPyTorch's constraint of a raw value and its derivative: ``softplus(x) + lower``
    (:data:`SOFTPLUS`, ``GreaterThan``) or ``lower + (upper - lower) sigmoid(x)`` (:data:`SIGMOID`, ``Interval``)."""
    if transform == SIGMOID:
        sig = 1.0 / (1.0 + math.exp(-x))
        return lower + (upper - lower) * sig, (upper - lower) * sig * (1.0 - sig)
    v, dv = softplus(x)
    return v + lower, dv


@njit(cache=True)
def with_precision(ans, nu):
    """``ans`` with the Beta ratings' precision ``nu``."""
    return Answers(
        ans.first,
        ans.second,
        ans.kind,
        ans.offset,
        ans.target,
        ans.scale,
        ans.lower,
        ans.upper,
        ans.lapse,
        ans.rating_scale,
        nu,
    )


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
    nu, dnu = ans.rating_precision, 0.0
    if spec.nu_index >= 0:
        nu, dnu = constrained(x[spec.nu_index], spec.nu_transform, spec.nu_lower, spec.nu_upper)
        ans = with_precision(ans, nu)
    pr, gprior_nu = log_prior(nu, spec.nu_prior)  # a fixed precision's prior too: BoTorch's loss has it
    lp += pr
    value, gls, gos, gnu, status = mode_and_evidence(X, ans, spec.kernel, ls, outputscale, state, tol, max_iter)
    grad = np.zeros(x.shape[0])
    if status != OK:
        return 0.0, grad, status
    for c in range(count):
        total = gls.sum() if count == 1 else gls[c]
        grad[spec.ls_start + c] = -(total + gprior_ls[c]) * dls[c]
    if spec.os_index >= 0:
        grad[spec.os_index] = -(gos + gprior_os) * dos
    if spec.nu_index >= 0:
        grad[spec.nu_index] = -(gnu + gprior_nu) * dnu
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
def cubic_step(lo, f_lo, g_lo, hi, f_hi, g_hi):
    """The minimiser of the cubic through ``(lo, f_lo, g_lo)`` and ``(hi, f_hi, g_hi)`` (derivatives
    along the search direction), safeguarded into the middle 80% of the interval (its midpoint where
    the cubic has no minimiser there or a value is not finite): Nocedal & Wright's eq. 3.59."""
    width = hi - lo
    mid = lo + 0.5 * width
    if not (np.isfinite(f_hi) and np.isfinite(g_hi)):
        return mid
    d1 = g_lo + g_hi - 3.0 * (f_lo - f_hi) / (lo - hi)
    disc = d1 * d1 - g_lo * g_hi
    if not disc >= 0.0:
        return mid
    d2 = math.copysign(math.sqrt(disc), hi - lo)
    denom = g_hi - g_lo + 2.0 * d2
    if denom == 0.0 or not np.isfinite(denom):
        return mid
    t = hi - (hi - lo) * (g_hi + d2 - d1) / denom
    a, b = min(lo, hi), max(lo, hi)
    margin = 0.1 * (b - a)
    if not np.isfinite(t):
        return mid
    return min(max(t, a + margin), b - margin)


@njit(cache=True)
def wolfe_search(x, fx, gx, d, t, floor, X, ans, spec, state, tol, max_iter):
    """A step along the descent direction ``d`` from ``x`` with L-BFGS-B's strong Wolfe constants
    (sufficient decrease :data:`WOLFE_DECREASE`, curvature :data:`WOLFE_CURVATURE`): Nocedal &
    Wright's bracketing (algorithm 3.5: longer steps while the loss still falls steeply) and zoom
    (algorithm 3.6: safeguarded cubic interpolation inside the bracket). A trial whose evaluation
    fails (a kernel matrix not positive definite, a mode that does not converge) counts as too
    long a step. Before any trial has decreased the loss enough, the search gives up once the decrease
    it predicts, ``-t grad^T d``, is below ``floor`` (L-BFGS-B's ``ftol`` scaled by the loss: less than
    the fit counts as progress, and of the order of the loss's noise from the mode's tolerance).
    Returns ``(x, loss, grad, status, evaluations)``:

    * :data:`OK`: the strong Wolfe conditions hold at the returned point;
    * :data:`WEAK_STEP`: the bracket shrank to round-off or the trials ran out, and the returned
      point is the trial of lowest loss with sufficient decrease (as MINPACK-2's ``dcsrch``, which
      L-BFGS-B accepts with a warning);
    * :data:`LINE_SEARCH_FAILED`: no trial decreased the loss enough; ``x`` is returned.

    ``state`` holds the mode of the last successful evaluation, not necessarily the returned point's.
    """
    gd = gx @ d
    lo, f_lo, g_lo = 0.0, fx, gd  # the best trial with sufficient decrease (0: none yet)
    x_lo, gx_lo = x, gx
    hi, f_hi, g_hi = np.inf, np.inf, np.inf
    evaluations = 0
    for _ in range(LINE_SEARCH_TRIALS):
        evaluations += 1
        xn = x + t * d
        fn, gn, status = fit_loss(xn, X, ans, spec, state, tol, max_iter)
        gnd = gn @ d
        if status != OK or not np.isfinite(fn):
            hi, f_hi, g_hi = t, np.inf, np.inf  # too far: the evaluation failed
        elif fn > fx + WOLFE_DECREASE * t * gd or fn >= f_lo:
            hi, f_hi, g_hi = t, fn, gnd  # not enough decrease: the minimiser is short of t
        elif abs(gnd) <= -WOLFE_CURVATURE * gd:
            return xn, fn, gn, OK, evaluations
        elif gnd * (hi - lo) >= 0.0 if hi < np.inf else gnd >= 0.0:
            # past a minimiser: it lies between t and the old best
            hi, f_hi, g_hi = lo, f_lo, g_lo
            lo, f_lo, g_lo, x_lo, gx_lo = t, fn, gnd, xn, gn
        else:
            lo, f_lo, g_lo, x_lo, gx_lo = t, fn, gnd, xn, gn  # still descending: keep it, go on
        if hi == np.inf:
            t = 4.0 * t  # no bracket yet: a longer step
            continue
        if lo == 0.0 and -hi * gd <= floor:
            break  # no step of a decrease the fit could tell from noise
        if abs(hi - lo) <= LINE_SEARCH_XTOL * max(abs(lo), abs(hi)):
            break  # the bracket is down to round-off
        t = cubic_step(lo, f_lo, g_lo, hi, f_hi, g_hi)
    if lo > 0.0:
        return x_lo, f_lo, gx_lo, WEAK_STEP, evaluations
    return x, fx, gx, LINE_SEARCH_FAILED, evaluations


@njit(cache=True)
def fit_lbfgs(x0, X, ans, spec, state, tol, max_iter):
    """The whole fit in one call: L-BFGS on :func:`fit_loss` from the raw parameters ``x0``, with
    SciPy's L-BFGS-B stopping rules, defaults, first step (unit length along the gradient) and
    line-search constants (unbounded, as BoTorch's softplus-constrained parameters are): ``(x,
    loss, status, iterations, evaluations)`` (:class:`~torchpref.inference.fast_types.FitResult`).

    A line search that ends on a weak step (:data:`WEAK_STEP`) is accepted, as L-BFGS-B accepts
    ``dcsrch``'s warnings. Where one finds no step at all, the fit has converged if the decrease the
    direction predicts, ``-grad^T d``, is below ``ftol`` times the loss (the loss near its minimum
    is noisy at about the mode's tolerance, and a step of that gain would meet the ``ftol`` stopping
    rule anyway); otherwise the search is retried along the steepest descent with the memory
    cleared, as L-BFGS-B does, and if that fails too the fit stops at the last good point with
    :data:`STALLED` (L-BFGS-B's ``ABNORMAL_TERMINATION_IN_LNSRCH``). A failure of the first
    evaluation is returned as its status. On success ``state`` holds the mode and factors at the
    returned ``x`` (re-evaluated there where the last evaluation was elsewhere)."""
    k = x0.shape[0]
    x = x0.copy()
    fx, gx, status = fit_loss(x, X, ans, spec, state, tol, max_iter)
    evaluations = 1
    if status != OK:
        return x, fx, status, 0, evaluations
    S, Y = np.zeros((LBFGS_MEMORY, k)), np.zeros((LBFGS_MEMORY, k))
    rho = np.zeros(LBFGS_MEMORY)
    count, head = 0, 0
    synced = True  # state holds the mode at x
    stop, iterations = OK, LBFGS_MAXITER
    for it in range(LBFGS_MAXITER):
        if np.max(np.abs(gx)) <= LBFGS_GTOL:
            stop, iterations = OK, it
            break
        d = -two_loop(gx, S, Y, rho, count, head)
        if not gx @ d < 0.0:
            d, count = -gx, 0
        t = 1.0 if count else 1.0 / math.sqrt(d @ d)  # L-BFGS-B's first step: unit length
        floor = LBFGS_FTOL * max(abs(fx), 1.0)
        xn, fn, gn, status, used = wolfe_search(x, fx, gx, d, t, floor, X, ans, spec, state, tol, max_iter)
        evaluations += used
        if status == LINE_SEARCH_FAILED and -(gx @ d) > floor and count:
            count = 0  # as L-BFGS-B: forget the memory, retry along the steepest descent
            d = -gx
            t = 1.0 / math.sqrt(d @ d)
            xn, fn, gn, status, used = wolfe_search(x, fx, gx, d, t, floor, X, ans, spec, state, tol, max_iter)
            evaluations += used
        if status == LINE_SEARCH_FAILED:
            synced = False  # the trials moved state's mode away from x
            stop, iterations = (OK if -(gx @ d) <= floor else STALLED), it
            break
        sv, yv = xn - x, gn - gx
        sy = sv @ yv
        if sy > 2.220446049250313e-16 * (yv @ yv):
            S[head], Y[head], rho[head] = sv, yv, 1.0 / sy
            head = (head + 1) % LBFGS_MEMORY
            count = min(count + 1, LBFGS_MEMORY)
        done = (fx - fn) <= LBFGS_FTOL * max(abs(fx), abs(fn), 1.0)
        x, fx, gx = xn, fn, gn
        synced = status == OK
        if done:
            stop, iterations = OK, it + 1
            break
    if not synced:
        fx, gx, status = fit_loss(x, X, ans, spec, state, tol, max_iter)
        evaluations += 1
        if status != OK:
            return x, fx, status, iterations, evaluations
    return x, fx, stop, iterations, evaluations
