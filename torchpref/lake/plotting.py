"""Figures of the lake world (the paper's Figs. 7 and 8). Needs matplotlib (the ``plot`` extra)."""

from __future__ import annotations

from pathlib import Path

import torch

from .operator import LakeOperator
from .scenario import LakeScenario

__all__ = ["plot_field", "plot_objectives"]

# Fig. 8's colours: red = 1, yellow = 2, green = 3, cyan = 4, blue = 5
LEVEL_COLOURS = ("#d62728", "#e6c229", "#2ca02c", "#17becf", "#1f3fbf")


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def plot_field(scenario: LakeScenario, path: str | Path, *, num_examples: int = 3) -> Path:
    """The field over the lake with the shoreline, start, goal and example paths of both planners
    (low, middle and high weight), written to ``path``."""
    plt = _pyplot()
    from matplotlib.patches import Polygon

    lake, field = scenario.lake, scenario.field
    fig, ax = plt.subplots(figsize=(8, 5.6))
    xmin, xmax, ymin, ymax = field.extent
    im = ax.imshow(field.grid.numpy(), origin="lower", extent=(xmin, xmax, ymin, ymax), cmap="YlOrRd", zorder=0)
    # grey land outside the shoreline
    outer = [(xmin, ymin), (xmax, ymin), (xmax, ymax), (xmin, ymax)]
    shore = lake.vertices.numpy()
    land = Polygon(outer, closed=True, facecolor="none")
    ax.add_patch(land)
    from matplotlib.path import Path as MPath

    codes = [MPath.MOVETO] + [MPath.LINETO] * 3 + [MPath.CLOSEPOLY]
    codes += [MPath.MOVETO] + [MPath.LINETO] * (len(shore) - 1) + [MPath.CLOSEPOLY]
    verts = outer + [outer[0]] + [tuple(p) for p in shore[::-1]] + [tuple(shore[-1])]
    from matplotlib.patches import PathPatch

    ax.add_patch(PathPatch(MPath(verts, codes), facecolor="#c9c3b5", edgecolor="none", zorder=1))
    ax.add_patch(Polygon(shore, closed=True, facecolor="none", edgecolor="#3b3b3b", lw=1.5, zorder=2))
    X, planner, w, paths = scenario.train_X, scenario.train_planner, scenario.train_weights, scenario.train_paths
    styles = {0: ("#1f3fbf", "-", "STOMP"), 1: ("#111111", "--", "RRT*")}
    for p in (0, 1):
        idx = torch.nonzero(planner == p).squeeze(-1)
        picks = idx[torch.linspace(0, len(idx) - 1, num_examples).round().long()]
        colour, ls, name = styles[p]
        for j, k in enumerate(picks.tolist()):
            xy = paths[k].numpy()
            label = f"{name}: w={float(w[k]):.2g}, d={float(X[k, 0]):.0f}, I={float(X[k, 1]):.0f}"
            ax.plot(xy[:, 0], xy[:, 1], ls, color=colour, lw=1.6, alpha=0.55 + 0.45 * j / max(1, num_examples - 1),
                    label=label, zorder=3)
    for pt, name, m in ((lake.start, "start", "o"), (lake.goal, "goal", "*")):
        ax.plot(*pt.tolist(), m, color="white", mec="black", ms=12, zorder=4)
        ax.annotate(name, pt.tolist(), xytext=(6, 8), textcoords="offset points", fontsize=10, zorder=4)
    ax.set_xlim(xmin, xmax)
    ax.set_ylim(ymin, ymax)
    ax.set_aspect("equal")
    ax.set_title("Information field over the lake, with paths from both planners")
    fig.colorbar(im, ax=ax, shrink=0.75, label="information per unit length")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.06), ncol=2, fontsize=7.5, frameon=False)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return path


def plot_objectives(scenario: LakeScenario, path: str | Path, operator: LakeOperator | None = None) -> Path:
    """The training and test paths over the objective space, coloured by the operator's rating
    (the paper's Fig. 8), written to ``path``."""
    plt = _pyplot()
    operator = LakeOperator() if operator is None else operator
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4), sharex=True, sharey=True)
    for ax, (name, X, planner) in zip(axes, (("training", scenario.train_X, scenario.train_planner),
                                                ("test", scenario.test_X, scenario.test_planner))):
        level = operator.level(X)
        for k in range(1, 6):
            for p, marker in ((0, "o"), (1, "^")):
                m = (level == k) & (planner == p)
                ax.scatter(X[m, 0], X[m, 1], s=22, marker=marker, color=LEVEL_COLOURS[k - 1], edgecolor="black",
                           lw=0.3, label=f"rating {k}" if p == 0 else None, zorder=3)
        ax.axhline(operator.info_poor, color="grey", ls=":", lw=1)
        ax.axhline(operator.info_good, color="grey", ls="--", lw=1)
        for d in (500, 550, 600, 650):
            ax.axvline(d, color="grey", lw=0.5, alpha=0.5)
        share = float((level == 5).double().mean())
        ax.set_title(f"{name} set: {X.shape[0]} paths, {100 * share:.0f}% rated 5")
        ax.set_xlabel("distance")
        ax.grid(alpha=0.2)
    axes[0].set_ylabel("information")
    handles, labels = axes[0].get_legend_handles_labels()
    from matplotlib.lines import Line2D

    handles += [Line2D([], [], marker="o", ls="", color="white", mec="black"),
                Line2D([], [], marker="^", ls="", color="white", mec="black")]
    labels += ["STOMP", "RRT*"]
    fig.legend(handles, labels, loc="center right", fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0, 0.9, 1))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return path
