r""":func:`fit_population`: the hierarchical model of many people's answers, fitted by its evidence.

The population mean ``m ~ GP(0, k_m)`` and each person's deviation ``g_p ~ GP(0, k_g)`` are
fitted together: the hyperparameters of both kernels (``k_m``'s lengthscales and outputscale; ``k_g``'s
lengthscales and its outputscale ``s^2``, the between-person spread) maximise the Laplace
evidence of **all** people's answers plus the kernels' hyperparameter priors, the joint mode
solved through the problem's structure (:mod:`torchpref.population.joint`), in process or over
shards of people on an executor, by one Newton loop. The mean is represented at every distinct
item (exact) up to :data:`EXACT_ITEMS` of them, and at :data:`DEFAULT_INDUCING` inducing items
above (:mod:`torchpref.population.inducing`); the population records which.
"""

from __future__ import annotations

import logging
import math
import numbers
from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Any

import torch
from gpytorch.kernels import Kernel
from gpytorch.module import Module
from torch import Tensor
from tqdm.auto import tqdm

from torchpref.data.preference_data import PreferenceData
from torchpref.inference.numerics import cholesky_jittered
from torchpref.models.defaults import default_covar_module
from torchpref.models.recipe import DEFAULT_MODEL, ModelSettings
from torchpref.population.hosts import host_for, workers_of
from torchpref.population.inducing import METHODS, choose_items
from torchpref.population.joint import Gradient, Shards, newton
from torchpref.population.lbfgs import FitStartError, minimise
from torchpref.population.memory import ShardSize, check_memory, estimate_peak, gigabytes, shard_transient
from torchpref.population.model import Population
from torchpref.population.people import Items, by_rows, check_people, shard_bounds, shard_data, warn_outside_unit_cube
from torchpref.population.prior import _dense
from torchpref.population.shards import Basis

__all__ = ["fit_population", "check_people", "EXACT_ITEMS", "DEFAULT_INDUCING"]

#: ``inducing="auto"`` represents the mean at every distinct item up to this many of them.
EXACT_ITEMS = 2000
#: ``inducing="auto"``'s number of inducing items above :data:`EXACT_ITEMS` distinct items.
DEFAULT_INDUCING = 256
#: In process, people are split into shards so that one shard's gradient holds at most about
#: this many bytes at once (the shards are worked one after another).
SHARD_BYTES = 2**29

log = logging.getLogger("torchpref.population")
#: what solves the population's joint mode (``stats["solver"]``): the torch Newton loop of
#: :mod:`torchpref.population.joint`, whatever the compiled path's setting. The compiled path
#: (:mod:`torchpref.inference.fast_path`) solves one person's problem; the population's is many
#: people's deviations and the shared mean at once, through a Schur complement over shards, which
#: it has no compiled form of. A person model built from the population is solved compiled.
SOLVER = "torch"


class _Kernels(Module):
    """``k_m`` and ``k_g`` together: their parameters and priors."""

    def __init__(self, k_m: Kernel, k_g: Kernel):
        super().__init__()
        self.k_m, self.k_g = k_m, k_g

    def log_prior(self) -> Tensor:
        out = torch.zeros((), dtype=torch.float64)
        for _, module, prior, closure, _ in self.named_priors():
            out = out + prior.log_prob(closure(module)).sum()
        return out


def _free(k: Module) -> list[Tensor]:
    return [p for p in k.parameters() if p.requires_grad]


@dataclass(frozen=True)
class Plan:
    """The fit laid out before anything large is allocated: the people's distinct items, the
    rows of ``U`` the mean is represented at (``z_rows``; all of them for ``exact``), the shards'
    people and sizes, and the estimated peak memory."""

    items: Items
    exact: bool
    method: str
    z_rows: Tensor
    bounds: list[tuple[int, int]]
    sizes: list[ShardSize]
    peak: int

    @property
    def M(self) -> int:
        return int(self.z_rows.shape[0])

    def describe(self) -> str:
        N, P = self.items.U.shape[0], len(self.items.offsets) - 1
        mean = f"exact mean at all N = {N} items" if self.exact else f"mean at M = {self.M} of N = {N} items"
        n = max(s.items for s in self.sizes)
        return f"{P} people, n <= {n} items each, {mean}, {len(self.sizes)} shard(s); peak about {gigabytes(self.peak)}"


def _sizes(items: Items, bounds: list[tuple[int, int]], M: int) -> list[ShardSize]:
    out = []
    for start, stop in bounds:
        ids = items.ids[int(items.offsets[start]) : int(items.offsets[stop])]
        P, N_s = stop - start, int(torch.unique(ids).shape[0])
        n = int((items.offsets[start + 1 : stop + 1] - items.offsets[start:stop]).max())
        out.append(ShardSize(P, n, N_s, by_rows(P, n, N_s, M)))
    return out


def _shard_count(items: Items, M: int, executor: object, shards: int | None) -> int:
    """The number of shards: ``shards`` if given; else, on an executor, two per worker; and at
    least enough that one shard's work fits :data:`SHARD_BYTES`."""
    if shards is not None:
        if isinstance(shards, bool) or not isinstance(shards, numbers.Integral) or shards < 1:
            raise ValueError(f"shards must be a positive integer, got {shards!r}.")
        return int(shards)
    P = len(items.offsets) - 1
    one = _sizes(items, [(0, P)], M)[0]
    k = math.ceil(8 * shard_transient(one, M) / SHARD_BYTES)
    if executor is not None:
        k = max(k, 2 * (workers_of(executor) or 2))
    return max(1, min(k, P))


def plan_fit(
    people: Sequence[PreferenceData],
    inducing: int | str | None,
    method: str,
    k_m: Kernel,
    executor: object,
    shards: int | None,
    memory_limit: int | None,
) -> Plan:
    """The :class:`Plan` of a fit, refused (naming the estimate and the way out) where its peak
    would exceed ``memory_limit``."""
    items = Items.of(people)
    N, d = items.U.shape
    exact = inducing is None or (inducing == "auto" and N <= EXACT_ITEMS)
    M = min(N if exact or inducing is None else (DEFAULT_INDUCING if inducing == "auto" else int(inducing)), N)
    bounds = shard_bounds(len(people), _shard_count(items, M, executor, shards))
    sizes = _sizes(items, bounds, M)
    peak = estimate_peak(sizes, N, M, d)
    what = f"{len(people)} people, N = {N} distinct items, the mean at M = {M} of them"
    alt = min(DEFAULT_INDUCING, max(N // 4, 1)) if exact or M > DEFAULT_INDUCING else max(M // 2, 1)
    alt_peak = estimate_peak(_sizes(items, bounds, alt), N, alt, d)
    check_memory(peak, memory_limit, what, f"fit with inducing={alt} (about {gigabytes(alt_peak)}) or fewer people")
    rows = torch.arange(N) if exact else choose_items(items.U, M, method, k_m)
    return Plan(items, exact, "exact" if exact else method, rows, bounds, sizes, peak)


@dataclass(frozen=True)
class Evaluation:
    """One evaluation of the evidence: its value, the mode's ``a`` and Schur factor, and ``L_Z``
    (with its jitter); the shards' states are not kept here (they rest in :class:`Shards`)."""

    evidence: float
    a: Tensor
    S_chol: Tensor
    L_Z: Tensor
    jitter: float


@dataclass
class Counters:
    """Evaluations, Newton steps, and the bytes crossing to and from the shards during Newton's
    steps (the per-step figure) and otherwise (each evaluation's start and gradient)."""

    evaluations: int = 0
    newton_steps: int = 0
    newton_bytes: int = 0
    other_bytes: int = 0


class Objective:
    """``-(evidence + log priors)`` of the kernels' hyperparameters, with its gradient; the mode
    re-solved at each evaluation from the last one's (``settings``: the likelihoods')."""

    def __init__(self, kernels: _Kernels, Z: Tensor, problem: Shards, settings: dict[str, Any]):
        self.kernels, self.Z, self.problem, self.settings = kernels, Z, problem, settings
        self.last: Evaluation | None = None
        self.counters = Counters()

    def __call__(self, with_gradient: bool = True) -> Tensor:
        k, last, traffic, c = self.kernels, self.last, self.problem.host.traffic, self.counters
        with torch.no_grad():
            K = _dense(k.k_m, self.Z, self.Z)
            L_Z, jitter = cholesky_jittered(K, None if last is None else last.jitter, "k_m(Z, Z)")
            a0 = L_Z.new_zeros(L_Z.shape[-1]) if last is None else self._warm(last, L_Z)
            b0 = traffic.total
            start = self.problem.start(Basis(self.Z, L_Z, k.k_m, k.k_g), a0)
            b1 = traffic.total
            mode = newton(self.problem, start)
            c.newton_steps, c.newton_bytes = c.newton_steps + mode.iterations, c.newton_bytes + traffic.total - b1
            value = mode.evidence()
            assert mode.hessian.S_chol is not None  # a mode's Hessian is factorised
            b2 = traffic.total
            grad = self.problem.gradient(mode) if with_gradient else None
            c.other_bytes += (b1 - b0) + (traffic.total - b2)
        c.evaluations += 1
        self.problem.keep(mode)
        self.last = Evaluation(float(value), mode.point.a, mode.hessian.S_chol, L_Z, jitter)
        loss = -(value + k.log_prior())
        return loss if grad is None else loss - self._linear(grad, jitter)

    @staticmethod
    def _warm(last: Evaluation, L_Z: Tensor) -> Tensor:
        """The last mode's ``a`` for the new ``L_Z``: the same mean at ``Z``, ``L_Z^{-1} m(Z)``."""
        u = last.L_Z @ last.a.unsqueeze(-1)
        return torch.linalg.solve_triangular(L_Z, u, upper=False).squeeze(-1)

    def _linear(self, grad: Gradient, jitter: float) -> Tensor:
        """``T - T.detach()``: the gradient's values on the kernels' parameters, ``L_Z`` chained
        through ``k_m`` by autograd here."""
        k = self.kernels
        K = _dense(k.k_m, self.Z, self.Z)
        L = torch.linalg.cholesky(K + jitter * torch.eye(K.shape[-1], dtype=K.dtype, device=K.device))
        T = (L * grad.L_Z).sum()
        for p, g in zip(_free(k.k_m), grad.k_m):
            T = T + (p * g).sum()
        for p, g in zip(_free(k.k_g), grad.k_g):
            T = T + (p * g).sum()
        return T - T.detach()


def _lbfgs(objective: Objective, params: list[Tensor], max_iter: int, bar: tqdm) -> None:
    """Minimise the objective with L-BFGS (strong Wolfe line search), a step meeting a non-finite
    evidence or a matrix that is not positive definite rejected (:func:`~torchpref.population.lbfgs.minimise`)."""
    minimise(objective, params, max_iter, bar, lambda: _describe_kernels(objective.kernels))


def _finite_last(objective: Objective) -> Evaluation:
    """The objective's last evaluation, whose evidence must be finite (else a :class:`FitStartError` naming the kernels)."""
    last = objective.last
    assert last is not None
    if not math.isfinite(last.evidence):
        raise FitStartError(
            f"the population's evidence is not finite ({last.evidence}) at the hyperparameters "
            f"({_describe_kernels(objective.kernels)}): start from longer lengthscales, or from the default kernels."
        )
    return last


def _describe_kernels(k: _Kernels) -> str:
    """The kernels' lengthscales and outputscales in a few words (for an error)."""
    out = []
    for name, kernel in (("k_m", k.k_m), ("k_g", k.k_g)):
        ls = getattr(getattr(kernel, "base_kernel", kernel), "lengthscale", None)
        os_ = getattr(kernel, "outputscale", None)
        parts = [] if ls is None else [f"lengthscale {[float(f'{v:.3g}') for v in ls.detach().flatten().tolist()]}"]
        parts += [] if os_ is None else [f"outputscale {float(os_.detach()):.3g}"]
        out.append(f"{name}: {', '.join(parts) or type(kernel).__name__}")
    return "; ".join(out)


def _refuse_fork(executor: object) -> None:
    """A process pool that forks is refused by name: a child forked from a process whose torch
    has started its thread pools can deadlock in its first factorisation (seen in a test run)."""
    context = getattr(executor, "_mp_context", None)  # concurrent.futures.ProcessPoolExecutor's
    if context is not None and context.get_start_method() == "fork":
        raise ValueError(
            "a ProcessPoolExecutor that forks can deadlock in torch's threads; give it "
            "mp_context=multiprocessing.get_context('spawn') (or 'forkserver')."
        )


def _check_settings(
    people: list[PreferenceData], names: object, max_iter: object, inducing: object, method: str
) -> None:
    d = people[0].train_X.shape[-1]
    if names is not None and (not isinstance(names, Sequence) or isinstance(names, str) or len(names) != d):
        raise ValueError(f"feature_names must name the {d} features, got {names!r}.")
    if isinstance(max_iter, bool) or not isinstance(max_iter, numbers.Integral) or max_iter < 1:
        raise ValueError(f"max_iter must be a positive integer, got {max_iter!r}.")
    positive = isinstance(inducing, numbers.Integral) and not isinstance(inducing, bool) and int(inducing) >= 1
    if not (inducing is None or inducing == "auto" or positive):
        raise ValueError(f"inducing must be 'auto', None (exact) or a positive integer, got {inducing!r}.")
    if method not in METHODS:
        raise ValueError(f"inducing_method must be one of {list(METHODS)}, got {method!r}.")


def _model_settings(
    people: Sequence[PreferenceData],
    model: ModelSettings | None,
    noise: float | None,
    scale: float | None,
    precision: float | None,
) -> ModelSettings:
    """The person model's settings of a fit: ``model`` (default :data:`~torchpref.models.recipe.DEFAULT_MODEL`)
    with the likelihood settings given and the people's rating levels."""
    base = model if model is not None else DEFAULT_MODEL
    if not isinstance(base, ModelSettings):
        raise ValueError(f"model must be a torchpref ModelSettings, got {type(base).__name__}.")
    given = {"comparison_noise": noise, "rating_scale": scale, "rating_precision": precision}
    for key, value in given.items():
        if value is not None and not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValueError(f"{key} must be a finite positive number, got {value!r}.")
    changes = {k: float(v) for k, v in given.items() if v is not None}
    return base.with_(**changes, rating_levels=people[0].rating_levels)


def _stats(people: list[PreferenceData], plan: Plan, objective: Objective) -> dict[str, Any]:
    assert objective.last is not None  # evaluated at least once
    c = objective.counters
    return dict(
        people=len(people),
        items=int(plan.items.U.shape[0]),
        answers=sum(p.num_observations for p in people),
        evidence=objective.last.evidence,
        mean="exact" if plan.exact else "inducing",
        inducing_items=plan.M,
        inducing_method=plan.method,
        shards=len(plan.bounds),
        memory_estimate_bytes=plan.peak,
        evaluations=c.evaluations,
        newton_steps=c.newton_steps,
        bytes_per_newton_step=round(c.newton_bytes / max(c.newton_steps, 1)),
        bytes_per_evaluation_besides=round(c.other_bytes / max(c.evaluations, 1)),
        solver=SOLVER,
    )


def fit_population(
    people: Sequence[PreferenceData],
    *,
    k_m: Kernel | None = None,
    k_g: Kernel | None = None,
    model: ModelSettings | None = None,
    comparison_noise: float | None = None,
    rating_scale: float | None = None,
    rating_precision: float | None = None,
    fit: bool = True,
    max_iter: int = 100,
    feature_names: Sequence[str] | None = None,
    names: Sequence[str] | None = None,
    inducing: int | str | None = "auto",
    inducing_method: str = "kmeans",
    memory_limit: int | None = None,
    progress: bool = False,
    executor: Executor | object | None = None,
    shards: int | None = None,
) -> Population:
    r"""The population of ``people`` (one :class:`~torchpref.data.preference_data.PreferenceData` each;
    comparisons, ratings and ties, all in the same ``d`` features, items in the unit cube):
    the mean utility and the between-person spread fitted together (module docstring).

    Args:
        k_m, k_g: the kernels of the mean and of a person's deviation (default
            :func:`~torchpref.models.defaults.default_covar_module` each, with its priors).
        model: the person model's settings (:class:`~torchpref.models.recipe.ModelSettings`; default
            :data:`~torchpref.models.recipe.DEFAULT_MODEL`, a session's): the likelihoods, fixed, and
            whether ties are offered; ordinal people's ``rating_levels`` from the data. A person model
            of the population has the same (:meth:`~torchpref.Population.person_model`).
        comparison_noise, rating_scale, rating_precision: override ``model``'s.
        fit: optimise the kernels' hyperparameters (L-BFGS on the evidence); ``False`` keeps them.
        max_iter: L-BFGS iterations.
        feature_names: the features' names (the objective space), kept with the population (and
            its file) so that it is refused for items of another space. ``names``: the same.
        inducing: where the mean is represented. ``"auto"``: at every distinct item (exact) up to
            :data:`EXACT_ITEMS` of them, else at :data:`DEFAULT_INDUCING` inducing items;
            ``None``: exact; an integer ``M``: at ``M`` inducing items. ``pop.stats["mean"]`` says
            which was used.
        inducing_method: ``"kmeans"`` or ``"variance"`` (:mod:`torchpref.population.inducing`).
        memory_limit: the most bytes the fit may plan to use (default 75% of the machine's
            memory): a fit whose estimated peak is larger is refused before anything large is
            allocated.
        progress: show a progress bar over the evidence evaluations (tqdm); its first line
            states the problem's sizes and the estimated peak memory.
        executor: a ``concurrent.futures.Executor`` (threads, processes, or Dask's
            ``Client.get_executor()``, or the Dask ``Client``): the evidence and its gradient are
            computed over ``shards`` shards of people on it, by the same Newton loop as in
            process. On Dask each shard's state stays on its worker and a Newton step sends
            ``O(M^2)`` numbers per shard. A process pool must spawn, not fork
            (``mp_context=multiprocessing.get_context("spawn")``): a forking one is refused.
        shards: the number of shards (default: 2 per worker on an executor; in process, as many
            as keep one shard's work within :data:`SHARD_BYTES`).

    Returns:
        a :class:`~torchpref.population.model.Population`.

    Raises:
        ValueError: bad people (:func:`check_people`) or settings, naming the value; an estimated
            peak memory above ``memory_limit``, naming both and the way out.
    """
    people = check_people(people)
    if names is not None and feature_names is not None and list(names) != list(feature_names):
        raise ValueError(f"names {list(names)} and feature_names {list(feature_names)} differ; give one.")
    feature_names = feature_names if feature_names is not None else names
    _check_settings(people, feature_names, max_iter, inducing, inducing_method)
    warn_outside_unit_cube(torch.cat([p.train_X for p in people]))
    objective, plan = population_objective(
        people,
        k_m,
        k_g,
        model=_model_settings(people, model, comparison_noise, rating_scale, rating_precision),
        inducing=inducing,
        inducing_method=inducing_method,
        executor=executor,
        shards=shards,
        memory_limit=memory_limit,
    )
    params = _free(objective.kernels)
    bar = tqdm(total=max_iter, desc=f"fit_population: {plan.describe()}", disable=not progress, mininterval=5)
    if fit and params:
        _lbfgs(objective, params, max_iter, bar)
    with torch.no_grad():
        objective(with_gradient=False)
    bar.close()
    last = _finite_last(objective)
    k = objective.kernels
    return Population.from_mode(
        k.k_m,
        k.k_g,
        objective.Z,
        last.L_Z,
        last.a,
        last.S_chol,
        objective.settings,
        _stats(people, plan, objective),
        feature_names,
    )


def population_objective(
    people: Sequence[PreferenceData],
    k_m: Kernel | None = None,
    k_g: Kernel | None = None,
    *,
    model: ModelSettings | None = None,
    inducing: int | str | None = "auto",
    inducing_method: str = "kmeans",
    executor: object = None,
    shards: int | None = None,
    memory_limit: int | None = None,
) -> tuple[Objective, Plan]:
    """The evidence of checked ``people`` as an :class:`Objective` of the kernels' hyperparameters,
    and the :class:`Plan` it runs (``model``: the person model's settings, default a session's,
    with the people's rating levels; the other settings as :func:`fit_population`'s)."""
    settings = _model_settings(people, model, None, None, None)
    lik = settings.likelihood()
    d = people[0].train_X.shape[-1]
    kernels = _Kernels(
        k_m if k_m is not None else default_covar_module(d), k_g if k_g is not None else default_covar_module(d)
    ).double()
    if executor is not None:
        _refuse_fork(executor)
    plan = plan_fit(people, inducing, inducing_method, kernels.k_m, executor, shards, memory_limit)
    log.info("fit_population: %s", plan.describe())
    z_pos = torch.full((plan.items.U.shape[0],), -1, dtype=torch.long)
    z_pos[plan.z_rows] = torch.arange(plan.M)
    data = [shard_data(people, plan.items, b, lik, z_pos, settings.ties_offered) for b in plan.bounds]
    return Objective(kernels, plan.items.U[plan.z_rows], Shards(host_for(executor), data), settings.to_json()), plan
