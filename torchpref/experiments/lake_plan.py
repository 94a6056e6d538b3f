r"""Planning with what the model has learned, in the lake experiment (the learning side).

The lake's planner (:func:`~torchpref.lake.plan.plan_with_utility`) optimises any differentiable
utility of a path's objectives. Here that utility is a *risk-aware* criterion of the learned
model, a lower confidence bound of the improvement over a reference path ``r``:

.. math::
    c(x) = \mu(x) - \mu(r) - \beta \sqrt{\operatorname{Var}[f(x) - f(r)]},
    \qquad \operatorname{Var}[f(x) - f(r)] = \sigma^2(x) + \sigma^2(r) - 2\,\mathrm{cov}(x, r),

from the joint posterior of the latent utility at ``x`` and ``r`` (objectives normalised as the
model sees them). ``c(x) > 0`` means the model is at least ``Phi(beta)`` sure (Laplace's
Gaussian posterior) that ``x`` beats ``r``, and ``c(r) = 0``: the reference is the explicit
fallback. Optionally, points farther than ``trust_radius`` (unit cube) from every item the
operator has answered about pay ``trust_weight * excess^2``.

The reference is the *best shown path* (the answered item of largest posterior mean): the
operator has seen and answered about it. The starts are the best pool paths by the posterior
mean (the model's own pick among them) and fresh STOMP and RRT* paths planned for the weights
around the pick's. The same criterion optimises the starts and chooses among all candidates.

:func:`compare` is the finer measure of a planned path against another: the operator's levels,
the distance difference, the information margin over the operator's threshold
(``information - info_good``) and whether the planned path is strictly better
(:meth:`~torchpref.lake.operator.LakeOperator.utility`: a higher level, or the same level and
shorter when the information is enough, more information when it is not).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from botorch.models.model import Model
from botorch.posteriors import GPyTorchPosterior
from botorch.utils.transforms import normalize as normalise
from torch import Tensor

from torchpref.experiments.results import paired_tests
from torchpref.lake.objectives import path_objectives
from torchpref.lake.operator import LakeOperator
from torchpref.lake.plan import SOURCES, plan_with_utility
from torchpref.lake.planners import pad_paths, rrt_star, stomp

if TYPE_CHECKING:
    from torchpref.lake.scenario import LakeScenario
    from torchpref.models.preference_gp import PreferenceGP

#: planning settings: ``beta`` of the bound, the reference (``"shown"``: the best shown path;
#: ``"pick"``: the model's pool pick), the trust region (``None``: none), the number of best pool
#: paths and of best fresh paths to start from, the weights of the fresh paths per lake (one STOMP
#: and one RRT* path each), and the optimiser's settings
PLAN_SETTINGS: dict[str, Any] = {
    "beta": 1.0,
    "reference": "shown",
    "trust_radius": None,
    "trust_weight": 100.0,
    "num_pool_starts": 3,
    "num_fresh": 2,
    "fresh_weights": 8,
    "steps": 60,
    "lr": 1.0,
    "num_points": 30,
    "step": 4.0,
}


def _posterior(model: Model, X: Tensor) -> GPyTorchPosterior:
    post = model.posterior(X)
    if not isinstance(post, GPyTorchPosterior):
        raise ValueError(f"planning needs a Gaussian posterior, got a {type(post).__name__}.")
    return post


def model_utility(model: Model, bounds: Tensor) -> Callable[[Tensor], Tensor]:
    """The posterior mean of ``model`` (trained on objectives normalised by ``bounds``) as a
    differentiable function of the lake's objectives ``n x 2`` -> ``n``."""

    def utility(X: Tensor) -> Tensor:
        Z = normalise(X, bounds)
        return _posterior(model, Z.unsqueeze(-2)).mean.reshape(Z.shape[:-1])

    return utility


def improvement_bound(
    model: Model,
    bounds: Tensor,
    reference: Tensor,
    beta: float,
    *,
    answered: Tensor | None = None,
    trust_radius: float | None = None,
    trust_weight: float = 100.0,
) -> Callable[[Tensor], Tensor]:
    r"""The criterion ``c`` of the module docstring as a function of the lake's objectives.

    Args:
        model: a model with a joint ``posterior`` (trained on normalised objectives).
        bounds: ``2 x 2`` the normalisation bounds.
        reference: ``2`` the reference path's objectives (lake units).
        beta: the bound's width in posterior standard deviations (``0``: the mean improvement).
        answered: ``k x 2`` normalised items the operator answered about (for the trust region).
        trust_radius: radius of the trust region in the unit cube, or ``None``.
        trust_weight: weight of the squared excess over the radius.

    Returns:
        A function ``n x 2`` -> ``n``.
    """
    if beta < 0:
        raise ValueError(f"beta must be non-negative, got {beta}.")
    if trust_radius is not None and (answered is None or answered.shape[0] == 0):
        raise ValueError("a trust region needs the answered items.")
    z_ref = normalise(reference, bounds)

    def criterion(X: Tensor) -> Tensor:
        Z = normalise(X, bounds)
        pair = torch.stack([Z, z_ref.expand_as(Z)], dim=-2)  # n x 2 x 2: the point and the reference
        post = _posterior(model, pair)
        mean, cov = post.mean[..., 0], post.covariance_matrix
        var = cov[..., 0, 0] + cov[..., 1, 1] - 2 * cov[..., 0, 1]
        c = mean[..., 0] - mean[..., 1] - beta * var.clamp_min(1e-12).sqrt()
        if trust_radius is not None:
            assert answered is not None  # checked above
            excess = torch.relu(torch.cdist(Z, answered).min(-1).values - trust_radius)
            c = c - trust_weight * excess.pow(2)
        return c

    return criterion


def fresh_paths(scenario: LakeScenario, num: int, generator: torch.Generator) -> Tensor:
    """``2 num x T x 2`` new STOMP and RRT* paths (not in the scenario's sets) for ``num`` weights
    spread log-uniformly over :func:`~torchpref.lake.scenario.make_scenario`'s sweep."""
    w = torch.logspace(-2, 3, num, dtype=torch.float64) / scenario.field.max
    a = stomp(scenario.lake, scenario.field, w, generator=generator)
    b = rrt_star(scenario.lake, scenario.field, w, generator=generator)
    return pad_paths([a, b])


def compare(operator: LakeOperator, X: Tensor, X_other: Tensor) -> dict[str, Any]:
    """The finer measure of a path with objectives ``X`` against one with ``X_other`` (both ``2``)."""
    level, other = int(operator.level(X)), int(operator.level(X_other))
    return {
        "level": level,
        "other_level": other,
        "distance_diff": float(X[0] - X_other[0]),
        "info_margin": float(X[1] - operator.info_good),
        "other_info_margin": float(X_other[1] - operator.info_good),
        "at_least_as_good": level >= other,
        "strictly_better": bool(operator.utility(X) > operator.utility(X_other)),
    }


def plan_for_model(
    scenario: LakeScenario,
    model: PreferenceGP,
    bounds: Tensor,
    pool_rows: Tensor,
    fresh: Tensor | None = None,
    settings: dict[str, Any] | None = None,
) -> dict[str, Any]:
    r"""Plan with a learned model and judge the plan against the model's pool pick.

    Args:
        scenario: the :class:`~torchpref.lake.scenario.LakeScenario`.
        model: the learned model (on objectives normalised by ``bounds``).
        bounds: ``2 x 2`` normalisation bounds.
        pool_rows: indices of the candidate training paths (the pool the model chose from).
        fresh: ``k x T x 2`` paths the operator has not seen (:func:`fresh_paths`); the
            ``num_fresh`` of largest posterior mean are starts too.
        settings: overrides of :data:`PLAN_SETTINGS`.

    Returns:
        ``{"source", "criterion", "planned": compare(planned, pick), "vs_shown":
        compare(planned, shown), "pick_level", "shown_level", "planned_objectives",
        "pick_objectives", "shown_objectives"}``.
    """
    s = {**PLAN_SETTINGS, **(settings or {})}
    operator = LakeOperator()
    paths, X = scenario.train_paths[pool_rows], scenario.train_X[pool_rows]
    mean = model_utility(model, bounds)
    with torch.no_grad():
        order = mean(X).argsort(descending=True)
        answered = model.train_X
        shown = int(_posterior(model, answered.unsqueeze(-2)).mean.reshape(-1).argmax())
    # the shown item's path: the pool row whose normalised objectives match it
    Z = normalise(X, bounds)
    shown_row = int((Z - answered[shown]).abs().sum(-1).argmin())
    pick = int(order[0])
    start_list = [paths[order[: s["num_pool_starts"]]]]
    if fresh is not None and s["num_fresh"] > 0:
        with torch.no_grad():
            best_fresh = mean(path_objectives(fresh, scenario.field)).argsort(descending=True)[: s["num_fresh"]]
        start_list.append(fresh[best_fresh])
    starts = pad_paths(start_list)
    ref = shown_row if s["reference"] == "shown" else pick
    criterion = improvement_bound(
        model,
        bounds,
        X[ref],
        s["beta"],
        answered=answered,
        trust_radius=s["trust_radius"],
        trust_weight=s["trust_weight"],
    )
    res = plan_with_utility(
        scenario,
        criterion,
        starts=starts,
        fallback=paths[ref],
        steps=s["steps"],
        lr=s["lr"],
        num_points=s["num_points"],
        step=s["step"],
    )
    return {
        "source": res.source,
        "criterion": res.utility,
        "planned": compare(operator, res.objectives, X[pick]),
        "vs_shown": compare(operator, res.objectives, X[shown_row]),
        "pick_level": int(operator.level(X[pick])),
        "shown_level": int(operator.level(X[shown_row])),
        "planned_objectives": res.objectives.tolist(),
        "pick_objectives": X[pick].tolist(),
        "shown_objectives": X[shown_row].tolist(),
        "pick_row": int(pool_rows[pick]),
        "shown_row": int(pool_rows[shown_row]),
        "path": res.path.tolist(),
    }


def summarise_plans(plans: list[dict[str, Any]]) -> dict[str, Any]:
    r"""Planned path against the model's pool pick over a set of plans (one lake, or pooled).

    Returns:
        ``n``; mean levels of the planned path, the pick and the best shown path; the shares
        ``at_least_as_good`` and ``strictly_better`` (the finer measure of :func:`compare`);
        ``worse`` (count); ``sources`` (counts); ``distance_gain``: mean and largest distance
        saved where the planned path is strictly better at the same level; and ``paired``:
        :func:`~torchpref.experiments.runner.paired_tests` of the planned vs the pick's levels.
    """
    n = len(plans)
    if n == 0:
        raise ValueError("no plans to summarise.")
    cmp = [p["planned"] for p in plans]
    gains = [-c["distance_diff"] for c in cmp if c["strictly_better"] and c["level"] == c["other_level"]]
    sources = {k: sum(p["source"] == k for p in plans) for k in SOURCES}
    out = {
        "n": n,
        "planned_level_mean": sum(c["level"] for c in cmp) / n,
        "pick_level_mean": sum(p["pick_level"] for p in plans) / n,
        "shown_level_mean": sum(p["shown_level"] for p in plans) / n,
        "at_least_as_good": sum(c["at_least_as_good"] for c in cmp) / n,
        "strictly_better": sum(c["strictly_better"] for c in cmp) / n,
        "worse": sum(not c["at_least_as_good"] for c in cmp),
        "sources": sources,
        "distance_gain": {
            "n": len(gains),
            "mean": sum(gains) / len(gains) if gains else 0.0,
            "max": max(gains, default=0.0),
        },
    }
    if n >= 2:
        out["paired"] = paired_tests([c["level"] for c in cmp], [c["other_level"] for c in cmp])
    return out


def plot_plan_maps(scenario: LakeScenario, plans: dict[str, dict[str, Any]], path: str | Path) -> Any:
    """Fig. 7-style maps, one panel per strategy: the field on the water (colour bar, land
    masked), the best shown path, the model's pool pick and the planned path."""
    from torchpref.lake.plotting import _pyplot, _save, draw_lake, draw_paths

    plt = _pyplot()
    names = list(plans)
    fig, axes = plt.subplots(1, len(names), figsize=(7.2 * len(names), 5.6), squeeze=False)
    for ax, name in zip(axes[0], names):
        p = plans[name]
        draw_lake(ax, scenario)
        rows = [p["shown_row"], p["pick_row"]]
        paths = [scenario.train_paths[r] for r in rows] + [torch.tensor(p["path"])]
        objs = [p["shown_objectives"], p["pick_objectives"], p["planned_objectives"]]
        levels = [p["shown_level"], p["pick_level"], p["planned"]["level"]]
        labels = [
            f"{k}: d={o[0]:.0f}, I={o[1]:.0f}, level {lv}"
            for k, o, lv in zip(
                ("shown (best answered)", "pick (best pool path)", f"planned ({p['source']})"), objs, levels
            )
        ]
        draw_paths(ax, paths, labels, colours=("#111111", "#2ca02c", "#1f3fbf"))
        ax.set_title(name)
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.06), ncol=1, fontsize=8, frameon=False)
    fig.tight_layout()
    return _save(fig, path)


def plot_plan_levels(plans: list[dict[str, Any]], lake_of: list[int], path: str | Path, title: str = "") -> Any:
    """The operator's level of the planned path, the pool pick and the best shown path over the
    trials (lakes separated by vertical lines)."""
    from torchpref.lake.plotting import _pyplot, _save

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(max(7.0, 0.03 * len(plans) + 6), 3.6))
    x = list(range(len(plans)))
    ax.plot(x, [p["shown_level"] for p in plans], "s", color="#999999", ms=7, label="best shown path")
    ax.plot(x, [p["pick_level"] for p in plans], "o", color="#2ca02c", ms=5, label="pool pick")
    ax.plot(x, [p["planned"]["level"] for p in plans], "x", color="#1f3fbf", ms=6, mew=1.8, label="planned path")
    for i in range(1, len(plans)):
        if lake_of[i] != lake_of[i - 1]:
            ax.axvline(i - 0.5, color="grey", lw=0.5, alpha=0.6)
    ax.set_yticks(range(1, 6))
    ax.set_ylim(0.5, 5.5)
    ax.set_xlabel("trial (grouped by lake)")
    ax.set_ylabel("operator's level")
    ax.set_title(title)
    ax.legend(loc="lower left", fontsize=8, ncol=3)
    fig.tight_layout()
    return _save(fig, path)
