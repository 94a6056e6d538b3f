r"""BoTorch's ``fit_gpytorch_mll`` for a :class:`~torchpref.models.preference_gp.PreferenceGP`: the
whole fit compiled where it applies, BoTorch's own routine otherwise (issue 33, items 1 and 4).

``fit_gpytorch_mll(mll)`` calls the model's ``custom_fit`` (BoTorch's hook for models with their
own fitting routine), which comes here. Where the compiled path applies
(:mod:`torchpref.inference.fast_path`: one problem, CPU, float64, probit comparisons, and here a
``ScaleKernel`` of an ``RBFKernel`` or ``MaternKernel`` with softplus-constrained lengthscales and
outputscale, LogNormal / Gamma priors or none, nothing else trainable and no other prior) it runs
BoTorch's optimiser, SciPy's L-BFGS-B from the same raw parameters with the same bounds, on one
compiled call per evaluation (:func:`torchpref.inference._compiled.fit_loss`: kernel matrix and its
derivatives, Newton warm-started from the last mode, the evidence and its written-out gradient,
the priors and the constraints' chain rule). Anything else, any failure of the compiled
evaluation (a kernel matrix that needs jitter, a Newton solve that does not converge) and any
L-BFGS-B stop other than success or its iteration limit, goes to BoTorch's ``_fit_fallback`` from
the starting values, so that retries, warnings and errors are exactly BoTorch's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from gpytorch.constraints import GreaterThan, Positive
from gpytorch.kernels import MaternKernel, RBFKernel, ScaleKernel
from gpytorch.priors import GammaPrior, LogNormalPrior

from torchpref.data.preference_data import PreferenceData
from torchpref.inference.fast_path import FIT_MAX_ITEMS, compiled, known_probit, setting
from torchpref.inference.numerics import default_tolerance

#: GPyTorch kernel -> :mod:`torchpref.inference._compiled`'s kind (Matern by its ``nu``)
KINDS = {RBFKernel: 0, (MaternKernel, 0.5): 1, (MaternKernel, 1.5): 2, (MaternKernel, 2.5): 3}


@dataclass
class CompiledFit:
    """One model's fit problem as the compiled loss takes it."""

    X: np.ndarray
    C: np.ndarray
    scale: float
    kind: int
    spec: np.ndarray
    params: dict[str, torch.nn.Parameter]  # BoTorch's order: the raw parameters x
    f0: np.ndarray
    tol: float
    max_iter: int


def _constraint(module: Any, name: str) -> float | None:
    """The lower bound of a ``GreaterThan`` (or ``Positive``) constraint with torch's default
    softplus, else ``None``."""
    c = module.constraint_for_parameter_name(name)
    t = getattr(c, "_transform", None)
    ok = type(c) in (GreaterThan, Positive)
    if not (ok and c.enforced and isinstance(t, torch.nn.Softplus) and t.beta == 1.0 and t.threshold == 20.0):
        return None
    return float(c.lower_bound)


def _prior(prior: Any) -> tuple[float, float, float, float] | None:
    """``(kind, p1, p2, const)`` of :func:`torchpref.inference._compiled.log_prior`, or ``None``;
    ``const`` computed as the prior computes it (in its parameters' dtype)."""
    if prior is None:
        return (0.0, 0.0, 0.0, 0.0)
    if type(prior) is LogNormalPrior and prior.loc.numel() == 1 and prior.scale.numel() == 1:
        # as torch's Normal.log_prob takes them: the variance and log(scale) in the prior's dtype
        const = -float(prior.scale.log()) - 0.5 * math.log(2 * math.pi)
        return (1.0, float(prior.loc), math.sqrt(float(prior.scale**2)), const)
    if type(prior) is GammaPrior and prior.concentration.numel() == 1 and prior.rate.numel() == 1:
        a, b = prior.concentration, prior.rate
        return (2.0, float(a), float(b), float(torch.xlogy(a, b) - torch.lgamma(a)))
    return None


def _kernel(model: Any, d: int) -> tuple[int, torch.nn.Module, torch.nn.Module | None] | None:
    """``(kind, base kernel, scale kernel or None)`` for a supported kernel, else ``None``."""
    k = model.covar_module
    scale, base = (k, k.base_kernel) if type(k) is ScaleKernel else (None, k)
    key = RBFKernel if type(base) is RBFKernel else (type(base), getattr(base, "nu", None))
    kind = KINDS.get(key)
    if kind is None or any(m.active_dims is not None or len(m.batch_shape) for m in (base, scale) if m is not None):
        return None
    if base.raw_lengthscale.shape not in ((1, 1), (1, d)) or (scale is not None and scale.raw_outputscale.dim()):
        return None
    return kind, base, scale


def _priors(model: Any, base: torch.nn.Module, scale: torch.nn.Module | None) -> dict[str, Any] | None:
    """The kernel's two priors (``"ls"``, ``"os"``), or ``None`` where the model has any other."""
    found: dict[str, Any] = {"ls": None, "os": None}
    for module in model.modules():
        for name, (prior, _, _) in getattr(module, "_priors", {}).items():
            if module is base and name == "lengthscale_prior":
                found["ls"] = prior
            elif module is scale and name == "outputscale_prior":
                found["os"] = prior
            else:
                return None
    return found


def _spec(mll: Any, base, scale, priors) -> tuple[np.ndarray, dict] | None:
    """The compiled loss's ``spec`` and the trainable parameters in BoTorch's order (that of
    ``named_parameters``, as ``get_parameters_and_bounds``), or ``None``."""
    params = {name: p for name, p in mll.named_parameters() if p.requires_grad}
    wanted = [base.raw_lengthscale] + ([] if scale is None else [scale.raw_outputscale])
    if len(params) != len(wanted) or {id(p) for p in params.values()} != {id(p) for p in wanted}:
        return None
    ls_lower = _constraint(base, "raw_lengthscale")
    os_lower = 0.0 if scale is None else _constraint(scale, "raw_outputscale")
    ls_prior, os_prior = _prior(priors["ls"]), _prior(priors["os"])
    if ls_lower is None or os_lower is None or ls_prior is None or os_prior is None:
        return None
    count, ls_start, os_index, offset = base.raw_lengthscale.numel(), 0, -1, 0
    for t in params.values():
        if t is base.raw_lengthscale:
            ls_start = offset
        else:
            os_index = offset
        offset += t.numel()
    spec = [ls_start, count, os_index, ls_lower, os_lower, *ls_prior[:3], *os_prior[:3], 1.0, ls_prior[3], os_prior[3]]
    return np.array(spec, dtype=np.float64), params


def _probit_scale(model: Any, data: PreferenceData) -> float | None:
    """``sqrt 2 sigma_R`` where the data are comparisons only, scored by the probit the compiled
    path knows (:func:`torchpref.inference.fast_path.probit_scale`, read from the data directly)."""
    lik = model.likelihood.comparison
    if model.ties_offered or data.ratings.numel() or (data.ties is not None and data.ties.numel()):
        return None
    if not known_probit(lik) or not data.comparisons.shape[0]:
        return None
    return float(lik.scale)


def compiled_problem(mll: Any) -> CompiledFit | None:
    """The fit of ``mll`` (a :class:`~torchpref.models.preference_gp.LaplaceMarginalLogLikelihood`)
    as a compiled problem, or ``None`` where the compiled path does not apply."""
    model = mll.model
    data = model.data
    if not isinstance(data, PreferenceData) or data.n == 0 or model.laplace_dtype != torch.float64:
        return None
    if getattr(model, "mean_module", None) is not None or getattr(model, "prior_mean", None) is not None:
        return None  # a prior mean: the compiled path solves a zero-mean GP
    X = model._transformed_train_X().detach()
    if X.dtype != torch.float64 or X.device.type != "cpu":
        return None
    if setting() != "on" and X.shape[0] > FIT_MAX_ITEMS:
        return None
    s = _probit_scale(model, data)
    kernel = _kernel(model, X.shape[-1])
    if s is None or kernel is None:
        return None
    kind, base, scale = kernel
    priors = _priors(model, base, scale)
    found = None if priors is None else _spec(mll, base, scale, priors)
    if found is None:
        return None
    spec, params = found
    cache = model._cache
    f0 = cache.mode.f[0].detach().numpy().copy() if cache is not None else np.zeros(X.shape[0])
    C = np.ascontiguousarray(data.comparisons.numpy())
    tol = default_tolerance(torch.float64)
    return CompiledFit(np.ascontiguousarray(X.numpy()), C, s, kind, spec, params, f0, tol, model.max_newton_iter)


def run(problem: CompiledFit, module: Any) -> bool:
    """The whole fit in one compiled call (:func:`torchpref.inference._compiled.fit_lbfgs`: L-BFGS
    with SciPy's L-BFGS-B stopping rules, from the model's raw parameters); sets the parameters
    and returns ``True`` on success, leaves them unchanged and returns ``False`` otherwise."""
    p = problem
    x0 = np.concatenate([t.detach().reshape(-1).numpy() for t in p.params.values()]).astype(np.float64)
    try:
        x, _, status, _ = module.fit_lbfgs(x0, p.X, p.C, p.scale, p.kind, p.spec, p.f0.copy(), p.tol, p.max_iter)
    except (ArithmeticError, ValueError):  # numba raises where torch gives inf or NaN (a lengthscale of 0)
        return False
    if status != module.OK or not np.all(np.isfinite(x)):
        return False
    with torch.no_grad():
        offset = 0
        for t in p.params.values():
            n = t.numel()
            t.copy_(torch.from_numpy(x[offset : offset + n].copy()).reshape(t.shape))
            offset += n
    return True


def _leave_in_eval(mll: Any) -> Any:
    """``mll.eval()``, as BoTorch's routine leaves it; a switch walks every module, so where the
    model and likelihood already are in eval mode only the MLL's own flag is set."""
    if any(m.training for m in mll.model.modules()) or any(m.training for m in mll.likelihood.modules()):
        return mll.eval()
    mll.training = False
    return mll


def fit_laplace(
    mll: Any,
    closure: Any = None,
    closure_kwargs: dict[str, Any] | None = None,
    optimizer_kwargs: dict[str, Any] | None = None,
    **kwargs: Any,
) -> Any:
    """``fit_gpytorch_mll(mll)`` for a Laplace MLL: compiled where it applies (and nothing but the
    defaults was asked for: no closure, optimizer or their arguments), else BoTorch's routine."""
    from botorch.fit import _fit_fallback
    from botorch.optim.fit import fit_gpytorch_mll_scipy

    default = closure is None and closure_kwargs is None and not optimizer_kwargs
    default = default and kwargs.get("optimizer", fit_gpytorch_mll_scipy) is fit_gpytorch_mll_scipy
    if default:
        problem = compiled_problem(mll)
        module = None if problem is None else compiled(load=True)
        if problem is not None and module is not None and run(problem, module):
            return _leave_in_eval(mll)
    kwargs.pop("optimizer", None) if kwargs.get("optimizer") is None else None
    return _fit_fallback(
        mll, closure=closure, closure_kwargs=closure_kwargs, optimizer_kwargs=optimizer_kwargs, **kwargs
    )
