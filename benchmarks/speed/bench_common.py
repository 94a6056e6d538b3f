r"""Shared data and model builders for the speed benchmarks against BoTorch's ``PairwiseGP``.

Both libraries get the same comparisons-only data and the same kernel: a
``ScaleKernel(RBFKernel(ard_num_dims=d))`` with the same initial lengthscale / outputscale and
the same hyperparameter priors, so the two Laplace evidences differ only in how they are computed.
``PreferenceGP(..., comparison_noise=1.0)`` has BoTorch's probit ``Phi((f_i - f_j) / sqrt 2)``.
"""

from __future__ import annotations

import math
import warnings

import torch
from botorch.fit import fit_gpytorch_mll
from botorch.models.pairwise_gp import PairwiseGP, PairwiseLaplaceMarginalLogLikelihood
from gpytorch.kernels import RBFKernel, ScaleKernel
from gpytorch.priors import GammaPrior, LogNormalPrior
from torch import Tensor

from torchpref import LaplaceMarginalLogLikelihood, PreferenceGP

DTYPE = torch.float64
DIM = 2
INIT_LENGTHSCALE = 0.3
INIT_OUTPUTSCALE = 1.0
UTILITY_SCALE = 2.0  # utilities of a few units: comparisons neither random nor all certain
SIZES = [(100, 200), (500, 1000)]  # (n items, p comparisons): the pytest-benchmark sizes
#: EUBO's ``optimize_acqf`` settings, as in BoTorch's preference-learning tutorial (q = 2, 3 restarts, 512 raw samples)
EUBO_SETTINGS = {"q": 2, "num_restarts": 3, "raw_samples": 512}
MIXED_N = 2000


def utility(X: Tensor) -> Tensor:
    r"""A sum of sines on ``[0, 1]^2`` (``... x 2 -> ...``), of amplitude about ``UTILITY_SCALE``."""
    x, y = X[..., 0], X[..., 1]
    return (
        UTILITY_SCALE
        * 0.5
        * (torch.sin(2 * math.pi * x) + torch.sin(3 * math.pi * y + 0.5) + 0.5 * torch.sin(2 * math.pi * (x + y)))
    )


def make_comparisons(n: int, p: int, dim: int = DIM, seed: int = 0) -> tuple[Tensor, Tensor]:
    r"""``n`` uniform items in ``[0, 1]^dim`` and ``p`` comparisons between random distinct pairs,
    answered by the utility plus ``N(0, 1)`` noise on each item (the ``sigma_R = 1`` probit).

    Returns:
        ``X`` (``n x dim``, float64) and ``comparisons`` (``p x 2`` long, preferred first).
    """
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, dim, generator=g, dtype=DTYPE)
    i = torch.randint(0, n, (p,), generator=g)
    j = (i + torch.randint(1, n, (p,), generator=g)) % n  # j != i
    u = utility(X)
    noisy_i = u[i] + torch.randn(p, generator=g, dtype=DTYPE)
    noisy_j = u[j] + torch.randn(p, generator=g, dtype=DTYPE)
    first = noisy_i >= noisy_j
    C = torch.stack([torch.where(first, i, j), torch.where(first, j, i)], dim=-1)
    return X, C


def make_mixed(n: int = MIXED_N, p: int | None = None, q: int | None = None, seed: int = 1):
    r"""Mixed data: ``n`` items, ``p = n`` comparisons and ``q = n / 2`` Beta ratings.

    Returns:
        ``X``, ``comparisons``, ``ratings`` (``q`` in ``(0, 1)``), ``rating_index`` (``q``).
    """
    p = n if p is None else p
    q = n // 2 if q is None else q
    X, C = make_comparisons(n, p, seed=seed)
    g = torch.Generator().manual_seed(seed + 1000)
    idx = torch.randperm(n, generator=g)[:q]
    mu = torch.special.ndtr(utility(X[idx]) / math.sqrt(2.0))  # sigma_B = 1
    nu = 80.0
    a = torch.distributions.Beta(nu * mu, nu * (1 - mu))
    # torch.distributions has no generator argument: draw with the global RNG under a fixed seed
    with torch.random.fork_rng():
        torch.manual_seed(seed + 2000)
        ratings = a.sample().clamp(1e-4, 1 - 1e-4)
    return X, C, ratings, idx


def make_kernel(dim: int = DIM) -> ScaleKernel:
    """The same kernel, priors and initial values for both libraries."""
    k = ScaleKernel(
        RBFKernel(ard_num_dims=dim, lengthscale_prior=LogNormalPrior(math.sqrt(2) + 0.5 * math.log(dim), math.sqrt(3))),
        outputscale_prior=GammaPrior(2.0, 1.0),
    ).to(DTYPE)
    k.base_kernel.lengthscale = INIT_LENGTHSCALE
    k.outputscale = INIT_OUTPUTSCALE
    return k


def build_torchpref(X: Tensor, C: Tensor) -> PreferenceGP:
    """Construct (no mode solved yet: it is solved lazily)."""
    return PreferenceGP(X, comparisons=C, covar_module=make_kernel(X.shape[-1]), comparison_noise=1.0)


def build_pairwisegp(X: Tensor, C: Tensor) -> PairwiseGP:
    """Construct; PairwiseGP's constructor solves its MAP."""
    return PairwiseGP(X, C, covar_module=make_kernel(X.shape[-1]))


def mode_torchpref(X: Tensor, C: Tensor) -> PreferenceGP:
    model = build_torchpref(X, C)
    model.mode  # noqa: B018 - solves the Laplace mode
    return model


def fit_torchpref(model: PreferenceGP) -> LaplaceMarginalLogLikelihood:
    mll = LaplaceMarginalLogLikelihood(model)
    fit_gpytorch_mll(mll)
    model.eval()
    return mll


def fit_pairwisegp(model: PairwiseGP) -> PairwiseLaplaceMarginalLogLikelihood:
    mll = PairwiseLaplaceMarginalLogLikelihood(model.likelihood, model)
    with warnings.catch_warnings():
        # PairwiseGP warns about its own internals during fitting; keep the benchmark output clean
        warnings.simplefilter("ignore", category=RuntimeWarning)
        fit_gpytorch_mll(mll)
    model.eval()
    return mll


# ------------------------------------------------ botorch-rust (optional peer: PyPI botorch-rust, import botorch_rs)
def botorch_rust_available() -> bool:
    """Whether ``botorch_rs`` (PyPI ``botorch-rust``) can be imported."""
    try:
        import botorch_rs  # noqa: F401
    except ImportError:
        return False
    return True


def make_kernel_rs(dim: int = DIM):
    """:func:`make_kernel` built from botorch-rust's own kernel and prior classes."""
    from botorch_rs.kernels import RBFKernel as RsRBF
    from botorch_rs.kernels import ScaleKernel as RsScale
    from botorch_rs.priors import GammaPrior as RsGamma
    from botorch_rs.priors import LogNormalPrior as RsLogNormal

    k = RsScale(
        RsRBF(ard_num_dims=dim, lengthscale_prior=RsLogNormal(math.sqrt(2) + 0.5 * math.log(dim), math.sqrt(3))),
        outputscale_prior=RsGamma(2.0, 1.0),
    )
    k.base_kernel.lengthscale = INIT_LENGTHSCALE
    k.outputscale = INIT_OUTPUTSCALE
    return k


def build_botorch_rust(X: Tensor, C: Tensor):
    """botorch-rust's ``PairwiseGP`` (its constructor solves the MAP, as BoTorch's does)."""
    from botorch_rs.models import PairwiseGP as RsPairwiseGP

    return RsPairwiseGP(X, C, covar_module=make_kernel_rs(X.shape[-1]))


def fit_botorch_rust(model):
    """botorch-rust's ``fit_gpytorch_mll`` with its ``PairwiseLaplaceMarginalLogLikelihood``."""
    from botorch_rs.fit import fit_gpytorch_mll as rs_fit
    from botorch_rs.models.pairwise_gp import PairwiseLaplaceMarginalLogLikelihood as RsMLL

    mll = RsMLL(model.likelihood, model)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", category=RuntimeWarning)
        rs_fit(mll)
    model.eval()
    return mll


def eubo_optimize(model, lib: str, seed: int = 0) -> Tensor:
    """``optimize_acqf`` of EUBO (``AnalyticExpectedUtilityOfBestOption``) on ``[0, 1]^d`` with
    :data:`EUBO_SETTINGS`; botorch-rust's own EUBO and ``optimize_acqf`` for its model."""
    if lib == "botorch_rust":
        from botorch_rs.acquisition.preference import AnalyticExpectedUtilityOfBestOption as Eubo
        from botorch_rs.optim import optimize_acqf as optimize
    else:
        from botorch.acquisition.preference import AnalyticExpectedUtilityOfBestOption as Eubo
        from botorch.optim import optimize_acqf as optimize
    d = DIM
    bounds = torch.stack([torch.zeros(d, dtype=DTYPE), torch.ones(d, dtype=DTYPE)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", category=RuntimeWarning)
        cand, _ = optimize(Eubo(pref_model=model), bounds=bounds, options={"seed": seed}, **EUBO_SETTINGS)
    return cand


def evidence_botorch_rust(model) -> float:
    """botorch-rust's Laplace evidence plus hyperparameter log priors (what its fit maximises)."""
    from botorch_rs.models.pairwise_gp import PairwiseLaplaceMarginalLogLikelihood as RsMLL

    mll = RsMLL(model.likelihood, model)
    model.train()
    val = float(mll(model(model.unconsolidated_datapoints), model.unconsolidated_comparisons))
    model.eval()
    return val


def posterior_moments(model, X: Tensor) -> tuple[Tensor, Tensor]:
    with torch.no_grad():
        post = model.posterior(X)
        return post.mean, post.variance


def query_points(num: int = 1000, dim: int = DIM, seed: int = 7) -> Tensor:
    r"""``num x 1 x dim`` batch of test points."""
    g = torch.Generator().manual_seed(seed)
    return torch.rand(num, 1, dim, generator=g, dtype=DTYPE)


def hyperparameters(model) -> dict[str, list[float]]:
    k = model.covar_module
    return {
        "lengthscale": [round(float(v), 5) for v in torch.as_tensor(k.base_kernel.lengthscale).detach().reshape(-1)],
        "outputscale": round(float(torch.as_tensor(k.outputscale).detach()), 5),
    }


def evidence_torchpref(model: PreferenceGP) -> float:
    """Laplace evidence plus hyperparameter log priors (what the fit maximises)."""
    with torch.no_grad():
        return float(LaplaceMarginalLogLikelihood(model)())


def evidence_pairwisegp(model: PairwiseGP) -> float:
    """PairwiseGP's Laplace evidence plus hyperparameter log priors (what its fit maximises)."""
    mll = PairwiseLaplaceMarginalLogLikelihood(model.likelihood, model)
    model.train()
    with torch.no_grad():
        out = model(model.datapoints)
        val = float(mll(out, model.unconsolidated_comparisons))
    model.eval()
    return val
