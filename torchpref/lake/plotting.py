"""Figures of the lake world (the paper's Figs. 7 and 8). Needs matplotlib (the ``plot`` extra)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from .operator import LakeOperator
from .scenario import LakeScenario

if TYPE_CHECKING:  # matplotlib is the plot extra: imported where drawn
    from matplotlib.axes import Axes
    from matplotlib.image import AxesImage

__all__ = ["draw_lake", "draw_paths", "plot_field", "plot_objectives", "plot_paths"]

# Fig. 8's colours: red = 1, yellow = 2, green = 3, cyan = 4, blue = 5
LEVEL_COLOURS = ("#d62728", "#e6c229", "#2ca02c", "#17becf", "#1f3fbf")
#: colours of labelled paths on a map
PATH_COLOURS = ("#1f3fbf", "#111111", "#2ca02c", "#9467bd", "#17becf", "#8c564b", "#e377c2")


def _pyplot():
    from torchpref.extras import require

    matplotlib = require("matplotlib", "drawing the lake")

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: str | Path, dpi: int = 130) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    _pyplot().close(fig)
    return path


def draw_lake(ax: Axes, scenario: LakeScenario, *, colorbar: bool = True) -> AxesImage:
    """The field on the water of ``ax`` (land masked grey, its own colour scale and colour bar),
    the shoreline, start and goal. Returns the field's image."""
    import numpy as np
    from matplotlib import colormaps
    from matplotlib.patches import Polygon

    lake, field = scenario.lake, scenario.field
    xmin, xmax, ymin, ymax = field.extent
    ny, nx = field.grid.shape
    xs = torch.linspace(xmin, xmax, nx, dtype=torch.float64)
    ys = torch.linspace(ymin, ymax, ny, dtype=torch.float64)
    water = lake.contains(torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1))
    values = np.ma.masked_array(field.grid.numpy(), mask=~water.numpy())
    cmap = colormaps["YlOrRd"].with_extremes(bad="#c9c3b5")  # land
    im = ax.imshow(values, origin="lower", extent=(xmin, xmax, ymin, ymax), cmap=cmap, zorder=0)
    ax.add_patch(Polygon(lake.vertices.numpy(), closed=True, facecolor="none", edgecolor="#3b3b3b", lw=1.5, zorder=2))
    for pt, name, m in ((lake.start, "start", "o"), (lake.goal, "goal", "*")):
        x, y = pt.tolist()
        ax.plot(x, y, m, color="white", mec="black", ms=11, zorder=5)
        ax.annotate(
            name,
            (x, y),
            xytext=(6, 8),
            textcoords="offset points",
            fontsize=9,
            zorder=5,
            bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.7),
        )
    ax.set_xlim(xmin, xmax)
    ax.set_ylim(ymin, ymax)
    ax.set_aspect("equal")
    if colorbar:
        ax.figure.colorbar(im, ax=ax, shrink=0.8, label="information per unit length")
    return im


def draw_paths(
    ax: Axes,
    paths: Sequence[Tensor],
    labels: Sequence[str],
    *,
    colours: Sequence[str] | None = None,
    styles: Sequence[str] | None = None,
    markers: bool = True,
    line_width: float = 2.2,
) -> None:
    """Paths (each ``T x 2``) on ``ax`` with their labels in the legend; with ``markers`` each path
    also carries its label's part before a colon at a point along it, staggered so that labels of paths
    that run together do not cover each other. ``line_width`` in points."""
    n = len(paths)
    for k, (p, label) in enumerate(zip(paths, labels)):
        xy = torch.as_tensor(p).numpy()
        c = (colours or PATH_COLOURS)[k % len(colours or PATH_COLOURS)]
        ls = styles[k] if styles else "-"
        ax.plot(xy[:, 0], xy[:, 1], ls, color=c, lw=line_width, label=label, zorder=3)
        if markers and ":" in label:
            at = xy[min(len(xy) - 1, int(len(xy) * (k + 1) / (n + 1)))]
            ax.annotate(
                label.split(":")[0],
                at,
                fontsize=10,
                fontweight="bold",
                color=c,
                zorder=4,
                ha="center",
                va="center",
                bbox=dict(boxstyle="round,pad=0.2", fc="white", ec=c, alpha=0.9),
            )


def plot_paths(
    scenario: LakeScenario,
    paths: Sequence[Tensor],
    labels: Sequence[str],
    path: str | Path,
    *,
    title: str = "",
    dpi: int = 110,
    line_width: float = 2.2,
) -> Path:
    """A map of the lake (:func:`draw_lake`) with ``paths`` (each ``T x 2``, drawn ``line_width``
    points wide) and their ``labels``, written to ``path``."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 5.4))
    draw_lake(ax, scenario)
    draw_paths(ax, paths, labels, line_width=line_width)
    ax.set_title(title)
    if any(labels):  # unlabelled paths (a served item's map) have no legend, and no warning that it is empty
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.06), ncol=min(2, len(paths)), fontsize=8, frameon=False)
    fig.tight_layout()
    return _save(fig, path, dpi)


def plot_field(scenario: LakeScenario, path: str | Path, *, num_examples: int = 3) -> Path:
    """The field over the lake with the shoreline, start, goal and example paths of both planners
    (low, middle and high weight), written to ``path``."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 5.6))
    draw_lake(ax, scenario)
    X, planner, w, paths = scenario.train_X, scenario.train_planner, scenario.train_weights, scenario.train_paths
    styles = {0: ("#1f3fbf", "-", "STOMP"), 1: ("#111111", "--", "RRT*")}
    for p in (0, 1):
        idx = torch.nonzero(planner == p).squeeze(-1)
        if idx.numel() == 0:
            continue
        picks = idx[torch.linspace(0, len(idx) - 1, num_examples).round().long()]
        colour, ls, name = styles[p]
        for j, k in enumerate(picks.tolist()):
            xy = paths[k].numpy()
            label = f"{name}: w={float(w[k]):.2g}, d={float(X[k, 0]):.0f}, I={float(X[k, 1]):.0f}"
            ax.plot(
                xy[:, 0],
                xy[:, 1],
                ls,
                color=colour,
                lw=1.6,
                alpha=0.55 + 0.45 * j / max(1, num_examples - 1),
                label=label,
                zorder=3,
            )
    ax.set_title("Information field over the lake, with paths from both planners")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.06), ncol=2, fontsize=7.5, frameon=False)
    fig.tight_layout()
    return _save(fig, path)


def plot_objectives(scenario: LakeScenario, path: str | Path, operator: LakeOperator | None = None) -> Path:
    """The training and test paths over the objective space, coloured by the operator's rating
    (the paper's Fig. 8), written to ``path``."""
    plt = _pyplot()
    operator = LakeOperator() if operator is None else operator
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4), sharex=True, sharey=True)
    for ax, (name, X, planner) in zip(
        axes, (("training", scenario.train_X, scenario.train_planner), ("test", scenario.test_X, scenario.test_planner))
    ):
        level = operator.level(X)
        for k in range(1, 6):
            for p, marker in ((0, "o"), (1, "^")):
                m = (level == k) & (planner == p)
                ax.scatter(
                    X[m, 0],
                    X[m, 1],
                    s=22,
                    marker=marker,
                    color=LEVEL_COLOURS[k - 1],
                    edgecolor="black",
                    lw=0.3,
                    label=f"rating {k}" if p == 0 else None,
                    zorder=3,
                )
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

    handles += [
        Line2D([], [], marker="o", ls="", color="white", mec="black"),
        Line2D([], [], marker="^", ls="", color="white", mec="black"),
    ]
    labels += ["STOMP", "RRT*"]
    fig.legend(handles, labels, loc="center right", fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0, 0.9, 1))
    return _save(fig, path)
