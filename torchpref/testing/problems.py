r"""Hostile preference problems and the checks run on each, shared by ``tests/inference/test_fuzz.py`` (a small
sample) and ``benchmarks/robustness/fuzz.py`` (a thousand and more).

A problem (:func:`make_problem`, from a seed): ``n`` log-uniform in ``1 .. max_n`` items in
``[0, 1]^d``, some duplicated; comparisons (some contradictory: both orders), ratings (some at
``1e-6`` from 0 or 1, or the same item rated inconsistently), or both; kernel lengthscale
``1e-3 .. 1e3`` and outputscale ``1e-2 .. 1e2`` (log-uniform), and for problems with ratings the
likelihood's ``sigma_R``, ``sigma_B`` and ``nu`` as hostile. Comparisons-only problems use
``sigma_R = 1``, BoTorch's ``PairwiseGP`` likelihood, so that ``PairwiseGP`` solves the same problem.

:func:`check` runs a problem as each model of :data:`RUNS` (float64; float32 solving in float64,
the default; float32 solving natively) and ``PairwiseGP`` in float32 on comparisons-only problems:
the exception raised if any, whether anything is NaN, whether Newton converged, the jitter and
the time taken, and how far each float32 posterior is from float64's, with autograd off and on
(the inputs requiring a gradient, as inside ``optimize_acqf``).
:func:`hostile_model` (from a seed) is the problem of that seed with a model started from hyperparameters at
the edges of what the optimiser can reach; :func:`fit_outcome` fits it and says how it ended
(``benchmarks/robustness/hostile_fits.py`` runs many).
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field
from typing import Any

import torch
from gpytorch.kernels import RBFKernel, ScaleKernel
from torch import Tensor

from torchpref import PreferenceGP

F32, F64 = torch.float32, torch.float64
KINDS = ("comparisons", "ratings", "mixed")
#: The models run on each problem: name -> (dtype, laplace_dtype). ``f32`` is the default float32
#: model (mixed precision), ``f32n`` a float32 model solving natively (docs/precision.md).
RUNS = {"f64": (F64, None), "f32": (F32, None), "f32n": (F32, F32)}
FLOAT32_RUNS = ("f32", "f32n")


@dataclass
class Problem:
    """One hostile problem (float64 tensors; indices long)."""

    seed: int
    kind: str
    X: Tensor
    comparisons: Tensor
    ratings: Tensor
    rating_index: Tensor
    lengthscale: float
    outputscale: float
    likelihood: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        """The number of items."""
        return self.X.shape[0]


def _log_uniform(lo: float, hi: float, g: torch.Generator) -> float:
    return math.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * float(torch.rand((), generator=g, dtype=F64)))


def make_problem(seed: int, max_n: int = 1500, pairwise_likelihood: bool = True) -> Problem:
    """The hostile problem of ``seed`` (see the module docstring); with ``pairwise_likelihood=False``
    comparisons-only problems get hostile likelihood parameters too."""
    g = torch.Generator().manual_seed(seed)
    n = max(1, min(max_n, round(_log_uniform(1.0, max_n, g))))
    d = int(torch.randint(1, 5, (), generator=g))
    kind = KINDS[int(torch.randint(0, 3, (), generator=g))] if n > 1 else "ratings"
    X = torch.rand(n, d, generator=g, dtype=F64)
    if n > 1 and torch.rand((), generator=g) < 0.3:  # duplicated items (same coordinates, two indices)
        X[n // 2 :] = X[: n - n // 2].clone()
    p = int(torch.randint(1, 3 * n, (), generator=g)) if kind != "ratings" else 0
    i = torch.randint(0, n, (p,), generator=g)
    j = (i + torch.randint(1, max(n, 2), (p,), generator=g)) % n
    C = torch.stack([i, j], -1)
    if p and torch.rand((), generator=g) < 0.4:  # contradictory comparisons: both orders
        C = torch.cat([C, C.flip(-1)])
    q = int(torch.randint(1, 2 * n + 1, (), generator=g)) if kind != "comparisons" else 0
    ri = torch.randint(0, n, (q,), generator=g)
    style = int(torch.randint(0, 3, (), generator=g))
    if style == 0:  # 1e-6 from the ends
        u = torch.where(
            torch.rand(q, generator=g) < 0.5, torch.full((q,), 1e-6, dtype=F64), torch.full((q,), 1 - 1e-6, dtype=F64)
        )
    elif style == 1:
        u = torch.rand(q, generator=g, dtype=F64).clamp(1e-4, 1 - 1e-4)
    else:  # one item rated all over the scale
        u, ri = torch.linspace(0.05, 0.95, q, dtype=F64), torch.zeros(q, dtype=torch.long)
    lengthscale, outputscale = _log_uniform(1e-3, 1e3, g), _log_uniform(1e-2, 1e2, g)
    lik = {"comparison_noise": 1.0}
    if kind != "comparisons" or not pairwise_likelihood:
        lik = {
            "comparison_noise": _log_uniform(1e-3, 10.0, g),
            "rating_scale": _log_uniform(0.1, 3.0, g),
            "rating_precision": _log_uniform(1.0, 1e3, g),
        }
    # float32-representable data: the float64 twin sees exactly the float32 model's inputs
    X, u = X.float().double(), u.float().double()
    lengthscale, outputscale = float(torch.tensor(lengthscale, dtype=F32)), float(torch.tensor(outputscale, dtype=F32))
    lik = {k: float(torch.tensor(v, dtype=F32)) for k, v in lik.items()}
    return Problem(seed, kind, X, C, u, ri, lengthscale, outputscale, lik)


def random_config(seed: int) -> tuple[dict, Tensor, Tensor, Tensor, Tensor]:
    """The hostile problem of ``seed`` from the fuzz (:func:`make_problem`), at most 15
    items, with hostile likelihood parameters for every kind."""
    p = make_problem(seed, max_n=15, pairwise_likelihood=False)
    cfg = dict(
        seed=seed,
        n=p.n,
        d=p.X.shape[-1],
        kind=p.kind,
        lengthscale=p.lengthscale,
        outputscale=p.outputscale,
        **p.likelihood,
    )
    return cfg, p.X, p.comparisons, p.ratings, p.rating_index


def kernel(problem: Problem, dtype: torch.dtype) -> ScaleKernel:
    """The problem's RBF kernel (its lengthscale and outputscale) in ``dtype``."""
    k = ScaleKernel(RBFKernel(ard_num_dims=problem.X.shape[-1])).to(dtype)
    k.base_kernel.lengthscale = problem.lengthscale
    k.outputscale = problem.outputscale
    return k


def query_points(problem: Problem, num: int = 8) -> Tensor:
    """``num`` fresh points and up to 4 training items (``m x d`` float64)."""
    g = torch.Generator().manual_seed(problem.seed + 7)
    return torch.cat([torch.rand(num, problem.X.shape[-1], generator=g, dtype=F64), problem.X[:4]])


def build(problem: Problem, dtype: torch.dtype, laplace_dtype: torch.dtype | None = None) -> PreferenceGP:
    """The problem's model in ``dtype``, solving in ``laplace_dtype`` (``None``: the default)."""
    C = problem.comparisons if problem.comparisons.numel() else None
    r, ri = (problem.ratings, problem.rating_index) if problem.ratings.numel() else (None, None)
    return PreferenceGP(
        problem.X.to(dtype),
        C,
        r.to(dtype) if r is not None else None,
        ri,
        covar_module=kernel(problem, dtype),
        laplace_dtype=laplace_dtype,
        **problem.likelihood,
    )


def posterior_moments(model: PreferenceGP, X: Tensor, grad: bool) -> tuple[Tensor, Tensor]:
    """Joint posterior mean and covariance at ``X`` (``m x d``, the model's dtype), float64; with
    ``grad`` the inputs require a gradient (and one is taken, as an optimiser would)."""
    if grad:
        X = X.clone().requires_grad_(True)
        with torch.enable_grad():
            mvn = model.posterior(X).distribution
            mvn.mean.sum().backward()
    else:
        with torch.no_grad():
            mvn = model.posterior(X).distribution
    return mvn.mean.detach().double(), mvn.covariance_matrix.detach().double()


def _run(problem: Problem, run: str, Xq: Tensor) -> dict:
    """One model of :data:`RUNS`: its outcome, moments (``None`` where it raised) and seconds
    (building, the mode, the posterior with autograd off and on)."""
    dtype, laplace_dtype = RUNS[run]
    out: dict[str, Any] = {"error": None, "nan": False, "converged": None, "iterations": None}
    out.update(moments=None, jitter=None)
    t = time.perf_counter()
    try:
        model = build(problem, dtype, laplace_dtype)
        mode = model.mode
        out["converged"], out["iterations"] = bool(mode.converged), int(mode.iterations)
        out["jitter"] = float(model.jitter) / problem.outputscale  # the diagonal jitter of L
        out["moments"] = {grad: posterior_moments(model, Xq.to(dtype), grad) for grad in (False, True)}
        out["nan"] = not bool(torch.isfinite(mode.f).all()) or any(
            not (torch.isfinite(m).all() and torch.isfinite(S).all()) for m, S in out["moments"].values()
        )
    except Exception as e:
        out["error"] = f"{type(e).__name__}: {str(e)[:160]}"
    out["seconds"] = time.perf_counter() - t
    return out


def _pairwisegp(problem: Problem, Xq: Tensor) -> dict:
    """BoTorch's ``PairwiseGP`` in float32 on a comparisons-only problem."""
    from botorch.models.pairwise_gp import PairwiseGP

    out: dict[str, Any] = {"error": None, "nan": False}
    try:
        model = PairwiseGP(problem.X.to(F32), problem.comparisons, covar_module=kernel(problem, F32))
        mean, cov = posterior_moments(model, Xq.to(F32), grad=False)
        out["nan"] = not bool(torch.isfinite(mean).all() and torch.isfinite(cov).all())
    except Exception as e:
        out["error"] = f"{type(e).__name__}: {str(e)[:160]}"
    return out


def relative_gap(a: tuple[Tensor, Tensor], b: tuple[Tensor, Tensor], outputscale: float) -> tuple[float, float]:
    r"""``(mean gap, covariance gap)`` of moments ``a`` from the reference ``b``: the largest mean
    difference over ``max(max |mean_b|, sqrt(outputscale))``, the largest covariance difference over
    the prior variance ``outputscale``."""
    (ma, Sa), (mb, Sb) = a, b
    mean_scale = max(float(mb.abs().max()), math.sqrt(outputscale))
    return float((ma - mb).abs().max()) / mean_scale, float((Sa - Sb).abs().max()) / outputscale


def check(problem: Problem, pairwisegp: bool = True, runs: tuple[str, ...] = tuple(RUNS)) -> dict:
    """Run ``problem`` as the models ``runs`` of :data:`RUNS` (``f64`` always; and ``PairwiseGP``
    in float32 where it has only comparisons); a flat record of the outcomes (see the module
    docstring): ``{run}_error``, ``_nan``, ``_converged``, ``_iterations``, ``_jitter``,
    ``_seconds``, and for each float32 run ``{run}_gap_{mean,cov}_{nograd,grad}``."""
    Xq = query_points(problem)
    runs = ("f64",) + tuple(r for r in runs if r != "f64")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # jitter, boundary and float32 warnings are expected here
        order = runs[problem.seed % len(runs) :] + runs[: problem.seed % len(runs)]  # none always first (timing)
        res = {run: _run(problem, run, Xq) for run in order}
        pg = _pairwisegp(problem, Xq) if pairwisegp and problem.kind == "comparisons" else None
    rec = {
        "seed": problem.seed,
        "kind": problem.kind,
        "n": problem.n,
        "d": problem.X.shape[-1],
        "p": problem.comparisons.shape[0],
        "q": problem.ratings.shape[0],
        "lengthscale": problem.lengthscale,
        "outputscale": problem.outputscale,
    }
    for name, r in res.items():
        rec.update({f"{name}_{k}": r[k] for k in ("error", "nan", "converged", "iterations", "jitter", "seconds")})
    for name in runs[1:]:
        for grad in (False, True):
            tag = "grad" if grad else "nograd"
            gaps: tuple[float | None, float | None] = (None, None)
            if res["f64"]["moments"] is not None and res[name]["moments"] is not None:
                gaps = relative_gap(res[name]["moments"][grad], res["f64"]["moments"][False], problem.outputscale)
            rec[f"{name}_gap_mean_{tag}"], rec[f"{name}_gap_cov_{tag}"] = gaps
    rec["pairwisegp_error"] = pg["error"] if pg else None
    rec["pairwisegp_nan"] = pg["nan"] if pg else None
    return rec


# Hostile-start fits
#: Errors a hostile start may end in: documented and named (docs/robustness.md).
NAMED = ("ModelFittingError", "NotPSDError", "LaplaceNumericalError")


def _log_uniform_tensor(lo: float, hi: float, g: torch.Generator, shape=()) -> torch.Tensor:
    u = torch.rand(shape, generator=g, dtype=F64)
    return torch.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * u)


def hostile_model(seed: int, max_n: int = 15) -> tuple[Problem, PreferenceGP]:
    """The hostile problem of ``seed`` and a model started from hostile hyperparameters."""
    from gpytorch.kernels import RBFKernel, ScaleKernel

    from torchpref import PreferenceGP

    p = make_problem(seed, max_n=max_n, pairwise_likelihood=False)
    g = torch.Generator().manual_seed(10_000 + seed)
    d = p.X.shape[-1]
    kernel = ScaleKernel(RBFKernel(ard_num_dims=d)).to(F64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = PreferenceGP(
            p.X,
            p.comparisons if len(p.comparisons) else None,
            p.ratings if len(p.ratings) else None,
            p.rating_index if len(p.ratings) else None,
            covar_module=kernel,
            learn_likelihood=True,
        )
        kernel.base_kernel.lengthscale = _log_uniform_tensor(1e-4, 1e4, g, (1, d))
        kernel.outputscale = _log_uniform_tensor(1e-5, 1e5, g)
        model.comparison_likelihood.comparison_noise = _log_uniform_tensor(1e-4, 1e3, g)
        model.rating_likelihood.rating_scale = _log_uniform_tensor(1e-4, 1e3, g)
        model.rating_likelihood.rating_precision = _log_uniform_tensor(1.01e-2, 0.99e6, g)
    return p, model


def usable(model: PreferenceGP) -> str | None:
    """Why ``model`` is not usable after a fit (``None``: it is)."""
    if not all(bool(torch.isfinite(v).all()) for v in model.parameters()):
        return "non-finite hyperparameters"
    if not bool(torch.as_tensor(model.mode.converged).all()):
        return "mode not converged"
    Xq = torch.rand(4, model.train_X.shape[-1], generator=torch.Generator().manual_seed(1), dtype=F64)
    with torch.no_grad():
        post = model.posterior(Xq)
        if not (bool(torch.isfinite(post.mean).all()) and bool(torch.isfinite(post.variance).all())):
            return "non-finite posterior"
        if bool((post.variance < 0).any()):
            return "negative posterior variance"
    return None


def fit_outcome(seed: int, max_n: int = 15) -> dict:
    """Fit the hostile start of ``seed``; its outcome (``"fit"``, ``"unusable: ..."``, or the name
    of the exception raised), the exception's text and the time taken."""
    from botorch.fit import fit_gpytorch_mll

    from torchpref import LaplaceMarginalLogLikelihood

    p, model = hostile_model(seed, max_n)
    t0 = time.perf_counter()
    out = {"seed": seed, "n": p.n, "kind": p.kind}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fit_gpytorch_mll(LaplaceMarginalLogLikelihood(model))
            why = usable(model)
        out["outcome"] = "fit" if why is None else f"unusable: {why}"
    except Exception as err:  # recorded: the point of the benchmark
        out["outcome"] = type(err).__name__
        out["error"] = str(err).splitlines()[0][:200] if str(err) else ""
    out["seconds"] = round(time.perf_counter() - t0, 3)
    return out
