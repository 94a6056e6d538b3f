"""Laplace inference (eqs. 2, 8-10 and the evidence) against an independent NumPy/SciPy version,
its evidence gradient against finite differences, and against BoTorch's PairwiseGP."""

import math

import numpy as np
import pytest
import torch
from gpytorch.kernels import RBFKernel, ScaleKernel
from scipy import linalg, optimize, special

from torchpref.inference.laplace import Observations
from torchpref.likelihoods.pairwise_beta import BetaRatingLikelihood, PairwiseProbitLikelihood
from torchpref.models.preference_gp import PreferenceGP
from torchpref.testing import assert_evidence_gradient, rand, randn, random_comparisons

SQRT2 = math.sqrt(2.0)


# ------------------------------------------------- an independent implementation in NumPy
class ScipyLaplace:
    """The Laplace approximation written from the paper with NumPy/SciPy only."""

    def __init__(self, X, C, u, ri, lengthscale, outputscale, sigma_R, sigma_B, nu):
        self.X, self.C, self.u, self.ri = X, C, u, ri
        self.sR, self.sB, self.nu = sigma_R, sigma_B, nu
        ls = np.broadcast_to(np.asarray(lengthscale, dtype=float), (X.shape[1],))
        self.ls, self.os = ls, outputscale
        self.K = self.kernel(X, X)
        self.cho = linalg.cho_factor(self.K, lower=True)

    def kernel(self, A, B):  # eq. 1 with ARD lengthscales
        d = (A[:, None, :] - B[None, :, :]) / self.ls
        return self.os * np.exp(-0.5 * (d**2).sum(-1))

    def loglik(self, f):
        C, u, ri = self.C, self.u, self.ri
        out = 0.0
        if len(C):
            out += special.log_ndtr((f[C[:, 0]] - f[C[:, 1]]) / (SQRT2 * self.sR)).sum()
        if len(u):
            t = f[ri] / (SQRT2 * self.sB)
            a = self.nu * np.exp(special.log_ndtr(t))
            b = self.nu * np.exp(special.log_ndtr(-t))
            out += ((a - 1) * np.log(u) + (b - 1) * np.log1p(-u) - special.betaln(a, b)).sum()
        return out

    def grad_loglik(self, f):
        C, u, ri = self.C, self.u, self.ri
        g = np.zeros_like(f)
        if len(C):
            s = SQRT2 * self.sR
            z = (f[C[:, 0]] - f[C[:, 1]]) / s
            r = np.exp(-0.5 * z**2 - 0.5 * math.log(2 * math.pi) - special.log_ndtr(z)) / s
            np.add.at(g, C[:, 0], r)
            np.add.at(g, C[:, 1], -r)
        if len(u):
            c = SQRT2 * self.sB
            t = f[ri] / c
            a = self.nu * np.exp(special.log_ndtr(t))
            b = self.nu * np.exp(special.log_ndtr(-t))
            dlp_dmu = self.nu * (np.log(u) - np.log1p(-u) - special.digamma(a) + special.digamma(b))
            np.add.at(g, ri, dlp_dmu * np.exp(-0.5 * t**2) / (math.sqrt(2 * math.pi) * c))
        return g

    def neg_hess_loglik(self, f, h=1e-5):
        """W by central finite differences of the analytic gradient (symmetrised)."""
        n = f.shape[0]
        H = np.zeros((n, n))
        for k in range(n):
            e = np.zeros(n)
            e[k] = h
            H[:, k] = (self.grad_loglik(f + e) - self.grad_loglik(f - e)) / (2 * h)
        return -0.5 * (H + H.T)

    def solve(self):
        # whitened coordinates f = L a (K = L L^T), where the problem is well scaled even when K
        # is ill-conditioned: minimise -log p(Y | L a) + a^T a / 2  (= f^T K^-1 f / 2)
        L = np.tril(self.cho[0])

        def obj(a):
            return -self.loglik(L @ a) + 0.5 * a @ a

        def jac(a):
            return -L.T @ self.grad_loglik(L @ a) + a

        def hess(a):
            return L.T @ self.neg_hess_loglik(L @ a) @ L + np.eye(len(a))

        a = np.zeros(len(self.X))
        res = optimize.minimize(obj, a, jac=jac, hess=hess, method="trust-exact", options={"gtol": 1e-10})
        a = res.x
        for _ in range(3):  # polish with plain Newton steps
            a = a - np.linalg.solve(hess(a), jac(a))
        assert np.abs(jac(a)).max() < 1e-9, res
        f = L @ a
        self.f = f
        self.W = self.neg_hess_loglik(f)
        n = len(f)
        sign, logdet = np.linalg.slogdet(np.eye(n) + self.W @ self.K)
        assert sign > 0
        self.evidence = self.loglik(f) - 0.5 * f @ linalg.cho_solve(self.cho, f) - 0.5 * logdet
        return self

    def predict(self, Xs):
        Kxs = self.kernel(self.X, Xs)
        mean = Kxs.T @ linalg.cho_solve(self.cho, self.f)  # eq. 9
        n = len(self.f)
        cov = self.kernel(Xs, Xs) - Kxs.T @ np.linalg.solve(np.eye(n) + self.W @ self.K, self.W @ Kxs)  # eq. 10
        return mean, cov


def make_problem(kind, d, seed):
    g = torch.Generator().manual_seed(seed)
    n = 8
    X = rand(n, d, generator=g)
    C = random_comparisons(n, 7, g) if kind in ("mixed", "comparisons") else torch.zeros(0, 2, dtype=torch.long)
    if kind in ("mixed", "ratings"):
        q = 5
        ri = torch.randperm(n, generator=g)[:q]
        u = rand(q, generator=g, low=0.05, high=0.95)
    else:
        ri, u = torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.float64)
    Xs = rand(6, d, generator=g)
    return X, C, u, ri, Xs


def kernel(lengthscale, outputscale, d, ard=True):
    k = ScaleKernel(RBFKernel(ard_num_dims=d if ard else None)).to(torch.float64)
    k.base_kernel.lengthscale = lengthscale
    k.outputscale = outputscale
    return k


HYPERS = {"lengthscale": [0.35, 0.5, 0.25], "outputscale": 1.3, "sigma_R": 0.3, "sigma_B": 0.8, "nu": 30.0}


def build(kind, d, seed, learn=False):
    X, C, u, ri, Xs = make_problem(kind, d, seed)
    ls = HYPERS["lengthscale"][:d]
    model = PreferenceGP(
        X,
        C,
        u if len(u) else None,
        ri if len(u) else None,
        covar_module=kernel(torch.tensor(ls, dtype=torch.float64), HYPERS["outputscale"], d),
        comparison_noise=HYPERS["sigma_R"],
        rating_scale=HYPERS["sigma_B"],
        rating_precision=HYPERS["nu"],
        learn_likelihood=learn,
    )
    ref = ScipyLaplace(
        X.numpy(),
        C.numpy(),
        u.numpy(),
        ri.numpy(),
        ls,
        HYPERS["outputscale"],
        HYPERS["sigma_R"],
        HYPERS["sigma_B"],
        HYPERS["nu"],
    )
    return model, ref, Xs


@pytest.mark.parametrize("kind", ["mixed", "comparisons", "ratings"])
@pytest.mark.parametrize("d", [1, 2, 3])
@pytest.mark.parametrize("seed", [0, 1])
def test_laplace_matches_scipy(kind, d, seed):
    model, ref, Xs = build(kind, d, seed)
    ref.solve()
    mode = model.mode
    assert mode.converged
    # the library stops once half its Newton decrement is below 1e-11, i.e. |grad| ~ 1e-6 in whitened
    # units, so its mode is good to a few 1e-7 (the SciPy one is polished to round-off)
    np.testing.assert_allclose(mode.f.numpy(), ref.f, rtol=0, atol=2e-6)
    W = model.W().detach().numpy()
    np.testing.assert_allclose(W, ref.W, rtol=0, atol=1e-5 * max(1.0, np.abs(ref.W).max()))
    post = model.posterior(Xs)
    mean, cov = ref.predict(Xs.numpy())
    np.testing.assert_allclose(post.mean.detach().squeeze(-1).numpy(), mean, rtol=0, atol=1e-6)
    np.testing.assert_allclose(post.variance.detach().squeeze(-1).numpy(), np.diag(cov), rtol=0, atol=1e-6)
    np.testing.assert_allclose(post.distribution.covariance_matrix.detach().numpy(), cov, rtol=0, atol=1e-6)
    # at the training items the posterior mean is the mode
    np.testing.assert_allclose(
        model.posterior(model.train_X).mean.detach().squeeze(-1).numpy(), ref.f, rtol=0, atol=2e-6
    )
    assert abs(float(model.log_marginal_likelihood().detach()) - ref.evidence) < 1e-6


# ---------------------------------------------------------- evidence gradient (implicit mode)
def _raw_params(model, learn, kind):
    params = {
        "raw_lengthscale": model.covar_module.base_kernel.raw_lengthscale,
        "raw_outputscale": model.covar_module.raw_outputscale,
    }
    if learn and kind != "ratings":
        params["raw_comparison_noise"] = model.comparison_likelihood.raw_comparison_noise
    if learn and kind != "comparisons":
        params["raw_rating_scale"] = model.rating_likelihood.raw_rating_scale
        params["raw_rating_precision"] = model.rating_likelihood.raw_rating_precision
    return params


@pytest.mark.parametrize(
    "kind,d,learn",
    [("mixed", 2, True), ("comparisons", 1, True), ("ratings", 3, True), ("mixed", 1, False), ("mixed", 3, True)],
)
def test_evidence_gradient_vs_finite_differences(kind, d, learn):
    model, _, _ = build(kind, d, seed=3, learn=learn)
    params = _raw_params(model, learn, kind)
    assert_evidence_gradient(model, params)


def test_evidence_gradient_is_not_the_fixed_mode_gradient():
    """The gradient must include d f_hat / d theta: differs from the naive fixed-mode derivative."""
    model, _, _ = build("mixed", 1, seed=5)
    p = model.covar_module.base_kernel.raw_lengthscale
    (g,) = torch.autograd.grad(model.log_marginal_likelihood(), [p])
    # naive: same formula with the mode held fixed (no implicit term through W)
    from torchpref.inference.laplace import laplace_evidence  # noqa: F401  (documented pure function)

    f_fixed = model.mode.f.clone()
    L = torch.linalg.cholesky(model.covar_module(model.train_X).to_dense())
    obs = model._observations()
    weights = obs.evaluate(f_fixed[None]).weights
    a = torch.linalg.solve_triangular(L, f_fixed.unsqueeze(-1), upper=False).squeeze(-1)
    B = obs.whitened_hessian(L[None], [w.detach() for w in weights])[0]
    naive = -0.5 * (a * a).sum() - torch.log(torch.diagonal(torch.linalg.cholesky(B))).sum()
    (gn,) = torch.autograd.grad(naive, [p])
    assert abs(float(g) - float(gn)) > 1e-6 * abs(float(g))


# ------------------------------------------------------------- against BoTorch's PairwiseGP
@pytest.mark.parametrize("d,seed", [(1, 0), (2, 1), (3, 2)])
def test_matches_botorch_pairwise_gp(d, seed):
    from botorch.models.pairwise_gp import PairwiseGP, PairwiseLaplaceMarginalLogLikelihood

    g = torch.Generator().manual_seed(seed)
    n = 7
    X = rand(n, d, generator=g)
    C = random_comparisons(n, 5, g)
    Xs = rand(5, d, generator=g)
    ls, os_ = [0.6, 0.8, 0.7][:d], 0.5  # modest: BoTorch clamps z to +-3
    ours = PreferenceGP(
        X, C, covar_module=kernel(torch.tensor(ls, dtype=torch.float64), os_, d), comparison_noise=1.0
    )  # Phi((f_i - f_j) / sqrt 2)
    theirs = PairwiseGP(
        X, C, covar_module=kernel(torch.tensor(ls, dtype=torch.float64), os_, d), xtol=1e-13, maxfev=10_000
    )
    theirs.eval()
    z = (ours.mode.f[C[:, 0]] - ours.mode.f[C[:, 1]]) / SQRT2
    assert z.abs().max() < 3, "the comparison must stay clear of PairwiseGP's z clamp"
    np.testing.assert_allclose(ours.mode.f.numpy(), theirs.utility.detach().numpy(), rtol=0, atol=1e-6)
    p1, p2 = ours.posterior(Xs), theirs.posterior(Xs)
    np.testing.assert_allclose(p1.mean.detach().numpy(), p2.mean.detach().numpy(), rtol=0, atol=1e-6)
    # PairwiseGP adds no jitter here (its Cholesky succeeds) but returns its covariance through a
    # Cholesky root; compare the variances
    np.testing.assert_allclose(p1.variance.detach().numpy(), p2.variance.detach().numpy(), rtol=0, atol=1e-6)
    # evidence: PairwiseLaplaceMarginalLogLikelihood is -S(f) - log|I + K W| / 2 + log priors, with
    # S = -log p(Y|f) + f K^-1 f / 2 (Chu & Ghahramani eq. 12). The kernels here carry no priors,
    # so the two must agree exactly (no additive constant).
    theirs.train()
    mll = PairwiseLaplaceMarginalLogLikelihood(theirs.likelihood, theirs)
    post = theirs(theirs.unconsolidated_datapoints)
    their_ev = float(mll(post, theirs.unconsolidated_comparisons).detach())
    assert abs(float(ours.log_marginal_likelihood().detach()) - their_ev) < 1e-6


@pytest.mark.parametrize("kind,d,learn", [("mixed", 2, True), ("comparisons", 1, True), ("ratings", 3, True)])
def test_written_out_evidence_gradient_equals_traced(kind, d, learn):
    """The hand-written evidence gradient against autograd through both Cholesky factorisations
    (the implicit mode dependence by a Newton step), at the same mode."""
    from torchpref.inference.laplace import _laplace_evidence_traced, laplace_evidence

    model, _, _ = build(kind, d, seed=7, learn=learn)
    params = list(_raw_params(model, learn, kind).values())
    st, obs = model._state(), model._observations()
    K = model._kernel(model._transformed_train_X())
    fast = laplace_evidence(K, obs, st.mode.select(0), L=st.pred.L[0], jitter=st.jitter)
    g_fast = torch.autograd.grad(fast, params)
    K = model._kernel(model._transformed_train_X())
    L = torch.linalg.cholesky(K + st.jitter * torch.eye(K.shape[0], dtype=K.dtype))
    traced = _laplace_evidence_traced(L, obs, st.mode.select(0))
    g_traced = torch.autograd.grad(traced, params)
    assert abs(float(fast.detach()) - float(traced.detach())) < 1e-10
    for a, b in zip(g_fast, g_traced):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-8)


def test_whitened_hessian_sparse_and_row_forms_agree(generator):
    """``B = I + L^T W L`` by the sparse-W product (many observations) and by the row form."""
    n = 12
    A = randn(n, n, generator=generator)
    L = torch.linalg.cholesky(A @ A.T / n + torch.eye(n, dtype=torch.float64))
    C = random_comparisons(n, 20, generator)
    ri = torch.randint(0, n, (9,), generator=generator)
    obs = Observations.from_data(
        C,
        rand(9, generator=generator, low=0.05, high=0.95),
        ri,
        PairwiseProbitLikelihood(0.3),
        BetaRatingLikelihood(0.8, 60.0),
    )
    weights = [rand(1, 20, generator=generator), randn(1, 9, generator=generator)]  # w may be negative
    sparse = obs.whitened_hessian(L[None], weights)[0]  # 2 (p + q) > n: the sparse path
    Lg = L.clone().requires_grad_(True)  # a tracked L takes the row form
    rows = obs.whitened_hessian(Lg[None], weights)[0].detach()
    # W written out from its definition (eq. 8)
    W = torch.zeros(n, n, dtype=torch.float64)
    for (i, j), lam in zip(C.tolist(), weights[0][0].tolist()):
        W[i, i] += lam
        W[j, j] += lam
        W[i, j] -= lam
        W[j, i] -= lam
    for i, w in zip(ri.tolist(), weights[1][0].tolist()):
        W[i, i] += w
    torch.testing.assert_close(obs.W_dense(n, weights)[0], W, rtol=0, atol=1e-14)
    dense = torch.eye(n, dtype=torch.float64) + L.T @ W @ L
    torch.testing.assert_close(sparse, dense, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(rows, dense, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(
    "sigma_R,lengthscale,nu", [(1.0, 0.3, 60.0), (1e-3, 0.05, 60.0), (10.0, 3.0, 60.0), (0.2, 0.01, 1e3)]
)
def test_mode_accelerations_reach_the_plain_newton_mode(sigma_R, lengthscale, nu):
    """Float32 steps far from the mode and chord steps near it (n >= 256) end at the mode that
    plain float64 Newton finds, with the same exact factorisation, also where float32 fails
    (tiny sigma_R: huge curvatures) and the solver falls back to float64."""
    from torchpref.inference.laplace import find_mode

    g = torch.Generator().manual_seed(11)
    n = 300
    X = rand(n, 2, generator=g)
    K = kernel(torch.tensor([lengthscale, lengthscale], dtype=torch.float64), 1.0, 2)(X).to_dense()
    L = torch.linalg.cholesky(K + 1e-6 * torch.eye(n, dtype=torch.float64))
    ri = torch.randperm(n, generator=g)[:100]
    obs = Observations.from_data(
        random_comparisons(n, 500, g),
        rand(100, generator=g, low=0.05, high=0.95),
        ri,
        PairwiseProbitLikelihood(sigma_R),
        BetaRatingLikelihood(0.8, nu),
    )
    fast = find_mode(L, obs)
    plain = find_mode(L, obs, max_chord=0, single_precision_min_size=10**9)
    assert fast.converged and plain.converged
    torch.testing.assert_close(fast.f, plain.f, rtol=0, atol=1e-6 * (1 + plain.f.abs().max()))
    assert fast.M.dtype == torch.float64
    scale = plain.M.abs().max()  # B ~ 1 / sigma_R^2: compare relative to its size
    torch.testing.assert_close(fast.M / scale, plain.M / scale, rtol=0, atol=1e-7)
