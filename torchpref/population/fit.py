r""":func:`fit_population`: the hierarchical model of many people's answers, fitted by its evidence.

The population mean ``m ~ GP(0, k_m)`` and each person's deviation ``g_p ~ GP(0, k_g)`` are
fitted together: the hyperparameters of both kernels (``k_m``'s lengthscales and outputscale; ``k_g``'s
lengthscales and its outputscale ``s^2``, the between-person spread) maximise the Laplace
evidence of **all** people's answers plus the kernels' hyperparameter priors, the joint mode
solved exactly through the problem's structure (:mod:`torchpref.population.joint`).
"""

from __future__ import annotations

import numbers
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from typing import Any

import torch
from gpytorch.kernels import Kernel
from gpytorch.module import Module
from torch import Tensor
from tqdm.auto import tqdm

from torchpref.data.preference_data import PreferenceData
from torchpref.inference.padding import PaddedData
from torchpref.models.defaults import PreferenceLikelihood, default_covar_module
from torchpref.population.joint import Factors, Layout, evidence, find_mode
from torchpref.population.model import Population
from torchpref.population.prior import _dense
from torchpref.population.shards import ShardedProblem, shard_layouts, sharded_objective

__all__ = ["fit_population", "check_people", "population_layout"]


def check_people(people: Any) -> list[PreferenceData]:
    """``people`` as a list of float64 :class:`~torchpref.data.preference_data.PreferenceData`.

    Raises:
        ValueError: naming the problem: not a sequence, empty, an entry that is not a
            ``PreferenceData``, feature dimensions that differ, items that are not finite,
            ratings of different kinds (Beta and levels, or different numbers of levels), or no
            answers at all.
    """
    if isinstance(people, (PreferenceData, str, bytes)) or not isinstance(people, Sequence):
        raise ValueError(f"people must be a sequence of PreferenceData, one per person; got {type(people).__name__}.")
    if len(people) == 0:
        raise ValueError("people is empty: a population needs at least one person's PreferenceData.")
    out = []
    for i, p in enumerate(people):
        if not isinstance(p, PreferenceData):
            raise ValueError(f"people[{i}] must be a PreferenceData, got {type(p).__name__}.")
        X = p.train_X
        if X.dim() != 2 or X.shape[-1] != people[0].train_X.shape[-1]:
            raise ValueError(
                f"people[{i}] has items of shape {tuple(X.shape)}: every person's items must have "
                f"d = {people[0].train_X.shape[-1]} features (people[0]'s)."
            )
        if not bool(torch.isfinite(X).all()):
            bad = X[~torch.isfinite(X)][:3].tolist()
            raise ValueError(f"people[{i}] has items that are not finite (such as {bad}).")
        if p.rating_levels != people[0].rating_levels:
            raise ValueError(
                f"people[{i}] has rating_levels={p.rating_levels}, people[0] {people[0].rating_levels}: "
                "a population's ratings are all Beta (None) or all levels of one scale."
            )
        out.append(p.to(dtype=torch.float64))
    if sum(p.num_observations for p in out) == 0:
        raise ValueError("the population has no answers: fit_population needs comparisons or ratings.")
    return out


def population_layout(people: Sequence[PreferenceData], likelihood: PreferenceLikelihood) -> Layout:
    """The distinct items of all people and each person's items as rows of them (:class:`Layout`)."""
    X_all = torch.cat([p.train_X for p in people])
    U, inverse = torch.unique(X_all, dim=0, return_inverse=True)
    padded = PaddedData.stack(people)
    n = padded.num_items
    index = torch.zeros(len(people), n, dtype=torch.long)
    start = 0
    for k, p in enumerate(people):
        index[k, : p.n] = inverse[start : start + p.n]
        start += p.n
    mask = padded.item_mask if padded.item_mask is not None else torch.ones(len(people), n, dtype=torch.bool)
    obs = padded.observations(likelihood.comparison, likelihood.rating, likelihood.tie)
    return Layout(U, padded.X, index, mask, obs)


class _Kernels(Module):
    """``k_m`` and ``k_g`` together: their parameters and priors."""

    def __init__(self, k_m: Kernel, k_g: Kernel):
        super().__init__()
        self.k_m, self.k_g = k_m, k_g

    def functions(self) -> tuple[Callable[[Tensor, Tensor], Tensor], Callable[[Tensor, Tensor], Tensor]]:
        return (lambda A, B: _dense(self.k_m, A, B)), (lambda A, B: _dense(self.k_g, A, B))

    def log_prior(self) -> Tensor:
        out = torch.zeros((), dtype=torch.float64)
        for _, module, prior, closure, _ in self.named_priors():
            out = out + prior.log_prob(closure(module)).sum()
        return out


def _objective(kernels: _Kernels, layout: Layout, state: dict) -> Tensor:
    """``-(evidence + log priors)``, the mode re-solved (warm-started) at the current values."""
    k_m, k_g = kernels.functions()
    with torch.no_grad():
        F = Factors.build(layout, k_m, k_g, state.get("factors"))
        mode = find_mode(layout, F, state.get("start"))
    state.update(factors=F, start=(mode.point.a, mode.point.b), mode=mode)
    state.update(L_U=F.L_U, a=mode.point.a, S_chol=mode.hessian.S_chol)
    value = evidence(layout, F.traced(layout, k_m, k_g), mode)
    state["evidence"] = float(value.detach())
    return -(value + kernels.log_prior())


def _refuse_fork(executor: Any) -> None:
    """A process pool that forks is refused by name: a child forked from a process whose torch
    has started its thread pools can deadlock in its first factorisation (seen in a test run)."""
    context = getattr(executor, "_mp_context", None)  # concurrent.futures.ProcessPoolExecutor's
    if context is not None and context.get_start_method() == "fork":
        raise ValueError(
            "a ProcessPoolExecutor that forks can deadlock in torch's threads; give it "
            "mp_context=multiprocessing.get_context('spawn') (or 'forkserver')."
        )


def _objective_on(people: list[PreferenceData], likelihood: PreferenceLikelihood, executor: Any, shards: Any) -> Any:
    """:func:`_objective` in process, or over shards of people on ``executor``."""
    if executor is None:
        return _objective
    _refuse_fork(executor)
    k = shards if shards is not None else 2 * getattr(executor, "_max_workers", 2)
    if isinstance(k, bool) or not isinstance(k, numbers.Integral) or k < 1:
        raise ValueError(f"shards must be a positive integer, got {shards!r}.")
    U, parts = shard_layouts(people, lambda ps: population_layout(ps, likelihood), int(k))
    problem = ShardedProblem(U, parts, executor)
    return lambda kern, _, st: sharded_objective(problem, kern, st)


def _lbfgs(loss_fn: Callable[[], Tensor], params: list[Tensor], max_iter: int, progress: bool) -> None:
    """Minimise ``loss_fn()`` in ``params`` with L-BFGS (strong Wolfe line search)."""
    opt = torch.optim.LBFGS(params, max_iter=max_iter, line_search_fn="strong_wolfe", tolerance_change=1e-9)
    bar = tqdm(total=max_iter, desc="fit_population", disable=not progress, mininterval=5)

    def closure() -> Tensor:
        opt.zero_grad()
        loss = loss_fn()
        loss.backward()
        bar.update()
        return loss

    opt.step(closure)
    bar.close()


def fit_population(
    people: Sequence[PreferenceData],
    *,
    k_m: Kernel | None = None,
    k_g: Kernel | None = None,
    comparison_noise: float = 1.0,
    rating_scale: float = 1.0,
    rating_precision: float = 80.0,
    fit: bool = True,
    max_iter: int = 100,
    names: Sequence[str] | None = None,
    progress: bool = False,
    executor: Executor | None = None,
    shards: int | None = None,
) -> Population:
    r"""The population of ``people`` (one :class:`~torchpref.data.preference_data.PreferenceData` each;
    comparisons, ratings and ties, all in the same ``d`` features, items in the unit cube):
    the mean utility and the between-person spread fitted together (module docstring).

    Args:
        k_m, k_g: the kernels of the mean and of a person's deviation (default
            :func:`~torchpref.models.defaults.default_covar_module` each, with its priors).
        comparison_noise, rating_scale, rating_precision: the likelihoods' settings, fixed, as
            :class:`~torchpref.PreferenceGP`'s (ordinal people: ``rating_levels`` from the data).
        fit: optimise the kernels' hyperparameters (L-BFGS on the evidence); ``False`` keeps them.
        max_iter: L-BFGS iterations.
        names: the features' names (the objective space), kept with the population so that a
            file of it is refused for items of another space.
        progress: show a progress bar over the evidence evaluations (tqdm).
        executor: a ``concurrent.futures.Executor`` (threads, processes, or Dask's
            ``Client.get_executor()``): the evidence and its gradient are computed over ``shards``
            shards of people on it (:mod:`torchpref.population.shards`), the same model as in
            process to the optimiser's tolerance. A process pool must spawn, not fork
            (``mp_context=multiprocessing.get_context("spawn")``): a forking one is refused.
        shards: the number of shards (default: 2 per worker where the executor says, else 4).

    Returns:
        a :class:`~torchpref.population.model.Population`.

    Raises:
        ValueError: bad people (:func:`check_people`) or settings, naming the value.
    """
    people = check_people(people)
    if names is not None and len(names) != people[0].train_X.shape[-1]:
        raise ValueError(f"names must name the {people[0].train_X.shape[-1]} features, got {list(names)}.")
    if isinstance(max_iter, bool) or not isinstance(max_iter, numbers.Integral) or max_iter < 1:
        raise ValueError(f"max_iter must be a positive integer, got {max_iter!r}.")
    d = people[0].train_X.shape[-1]
    settings = dict(
        comparison_noise=float(comparison_noise),
        rating_scale=float(rating_scale),
        rating_precision=float(rating_precision),
        rating_levels=people[0].rating_levels,
    )
    likelihood = PreferenceLikelihood.create(
        settings["comparison_noise"], settings["rating_scale"], settings["rating_precision"], False, 0.1,
        settings["rating_levels"],
    )  # fmt: skip
    likelihood = likelihood.double()
    kernels = _Kernels(
        (k_m if k_m is not None else default_covar_module(d)), (k_g if k_g is not None else default_covar_module(d))
    ).double()
    layout = population_layout(people, likelihood)
    objective = _objective_on(people, likelihood, executor, shards)
    state: dict = {}
    params = [p for p in kernels.parameters() if p.requires_grad]
    if fit and params:
        _lbfgs(lambda: objective(kernels, layout, state), params, max_iter, progress)
    with torch.no_grad():
        objective(kernels, layout, state)
    stats = dict(people=len(people), items=int(layout.U.shape[0]), answers=sum(p.num_observations for p in people))
    stats.update(evidence=state["evidence"])
    return Population.from_mode(
        kernels.k_m, kernels.k_g, layout.U, state["L_U"], state["a"], state["S_chol"], settings, stats, names
    )
