r"""The compiled small-problem path (issues 33 and 42): the Laplace mode and the second-order
corrected evidence with its gradient in ``K``, for one problem on the CPU in float64, with probit
comparisons (eq. 3; strict choices where ties were offered), Beta ratings (eqs. 4-7; a person's gain
and offset on the link), ties and ordinal levels (Gaussian intervals) and comparisons with lapses,
each optionally shifted by a prior mean's offset (a population's person model). The hyperparameter fit built on them is
:mod:`torchpref.inference._compiled_fit`.

The torch solver (:mod:`torchpref.inference.newton`, :mod:`torchpref.inference.laplace`) is the
reference: the same Newton iteration (exact ``B = I + L^T W L``, Fisher weights for the Beta ratings
where that ``B`` is not positive definite, Armijo backtracking, the same stopping tests; no chord or
float32 steps, which the torch solver takes only from ``n = 128`` and ``256``), the same
second-order corrected evidence and the same written-out gradient
(:func:`~torchpref.inference.laplace.laplace_evidence`).

The observations cross the boundary as one named structure,
:class:`~torchpref.inference.fast_types.Answers` (one row per comparison or rating).

This module imports numba; nothing imports it at ``import torchpref`` time, and nothing compiles
it but an explicit build (:mod:`torchpref.inference.fast_cache`: ``torchpref fast-path build``).

Status codes returned by the compiled calls: :data:`OK`, :data:`NOT_PD` (the kernel matrix is
not positive definite even with the torch solver's largest jitter, or Fisher scoring's ``B`` is
not), :data:`NOT_FINITE` (a non-finite Newton step or evidence), :data:`NOT_CONVERGED`,
:data:`FISHER` (the final factor needed Fisher weights: the torch solver answers, with its warning).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from torchpref.inference.fast_types import BETA, FISHER, INTERVAL, LAPSE, NOT_CONVERGED, NOT_FINITE, NOT_PD, OK, PROBIT
from torchpref.inference.step_rule import STEP_RULE

BELOW_ZERO = 6  # internal: a converged point below Psi(0), which no mode is (retried from zeros)

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
def polygammas(x):
    """``(psi(x), psi'(x), psi''(x))`` for ``x >= 1``: the recurrences up to ``x >= 10``, then the
    asymptotic series (Abramowitz & Stegun 6.3.18, 6.4.11-12), to about ``1e-16`` relative."""
    p0, p1, p2 = 0.0, 0.0, 0.0
    while x < 10.0:
        p0 -= 1.0 / x
        p1 += 1.0 / (x * x)
        p2 -= 2.0 / (x * x * x)
        x += 1.0
    v = 1.0 / (x * x)
    p0 += math.log(x) - 0.5 / x
    p0 -= v * (1 / 12 - v * (1 / 120 - v * (1 / 252 - v * (1 / 240 - v * (1 / 132 - v * (691 / 32760 - v / 12))))))
    s1 = 1 / 6 - v * (1 / 30 - v * (1 / 42 - v * (1 / 30 - v * (5 / 66 - v * (691 / 2730 - v * 7 / 6)))))
    p1 += 1.0 / x + 0.5 * v + s1 * v / x
    s2 = 0.5 - v * (1 / 6 - v * (1 / 6 - v * (3 / 10 - v * (5 / 6 - v * (691 / 210 - v * 35 / 2)))))
    p2 += -v - v / x - s2 * v * v
    return p0, p1, p2


@njit(cache=True)
def beta_rating(eta, u, c, nu):
    """``(log p, l', w = -l'', -l''', Fisher weight)`` of a rating ``u ~ Beta(nu mu, nu (1 - mu))``,
    ``mu = Phi(eta / c)``, written as :class:`~torchpref.likelihoods.pairwise_beta.BetaRatingLikelihood`
    writes them (finite where ``mu`` rounds to 0 or 1)."""
    t = eta / c
    log_mu, mills_a = log_cdf_mills(t)
    log_1mmu, mills_b = log_cdf_mills(-t)
    a, b = nu * math.exp(log_mu), nu * math.exp(log_1mmu)
    r_a, r_b = mills_a / c, mills_b / c
    dmu = math.exp(-0.5 * t * t - LOG_2PI_HALF) / c
    lu, l1u = math.log(u), math.log1p(-u)
    lp = (a - 1.0) * lu + (b - 1.0) * l1u + math.lgamma(nu) - math.lgamma(a + 1.0) - math.lgamma(b + 1.0)
    lp += 2.0 * math.log(nu) + log_mu + log_1mmu
    pa0, pa1, pa2 = polygammas(a + 1.0)
    pb0, pb1, pb2 = polygammas(b + 1.0)
    g = nu * (lu - l1u - pa0 + pb0) * dmu + r_a - r_b
    F = r_a * r_a + r_b * r_b + nu * nu * (pa1 + pb1) * dmu * dmu
    l3 = -(nu**3) * (pa2 - pb2) * dmu**3 + 2.0 * r_a**3 - 2.0 * r_b**3
    third = l3 + 3.0 * F * t / c + g * (t * t - 1.0) / (c * c)
    return lp, g, F + t * g / c, -third, F


@njit(cache=True)
def beta_rating_dnu(eta, u, c, nu):
    """``(d log p / d nu, d l' / d nu, d w / d nu)`` of :func:`beta_rating` (``w = -l''``): with
    ``a = nu mu``, ``b = nu (1 - mu)`` and ``psi(x) = psi(x + 1) - 1 / x`` as there,
    ``d log p / d nu = mu log u + (1 - mu) log(1 - u) + psi(nu) - mu psi(a + 1) - (1 - mu) psi(b + 1) + 2 / nu``,
    ``d l' / d nu = (log u - log(1 - u) - psi(a + 1) + psi(b + 1) - nu (mu psi'(a + 1) - (1 - mu) psi'(b + 1))) mu'``
    and ``d w / d nu = dF / d nu + t / c d l' / d nu`` with
    ``dF / d nu = (2 nu (psi'(a + 1) + psi'(b + 1)) + nu^2 (mu psi''(a + 1) + (1 - mu) psi''(b + 1))) mu'^2``."""
    t = eta / c
    log_mu = log_cdf_mills(t)[0]
    log_1mmu = log_cdf_mills(-t)[0]
    mu, nmu = math.exp(log_mu), math.exp(log_1mmu)
    dmu = math.exp(-0.5 * t * t - LOG_2PI_HALF) / c
    lu, l1u = math.log(u), math.log1p(-u)
    pa0, pa1, pa2 = polygammas(nu * mu + 1.0)
    pb0, pb1, pb2 = polygammas(nu * nmu + 1.0)
    pnu = polygammas(nu + 1.0)[0] - 1.0 / nu
    dl = mu * lu + nmu * l1u + pnu - mu * pa0 - nmu * pb0 + 2.0 / nu
    dg = (lu - l1u - pa0 + pb0 - nu * (mu * pa1 - nmu * pb1)) * dmu
    dF = (2.0 * nu * (pa1 + pb1) + nu * nu * (mu * pa2 + nmu * pb2)) * dmu * dmu
    return dl, dg, dF + t * dg / c


@njit(cache=True)
def mills(z):
    """The Mills ratio ``(1 - Phi(z)) / phi(z)`` for ``z >= 0`` (below 8 from ``erfc``, above by
    its continued fraction), so that ``Phi(-z) = phi(z) mills(z)`` keeps tails free of underflow
    (``erfcx(z / sqrt 2) = sqrt(2 / pi) mills(z)``)."""
    if z < 8.0:
        return 0.5 * math.erfc(z / math.sqrt(2.0)) * math.exp(0.5 * z * z + LOG_2PI_HALF)
    t = z
    for k in range(60, 0, -1):
        t = z + k / t
    return 1.0 / t


@njit(cache=True)
def interval(eta, lower, upper, s):
    """``(log P, d log P / d eta, w = -d^2 log P, d w / d eta)`` of ``P = Phi((upper - eta) / s) -
    Phi((lower - eta) / s)`` (``lower`` may be ``-inf``, ``upper`` ``inf``), as
    :func:`torchpref.inference.numerics.normal_interval` computes them: intervals across zero by
    ``erf``, intervals in a tail mirrored below zero and written ``Phi(hi) (1 - Phi(lo) / Phi(hi))``
    with Mills ratios, accurate in both tails. Log-concave: ``w >= 0``."""
    a_inf, b_inf = upper == np.inf, lower == -np.inf
    a = 0.0 if a_inf else (upper - eta) / s
    b = 0.0 if b_inf else (lower - eta) / s
    mirror = (not b_inf) and b > 0.0
    hi, hi_inf = (-b, b_inf) if mirror else (a, a_inf)
    lo, lo_inf = (-a, a_inf) if mirror else (b, b_inf)
    if hi_inf or hi > 0.0:  # across zero
        ea = 1.0 if a_inf else math.erf(a / math.sqrt(2.0))
        eb = -1.0 if b_inf else math.erf(b / math.sqrt(2.0))
        log_p = math.log(0.5 * (ea - eb))
        r_a = 0.0 if a_inf else math.exp(-0.5 * a * a - LOG_2PI_HALF - log_p)
        r_b = 0.0 if b_inf else math.exp(-0.5 * b * b - LOG_2PI_HALF - log_p)
    else:  # in the lower tail (after mirroring): Phi(hi) (1 - q), q = Phi(lo) / Phi(hi)
        m_hi = mills(-hi)
        e, q = 0.0, 0.0
        if not lo_inf:
            lo = min(lo, hi - 1e-300)
            e = math.exp(-0.5 * (lo - hi) * (lo + hi))  # phi(lo) / phi(hi)
            q = e * mills(-lo) / m_hi
        log_p = -0.5 * hi * hi - LOG_2PI_HALF + math.log(m_hi) + math.log1p(-q)
        r_hi = 1.0 / (m_hi * (1.0 - q))
        r_a, r_b = (e * r_hi, r_hi) if mirror else (r_hi, e * r_hi)
    d1 = (r_b - r_a) / s
    p2 = (b * r_b - a * r_a) / (s * s)  # (d^2 P / d eta^2) / P
    p3 = ((1.0 - a * a) * r_a - (1.0 - b * b) * r_b) / (s * s * s)  # (d^3 P / d eta^3) / P
    d2 = p2 - d1 * d1
    d3 = p3 - 3.0 * d1 * p2 + 2.0 * d1 * d1 * d1
    return log_p, d1, -d2, -d3


@njit(cache=True)
def lapse_probit(eta, s, eps):
    """``(log p, l', w = -l'', d w / d eta, Fisher weight)`` of ``p = eps / 2 + (1 - eps) Phi(eta / s)``
    as :class:`~torchpref.likelihoods.person.LapseProbitLikelihood` writes them (not log-concave:
    its Fisher weight ``l'^2 p / (1 - p)`` where the exact ``B`` is not positive definite)."""
    z = eta / s
    log_keep = math.log1p(-eps)
    log_half_eps = math.log(0.5 * eps)
    log_p = np.logaddexp(log_half_eps, log_keep + log_cdf_mills(z)[0])
    log_1mp = np.logaddexp(log_half_eps, log_keep + log_cdf_mills(-z)[0])
    q = math.exp(log_keep - 0.5 * z * z - LOG_2PI_HALF - log_p)  # (1 - eps) phi(z) / p
    d1 = q / s
    w = (z * q + q * q) / (s * s)
    dw = -((z * z - 1.0) * q + 3.0 * z * q * q + 2.0 * q * q * q) / (s * s * s)
    return log_p, d1, w, dw, d1 * d1 * math.exp(log_p - log_1mp)


@njit(cache=True)
def answer_terms(f, ans):
    """``(log p, d log p / d f, weights w, d w / d eta, Fisher weights)`` of the rows of ``ans`` at ``f``."""
    n, m = f.shape[0], ans.first.shape[0]
    gf = np.zeros(n)
    w, dw, fw = np.empty(m), np.empty(m), np.empty(m)
    ll = 0.0
    for k in range(m):
        i, j = ans.first[k], ans.second[k]
        eta = f[i] + ans.offset[k] - (f[j] if j >= 0 else 0.0)
        kind = ans.kind[k]
        if kind == PROBIT:
            lp, d1, wk, dwk = probit(eta, ans.scale[k])
            fk = wk
        elif kind == INTERVAL:
            lp, d1, wk, dwk = interval(eta, ans.lower[k], ans.upper[k], ans.scale[k])
            fk = wk
        elif kind == LAPSE:
            lp, d1, wk, dwk, fk = lapse_probit(eta, ans.scale[k], ans.lapse[k])
        else:
            lp, d1, wk, dwk, fk = beta_rating(eta, ans.target[k], ans.rating_scale, ans.rating_precision)
        ll += lp
        gf[i] += d1
        if j >= 0:
            gf[j] -= d1
        w[k], dw[k], fw[k] = wk, dwk, fk
    return ll, gf, w, dw, fw


@njit(cache=True)
def evaluate(L, a, ans):
    """``(Psi, grad Psi, weights, log p)`` at the whitened point ``a``."""
    ll, gf, w, _, _ = answer_terms(L @ a, ans)
    grad = L.T @ gf - a
    return ll - 0.5 * (a @ a), grad, w, ll


@njit(cache=True)
def w_times(ans, w, A):
    """``W A`` for ``W = sum_k w_k d_k d_k^T`` (``d_k = e_i - e_j``, or ``e_i`` for a rating) and ``A`` (``n x k``)."""
    out = np.zeros_like(A)
    for k in range(ans.first.shape[0]):
        i, j = ans.first[k], ans.second[k]
        for c in range(A.shape[1]):
            v = w[k] * (A[i, c] - (A[j, c] if j >= 0 else 0.0))
            out[i, c] += v
            if j >= 0:
                out[j, c] -= v
    return out


@njit(cache=True)
def w_dense(ans, w, n):
    """``W`` (``n x n``) densely."""
    W = np.zeros((n, n))
    for k in range(ans.first.shape[0]):
        i, j = ans.first[k], ans.second[k]
        W[i, i] += w[k]
        if j >= 0:
            W[j, j] += w[k]
            W[i, j] -= w[k]
            W[j, i] -= w[k]
    return W


@njit(cache=True)
def cholesky(A):
    """``(L, ok)``: the lower Cholesky factor of ``A``, ``ok`` false where it is not positive definite."""
    try:
        return np.linalg.cholesky(A), True
    except Exception:  # numba's LinAlgError
        return np.zeros_like(A), False


@njit(cache=True)
def factorise(L, ans, a, w):
    """``(M, weights, fisher, ok)``: the Cholesky factor of ``B = I + L^T W L`` at ``a``, with the
    Fisher weights of the Beta ratings where the exact ``B`` is not positive definite
    (:meth:`torchpref.inference.newton.Problem.factorise`)."""
    B = L.T @ w_times(ans, w, L)
    for i in range(B.shape[0]):
        B[i, i] += 1.0
    M, ok = cholesky(B)
    if ok:
        return M, w, False, True
    fw = answer_terms(L @ a, ans)[4]
    B = L.T @ w_times(ans, fw, L)
    for i in range(B.shape[0]):
        B[i, i] += 1.0
    M, ok = cholesky(B)
    return M, fw, True, ok


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
def line_search(L, ans, a, psi, grad, w, ll, step, dec):
    """Armijo backtracking from ``a`` along ``step``: ``(a, Psi, grad, weights, log p, moved)``."""
    t = 1.0
    while True:
        trial = a + t * step
        psi_t, grad_t, w_t, ll_t = evaluate(L, trial, ans)
        if np.isfinite(psi_t) and psi_t >= psi + ARMIJO * t * dec:
            return trial, psi_t, grad_t, w_t, ll_t, True
        t *= SHRINK
        if t <= MIN_STEP:
            return a, psi, grad, w, ll, False


@njit(cache=True)
def best_start(L, ans, starts):
    """``(a, Psi, grad, weights, log p, Psi(0))`` at the candidate start (rows of ``starts``,
    utilities) of highest ``Psi``; zeros without one (a start that is not finite counts as zeros)."""
    n = L.shape[0]
    a = np.zeros(n)
    psi, grad, w, ll = evaluate(L, a, ans)
    psi0 = psi
    for r in range(starts.shape[0]):
        ar = solve_lower(L, starts[r].copy())
        if not np.all(np.isfinite(ar)):
            ar = np.zeros(n)
        pr, gr, wr, lr = evaluate(L, ar, ans)
        if r == 0 or pr > psi:
            a, psi, grad, w, ll = ar, pr, gr, wr, lr
    return a, psi, grad, w, ll, psi0


@njit(cache=True)
def final_status(fisher, ok, status, psi, psi0):
    """The status of a mode and factor handed back: ``status``, or why the torch solver must
    answer: the factor is not positive definite, needed Fisher weights, or the point is below
    ``Psi(0)`` (no mode is: a warm start that "converged" where round-off hides the gradient,
    as far in a saturated likelihood's tail; the torch solver then fails or restarts cold)."""
    if not ok:
        return NOT_PD
    if status == OK and not psi >= psi0:
        return BELOW_ZERO
    return FISHER if fisher and status == OK else status


@njit(cache=True)
def newton(L, ans, starts, tol, max_iter):
    """The Laplace mode: ``(a, M, weights, iterations, status, decrement)`` with ``M`` the Cholesky
    factor of ``B`` at ``a`` (:func:`torchpref.inference.newton.newton_mode` for one problem). A
    warm start that fails (a non-finite step, no convergence, or a point below ``Psi(0)``, which no
    mode is) is retried from zeros, as the torch solver's caller retries a warm start that raises
    (:meth:`torchpref.inference.solver.PosteriorState.solve`): far in a saturated likelihood's tail
    a start predicted for other hyperparameters can stall where round-off hides the gradient."""
    out = newton_from(L, ans, starts, tol, max_iter)
    if starts.shape[0] and out[4] in (BELOW_ZERO, NOT_CONVERGED, NOT_FINITE, NOT_PD):
        out = newton_from(L, ans, np.empty((0, L.shape[0])), tol, max_iter)
    if out[4] == BELOW_ZERO:
        return out[0], out[1], out[2], out[3], NOT_CONVERGED, out[5]
    return out


@njit(cache=True)
def newton_from(L, ans, starts, tol, max_iter):
    """:func:`newton` from the best of ``starts`` (zeros without one), without the retry."""
    a, psi, grad, w, ll, psi0 = best_start(L, ans, starts)
    newton_dec = np.inf
    dec = np.inf
    for it in range(1, max_iter + 1):
        M, wM, fisher, ok = factorise(L, ans, a, w)
        if not ok:
            return a, M, wM, it, NOT_PD, dec
        step = chol_solve(M, grad)
        dec = grad @ step
        if not np.isfinite(dec):
            return a, M, wM, it, NOT_FINITE, dec
        prior = 0.5 * (a @ a)
        stalled = dec > 0.25 * newton_dec and dec / 2 < ROUNDOFF * (abs(psi + prior) + prior)
        newton_dec = dec
        if dec / 2 < tol or stalled:
            return a, M, wM, it, final_status(fisher, ok, OK, psi, psi0), dec
        a, psi, grad, w, ll, moved = line_search(L, ans, a, psi, grad, w, ll, step, dec)
        if not moved:
            M, wM, fisher, ok = factorise(L, ans, a, w)
            floor = ROUNDOFF * (abs(psi + prior) + prior)
            status = OK if dec / 2 < max(floor, STUCK_TOL) else NOT_CONVERGED
            return a, M, wM, it, final_status(fisher, ok, status, psi, psi0), dec
    M, wM, fisher, ok = factorise(L, ans, a, w)
    return a, M, wM, max_iter, final_status(fisher, ok, NOT_CONVERGED, psi, psi0), dec


@njit(cache=True)
def evidence(L, ans, a, M, w):
    r"""``(log q, G, d log q / d nu)``: the second-order corrected Laplace evidence at the mode ``a``,
    its gradient in ``K``, ``G = (alpha alpha^T - (W - W Sigma W) - (I - W Sigma) h alpha^T) / 2``,
    and its derivative in the Beta ratings' precision ``nu``, ``sum_k (d l_k / d nu - s_k (d w_k /
    d nu) / 2) - (Sigma h)^T (d grad l / d nu) / 2`` at the fixed mode (``s_k = Sigma_ii`` of the
    rated item; the mode's implicit dependence through ``h``), as
    :func:`torchpref.inference.laplace.laplace_evidence` does for a likelihood parameter."""
    n, m = L.shape[0], ans.first.shape[0]
    ll, g, _, dw, _ = answer_terms(L @ a, ans)
    V = np.linalg.solve(M, np.ascontiguousarray(L.T))  # M^-1 L^T: Sigma = V^T V
    Sigma = V.T @ V
    h = np.zeros(n)
    for k in range(m):
        i, j = ans.first[k], ans.second[k]
        if j >= 0:
            v = dw[k] * (Sigma[i, i] + Sigma[j, j] - 2.0 * Sigma[i, j])
            h[j] -= v
        else:
            v = dw[k] * Sigma[i, i]
        h[i] += v
    Sigma_h = Sigma @ h
    WS = w_times(ans, w, Sigma)
    WSW = w_times(ans, w, np.ascontiguousarray(WS.T))
    b = h - w_times(ans, w, Sigma_h.reshape(n, 1))[:, 0]
    alpha = solve_lower_t(L, a)
    W = w_dense(ans, w, n)
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
    f = L @ a
    dnu = 0.0
    for k in range(m):
        if ans.kind[k] == BETA:
            i = ans.first[k]
            dl, dg, dw_nu = beta_rating_dnu(f[i] + ans.offset[k], ans.target[k], ans.rating_scale, ans.rating_precision)
            dnu += dl - 0.5 * Sigma[i, i] * dw_nu - 0.5 * Sigma_h[i] * dg
    return value, G, dnu


@njit(cache=True)
def jittered_cholesky(K):
    """``(L, jitter, ok)`` with ``L L^T = K + jitter I`` for the first jitter of the torch solver's
    float64 schedule that works (:func:`torchpref.inference.numerics.jitter_schedule`: 0, then
    ``1e-10`` to ``1e-6`` of the mean diagonal, tenfold)."""
    L, ok = cholesky(K)
    if ok:
        return L, 0.0, ok
    n = K.shape[0]
    scale = np.trace(K) / n
    if not (np.isfinite(scale) and scale > 0.0):
        scale = 1.0
    for e in range(-10, -5):
        Kj = K.copy()
        j = scale * 10.0**e
        for i in range(n):
            Kj[i, i] += j
        L, ok = cholesky(Kj)
        if ok:
            return L, j, ok
    return L, 0.0, False
