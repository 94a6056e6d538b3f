r"""BoTorch's ``fit_gpytorch_mll`` for a :class:`~torchpref.models.preference_gp.PreferenceGP`: the
whole fit compiled where it applies, BoTorch's own routine otherwise (issues 33, 42 and 52).

``fit_gpytorch_mll(mll)`` calls the model's ``custom_fit`` (BoTorch's hook for models with their
own fitting routine), which comes here. Where the compiled path applies
(:mod:`torchpref.inference.fast_path`: one problem, CPU, float64, the likelihoods it knows with
their parameters fixed, a fixed prior mean or none, and here a ``ScaleKernel`` of an ``RBFKernel`` or
``MaternKernel`` with softplus-constrained lengthscales and outputscale, LogNormal / Gamma priors or
none, nothing else trainable and no other prior) the whole L-BFGS fit is one compiled call
(:func:`torchpref.inference._compiled_fit.fit_lbfgs`: kernel matrix and its derivatives, Newton
warm-started from the last mode, the evidence and its written-out gradient, the priors and the
constraints' chain rule, from the model's raw parameters), and its last mode and factors become the
model's posterior cache (the next prediction solves nothing). Anything else, and a compiled fit
that fails at its first evaluation (a kernel matrix that is not positive definite, a Newton solve
that does not converge) or stalls before any step, goes to BoTorch's ``_fit_fallback`` from the
starting values, so that retries, warnings and errors are exactly BoTorch's. Either way the model's
``last_fit`` (:class:`FitReport`) says which solver fitted and how it stopped.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

import numpy as np
import torch
from gpytorch.constraints import GreaterThan, Interval, Positive
from gpytorch.kernels import Kernel, MaternKernel, RBFKernel, ScaleKernel
from gpytorch.module import Module
from gpytorch.priors import GammaPrior, LogNormalPrior, Prior
from torch import Tensor

import torchpref.inference.fast_types as ft
from torchpref.data.preference_data import PreferenceData
from torchpref.inference.fast_path import FIT_MAX_ITEMS, answers, call, compiled, known, setting
from torchpref.inference.laplace import ModeResult, Observations
from torchpref.inference.numerics import default_tolerance
from torchpref.inference.padding import PaddedData
from torchpref.inference.solver import PosteriorState

#: GPyTorch kernel -> the compiled kernel kind (Matern by its ``nu``)
KINDS = {
    RBFKernel: ft.RBF,
    (MaternKernel, 0.5): ft.MATERN12,
    (MaternKernel, 1.5): ft.MATERN32,
    (MaternKernel, 2.5): ft.MATERN52,
}


class LaplaceModel(Protocol):
    """What the compiled fit reads and sets of a :class:`~torchpref.models.preference_gp.PreferenceGP`
    (a Protocol: that module imports this one)."""

    @property
    def covar_module(self) -> Kernel:
        """The kernel."""

    @property
    def data(self) -> PreferenceData | PaddedData:
        """The observations."""

    @property
    def laplace_dtype(self) -> torch.dtype:
        """The dtype of the Laplace solve."""

    @property
    def max_newton_iter(self) -> int:
        """The mode finder's iteration budget."""

    @property
    def _cache(self) -> PosteriorState | None: ...

    def modules(self) -> Iterator[torch.nn.Module]:
        """The model and its submodules (their priors)."""

    def _transformed_train_X(self) -> Tensor: ...

    def _padded(self) -> PaddedData: ...

    def _item_mean(self, padded: PaddedData) -> Tensor | None: ...

    def _observations(self) -> Observations: ...

    def _adopt_mode(self, L: Tensor, jitter: float, mode: ModeResult) -> None: ...

    last_fit: FitReport | None


class LaplaceMLL(Protocol):
    """What the compiled fit reads and sets of a
    :class:`~torchpref.models.preference_gp.LaplaceMarginalLogLikelihood` (its model and likelihood,
    its trainable parameters, its mode)."""

    training: bool

    @property
    def model(self) -> LaplaceModel:
        """The model fitted."""

    @property
    def likelihood(self) -> torch.nn.Module:
        """The model's likelihood module."""

    def named_parameters(self) -> Iterator[tuple[str, torch.nn.Parameter]]:
        """The parameters by name, in BoTorch's order."""

    def eval(self) -> torch.nn.Module:
        """Evaluation mode for the MLL, its model and likelihood."""


MLL = TypeVar("MLL", bound=LaplaceMLL)

#: BoTorch's closure of a fit: ``() -> (loss, gradients)`` (``fit_gpytorch_mll``'s ``closure``)
Closure = Callable[[], tuple[Tensor, Sequence[Tensor | None]]]


@dataclass
class CompiledFit:
    """One model's fit problem as the compiled fit takes it."""

    X: np.ndarray
    answers: ft.Answers
    spec: ft.FitSpec
    params: dict[str, torch.nn.Parameter]  # BoTorch's order: the raw parameters x
    f0: np.ndarray
    sizes: tuple[int, ...]  # the answers of each observation term, in order
    tol: float
    max_iter: int


def _constraint(module: Module, name: str) -> float | None:
    """The lower bound of a ``GreaterThan`` (or ``Positive``) constraint with torch's default
    softplus, else ``None``."""
    c = module.constraint_for_parameter_name(name)
    t = getattr(c, "_transform", None)
    ok = type(c) in (GreaterThan, Positive)
    if not (ok and c.enforced and isinstance(t, torch.nn.Softplus) and t.beta == 1.0 and t.threshold == 20.0):
        return None
    return float(c.lower_bound)


def _nu_constraint(module: Module) -> tuple[int, float, float] | None:
    """``(transform, lower, upper)`` of the rating precision's constraint: GPyTorch's ``Interval``
    with its sigmoid, or a ``GreaterThan`` / ``Positive`` with torch's default softplus; else ``None``."""
    c = module.constraint_for_parameter_name("raw_rating_precision")
    if type(c) is Interval and c.enforced and getattr(c, "_transform", None) is torch.sigmoid:
        return ft.SIGMOID, float(c.lower_bound), float(c.upper_bound)
    lower = _constraint(module, "raw_rating_precision")
    return None if lower is None else (ft.SOFTPLUS, lower, 0.0)


def _rating(model: LaplaceModel) -> Module | None:
    """The model's Beta rating likelihood, where the compiled path knows it (its precision may be
    fitted), else ``None``."""
    rating = getattr(getattr(model, "likelihood", None), "rating", None)
    return rating if rating is not None and known(rating, "beta") else None


def _prior(prior: Prior | None) -> ft.Prior | None:
    """The compiled :class:`~torchpref.inference.fast_types.Prior` of a GPyTorch prior, or ``None``;
    its ``const`` computed as the prior computes it (in its parameters' dtype)."""
    if prior is None:
        return ft.prior(ft.NO_PRIOR, 0.0, 0.0, 0.0)
    if type(prior) is LogNormalPrior and prior.loc.numel() == 1 and prior.scale.numel() == 1:
        # as torch's Normal.log_prob takes them: the variance and log(scale) in the prior's dtype
        const = -float(prior.scale.log()) - 0.5 * math.log(2 * math.pi)
        return ft.prior(ft.LOG_NORMAL, float(prior.loc), math.sqrt(float(prior.scale**2)), const)
    if type(prior) is GammaPrior and prior.concentration.numel() == 1 and prior.rate.numel() == 1:
        a, b = prior.concentration, prior.rate
        return ft.prior(ft.GAMMA, float(a), float(b), float(torch.xlogy(a, b) - torch.lgamma(a)))
    return None


def _kernel(model: LaplaceModel, d: int) -> tuple[int, torch.nn.Module, torch.nn.Module | None] | None:
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


def _priors(
    model: LaplaceModel, base: torch.nn.Module, scale: torch.nn.Module | None, rating: Module | None
) -> dict[str, Any] | None:
    """The kernel's two priors (``"ls"``, ``"os"``) and the Beta rating precision's (``"nu"``), or
    ``None`` where the model has any other."""
    found: dict[str, Any] = {"ls": None, "os": None, "nu": None}
    for module in model.modules():
        for name, (prior, _, _) in getattr(module, "_priors", {}).items():
            if module is base and name == "lengthscale_prior":
                found["ls"] = prior
            elif module is scale and name == "outputscale_prior":
                found["os"] = prior
            elif rating is not None and module is rating and name == "rating_precision_prior":
                found["nu"] = prior
            else:
                return None
    return found


def _spec(mll: LaplaceMLL, kind: int, base, scale, priors, rating) -> tuple[ft.FitSpec, dict] | None:
    """The compiled fit's :class:`~torchpref.inference.fast_types.FitSpec` and the trainable
    parameters in BoTorch's order (that of ``named_parameters``, as ``get_parameters_and_bounds``),
    or ``None``. Trainable may be the kernel's lengthscales and outputscale and the Beta ratings'
    precision (issue 52), nothing else."""
    params = {name: p for name, p in mll.named_parameters() if p.requires_grad}
    wanted = [base.raw_lengthscale] + ([] if scale is None else [scale.raw_outputscale])
    learn_nu = rating is not None and rating.raw_rating_precision.requires_grad
    wanted += [rating.raw_rating_precision] if learn_nu else []
    if len(params) != len(wanted) or {id(p) for p in params.values()} != {id(p) for p in wanted}:
        return None
    ls_lower = _constraint(base, "raw_lengthscale")
    os_lower = 0.0 if scale is None else _constraint(scale, "raw_outputscale")
    nu_constraint = _nu_constraint(rating) if learn_nu else (ft.SOFTPLUS, 0.0, 0.0)
    ls_prior, os_prior, nu_prior = _prior(priors["ls"]), _prior(priors["os"]), _prior(priors["nu"])
    if ls_lower is None or os_lower is None or ls_prior is None or os_prior is None:
        return None
    if nu_constraint is None or nu_prior is None:
        return None
    nu_transform, nu_lower, nu_upper = nu_constraint
    count, ls_start, os_index, nu_index, offset = base.raw_lengthscale.numel(), 0, -1, -1, 0
    for t in params.values():
        if t is base.raw_lengthscale:
            ls_start = offset
        elif learn_nu and t is rating.raw_rating_precision:
            nu_index = offset
        else:
            os_index = offset
        offset += t.numel()
    spec = ft.fit_spec(
        kind,
        ls_start,
        count,
        ls_lower,
        ls_prior,
        os_index,
        os_lower,
        os_prior,
        1.0,
        nu_index,
        nu_transform,
        nu_lower,
        nu_upper,
        nu_prior,
    )
    return spec, params


def _answers(model: LaplaceModel, X: torch.Tensor) -> tuple[ft.Answers, tuple[int, ...]] | None:
    """The model's observations (shifted by its prior mean, fixed during the fit) as compiled
    :class:`~torchpref.inference.fast_types.Answers` and the number of each term's, or ``None``."""
    obs = model._observations()
    with torch.no_grad():
        mean = model._item_mean(model._padded().with_items(X))
    obs = obs.shifted(None if mean is None else mean.detach())
    found = answers(obs)
    return None if found is None else (found, tuple(t.size for t in obs.terms))


def compiled_problem(mll: LaplaceMLL) -> CompiledFit | None:
    """The fit of ``mll`` (a :class:`~torchpref.models.preference_gp.LaplaceMarginalLogLikelihood`)
    as a compiled problem, or ``None`` where the compiled path does not apply."""
    model = mll.model
    data = model.data
    if not isinstance(data, PreferenceData) or data.n == 0 or model.laplace_dtype != torch.float64:
        return None
    X = model._transformed_train_X().detach()
    if X.dtype != torch.float64 or X.device.type != "cpu":
        return None
    if setting() != "on" and X.shape[0] > FIT_MAX_ITEMS:
        return None
    kernel = _kernel(model, X.shape[-1])
    if kernel is None:
        return None
    kind, base, scale = kernel
    rating = _rating(model)
    priors = _priors(model, base, scale, rating)
    found = None if priors is None else _spec(mll, kind, base, scale, priors, rating)
    rows = None if found is None else _answers(model, X)
    if found is None or rows is None:
        return None
    spec, params = found
    if rating is not None:  # the answers' precision is the model's (also where none is a rating: its prior's value)
        rows = (rows[0]._replace(rating_precision=float(rating.rating_precision.detach())), rows[1])
    cache = model._cache
    f0 = cache.mode.f[0].detach().numpy().copy() if cache is not None else np.zeros(X.shape[0])
    tol = default_tolerance(torch.float64)
    return CompiledFit(ft.floats(X.numpy(), 2), rows[0], spec, params, f0, rows[1], tol, model.max_newton_iter)


@dataclass(frozen=True)
class FitReport:
    """How the last ``fit_gpytorch_mll`` of a model went (``model.last_fit``): which solver fitted
    it (``"compiled"``: one numba call, :func:`run`; ``"torch"``: BoTorch's routine on the torch
    solver), how it stopped or why the compiled fit did not answer (``status``), and, for a compiled
    fit, L-BFGS's iterations and loss evaluations."""

    solver: str
    status: str
    iterations: int | None = None
    evaluations: int | None = None


def run(problem: CompiledFit) -> tuple[ft.FitState | None, FitReport]:
    """The whole fit in one compiled call (:func:`torchpref.inference._compiled_fit.fit_lbfgs`:
    L-BFGS with SciPy's L-BFGS-B stopping rules, from the model's raw parameters): on success
    (converged, or stalled at its last good point after at least one step: SciPy's abnormal
    termination in the line search) the parameters are set and the final mode and factors returned
    with the report; otherwise the parameters are left unchanged and ``None`` returned, with the
    report saying why."""
    p = problem
    x0 = ft.floats(np.concatenate([t.detach().reshape(-1).numpy() for t in p.params.values()]))
    state = ft.fit_state(p.f0, p.answers.first.shape[0])
    out = call("fit_lbfgs", x0, p.X, p.answers, p.spec, state, float(p.tol), int(p.max_iter))
    if out is None:
        return None, FitReport("torch", "the compiled fit raised or is off in this process")
    name = ft.STATUS_NAMES.get(out.status, str(out.status))
    report = FitReport("compiled", name, int(out.iterations), int(out.evaluations))
    if out.status not in ft.SUCCESS or (out.status == ft.STALLED and out.iterations == 0):
        return None, FitReport("torch", f"the compiled fit stopped: {name}", report.iterations, report.evaluations)
    x = out.x
    with torch.no_grad():
        offset = 0
        for t in p.params.values():
            n = t.numel()
            t.copy_(torch.from_numpy(x[offset : offset + n].copy()).reshape(t.shape))
            offset += n
    return state, report


def hand_back(model: LaplaceModel, problem: CompiledFit, state: ft.FitState) -> None:
    """The compiled fit's last mode and factors (at the fitted hyperparameters) as the model's
    posterior cache (:meth:`~torchpref.models.preference_gp.PreferenceGP._adopt_mode`)."""
    w = torch.from_numpy(state.w)
    weights = tuple(part[None] for part in torch.split(w, list(problem.sizes)))
    one, no = torch.ones(1, dtype=torch.bool), torch.zeros(1, dtype=torch.bool)
    a, f, M = (torch.from_numpy(v)[None] for v in (state.a, state.f, state.M))
    mode = ModeResult(a, f, M, weights, int(state.iterations[0]), one, no, solver="compiled")
    model._adopt_mode(torch.from_numpy(state.L)[None], float(state.jitter[0]), mode)


def _leave_in_eval(mll: MLL) -> MLL | torch.nn.Module:
    """``mll.eval()``, as BoTorch's routine leaves it; a switch walks every module, so where the
    model and likelihood already are in eval mode only the MLL's own flag is set."""
    if any(m.training for m in mll.model.modules()) or any(m.training for m in mll.likelihood.modules()):
        return mll.eval()
    mll.training = False
    return mll


def fit_laplace(
    mll: MLL,
    closure: Closure | None = None,
    closure_kwargs: dict[str, Any] | None = None,
    optimizer_kwargs: dict[str, Any] | None = None,
    **kwargs: Any,
) -> MLL:
    """``fit_gpytorch_mll(mll)`` for a Laplace MLL: compiled where it applies (and nothing but the
    defaults was asked for: no closure, optimizer or their arguments), else BoTorch's routine."""
    from botorch.fit import _fit_fallback
    from botorch.optim.fit import fit_gpytorch_mll_scipy

    default = closure is None and closure_kwargs is None and not optimizer_kwargs
    default = default and kwargs.get("optimizer", fit_gpytorch_mll_scipy) is fit_gpytorch_mll_scipy
    report = FitReport("torch", "arguments other than the defaults were given")
    if default:
        problem = compiled_problem(mll) if setting() != "off" else None
        if problem is None:
            report = FitReport("torch", "the compiled fit does not apply to this model or setting")
        elif compiled() is None:
            report = FitReport("torch", "the compiled path is not loaded in this process")
        else:
            state, report = run(problem)
            if state is not None:
                _leave_in_eval(mll)
                hand_back(mll.model, problem, state)
                mll.model.last_fit = report
                return mll
    kwargs.pop("optimizer", None) if kwargs.get("optimizer") is None else None
    mll.model.last_fit = report
    return _fit_fallback(
        mll, closure=closure, closure_kwargs=closure_kwargs, optimizer_kwargs=optimizer_kwargs, **kwargs
    )
