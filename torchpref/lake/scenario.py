r"""The lake-monitoring scenario of the paper (Sec. IV.B): a lake, an information field and
training and test sets of planned paths with their objectives ``[distance, information]``."""

from __future__ import annotations

import math
import os
import pickle
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from .field import InformationField
from .geometry import Lake
from .objectives import path_objectives
from .planners import pad_paths, rrt_star, stomp

__all__ = [
    "LakeScenario",
    "make_scenario",
    "PLANNERS",
    "SCENARIO_VERSION",
    "cached_scenario",
    "default_cache_dir",
    "load_scenario",
    "save_scenario",
    "scenario_cache_path",
]

PLANNERS = ("stomp", "rrt_star")
"""Planner names; ``LakeScenario.train_planner`` holds indices into this tuple."""


@dataclass
class LakeScenario:
    r"""A lake, its field and two sets of paths.

    Attributes:
        lake: the lake with start and goal.
        field: the information field (already scaled, see :func:`make_scenario`).
        train_paths: ``n x T x 2`` paths (shorter ones padded by repeating the goal).
        train_X: ``n x 2`` objectives ``[distance, information]`` of the training paths.
        train_planner: ``n`` planner indices into :data:`PLANNERS`.
        train_weights: ``n`` weights ``w`` the paths were planned with.
        test_paths, test_X, test_planner, test_weights: the same for the test set.
    """

    lake: Lake
    field: InformationField
    train_paths: Tensor
    train_X: Tensor
    train_planner: Tensor
    train_weights: Tensor
    test_paths: Tensor
    test_X: Tensor
    test_planner: Tensor
    test_weights: Tensor


def make_scenario(
    seed: int | None = None,
    *,
    generator: torch.Generator | None = None,
    paths_per_planner: int = 100,
    weight_range: tuple[float, float] = (0.01, 1000.0),
    share_five: float | None = 0.1,
    lake: Lake | None = None,
    field: InformationField | None = None,
    stomp_options: dict | None = None,
    rrt_options: dict | None = None,
    progress: bool = False,
) -> LakeScenario:
    r"""Build a lake-monitoring scenario.

    Each set has ``paths_per_planner`` STOMP and as many RRT* paths, planned for weights drawn
    log-uniformly from ``weight_range`` (sorted) in the dimensionless cost
    ``L + w (L - I / f_max)``. That cost does not change when the field is scaled, so the
    paths are planned first and the field is then scaled so that a share ``share_five`` of
    the training paths gets the paper's operator's top rating (information >= 150 and
    distance < 500): the thresholds then mean the same whatever the seed.

    Args:
        seed: a seed for a fresh ``torch.Generator`` (give this or ``generator``).
        generator: the random source.
        paths_per_planner: paths per planner and set (paper: 100).
        weight_range: ``(w_min, w_max)`` of the weight sweep, ``0 < w_min <= w_max``.
        share_five: the share of training paths to be rated 5 by
            :class:`~torchpref.lake.operator.LakeOperator` after scaling the field;
            ``None`` leaves the field as it is.
        lake: a lake to use instead of a random one.
        field: a field to use instead of a random one.
        stomp_options: keyword arguments for :func:`~torchpref.lake.planners.stomp`.
        rrt_options: keyword arguments for :func:`~torchpref.lake.planners.rrt_star`.
        progress: show progress bars.
    """
    if (seed is None) == (generator is None):
        raise ValueError(f"give exactly one of seed and generator, got seed={seed}, generator={generator}.")
    if generator is None:
        generator = torch.Generator().manual_seed(int(seed))  # type: ignore[arg-type]
    if paths_per_planner < 1:
        raise ValueError(f"paths_per_planner must be positive, got {paths_per_planner}.")
    if not 0 < weight_range[0] <= weight_range[1]:
        raise ValueError(f"weight_range must satisfy 0 < w_min <= w_max, got {weight_range}.")
    lake = Lake.random(generator=generator) if lake is None else lake
    if field is None:
        xmin, xmax, ymin, ymax = lake.bounds
        field = InformationField.random(generator=generator, extent=(xmin - 5, xmax + 5, ymin - 5, ymax + 5))
    if share_five is not None and not 0 < share_five < 1:
        raise ValueError(f"share_five must be in (0, 1), got {share_five}.")

    train, test = (
        _plan_set(lake, field, paths_per_planner, weight_range, generator, progress, stomp_options, rrt_options)
        for _ in range(2)
    )
    if share_five is not None:
        field, train, test = _scaled_for_share_five(field, train, test, share_five)
    return LakeScenario(lake, field, *train, *test)


def _plan_set(
    lake: Lake,
    field: InformationField,
    n: int,
    weight_range: tuple[float, float],
    generator: torch.Generator,
    progress: bool,
    stomp_options: dict | None,
    rrt_options: dict | None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """One set: ``n`` STOMP and ``n`` RRT* paths for weights drawn log-uniformly from
    ``weight_range`` (sorted): ``(paths, objectives, planner indices, weights)``."""
    w_min, w_max = weight_range
    u = torch.rand(n, generator=generator, dtype=torch.float64)
    w = torch.exp(math.log(w_min) + u * (math.log(w_max) - math.log(w_min))).sort().values
    # the cost's information term is f_max L - I: scale w so that it means the same per unit field
    w_eff = w / field.max
    a = stomp(lake, field, w_eff, generator=generator, progress=progress, **(stomp_options or {}))
    b = rrt_star(lake, field, w_eff, generator=generator, progress=progress, **(rrt_options or {}))
    paths = pad_paths([a, b])
    planner = torch.cat([torch.zeros(n), torch.ones(n)]).long()
    return paths, path_objectives(paths, field), planner, torch.cat([w, w])


def _scaled_for_share_five(field: InformationField, train: tuple, test: tuple, share_five: float) -> tuple:
    """The field scaled so that a share ``share_five`` of the training paths is rated 5 (information
    >= 150 and distance < 500), and both sets' objectives scaled with it: ``(field, train, test)``."""
    X = train[1]
    short = X[X[:, 0] < 500.0, 1].sort(descending=True).values
    k = min(max(1, round(share_five * X.shape[0])), short.numel())
    if k == 0 or not short[0] > 0:
        raise RuntimeError("no training path is short enough (< 500) to be rated 5.")
    # the k-th most informative short path lands halfway above 150
    edge = short[k - 1] if k == short.numel() else 0.5 * (short[k - 1] + short[k])
    scale = 150.0 / float(edge)
    factor = torch.tensor([1.0, scale], dtype=torch.float64)
    return field.scaled(scale), (train[0], train[1] * factor, *train[2:]), (test[0], test[1] * factor, *test[2:])


SCENARIO_VERSION = 1
"""Version of :func:`make_scenario`'s output; bump it whenever the same seed would build a
different scenario, so that cached scenarios of the old builder are not used."""

_TENSORS = (
    "train_paths",
    "train_X",
    "train_planner",
    "train_weights",
    "test_paths",
    "test_X",
    "test_planner",
    "test_weights",
)


def default_cache_dir() -> Path:
    """``$TORCHPREF_CACHE/lake``, else ``$XDG_CACHE_HOME/torchpref/lake``, else ``~/.cache/torchpref/lake``."""
    root = os.environ.get("TORCHPREF_CACHE")
    if root:
        return Path(root) / "lake"
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "torchpref" / "lake"


def scenario_cache_path(seed: int, cache_dir: str | os.PathLike | None = None) -> Path:
    """The file holding the scenario of ``seed`` (keyed by the seed and :data:`SCENARIO_VERSION`)."""
    folder = default_cache_dir() if cache_dir is None else Path(cache_dir)
    return folder / f"scenario-v{SCENARIO_VERSION}-seed{int(seed)}.pt"


def save_scenario(scenario: LakeScenario, path: str | os.PathLike) -> Path:
    """Write ``scenario`` to ``path`` atomically (a temporary file, then a rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {
        "version": SCENARIO_VERSION,
        "vertices": scenario.lake.vertices,
        "start": scenario.lake.start,
        "goal": scenario.lake.goal,
        "grid": scenario.field.grid,
        "extent": list(scenario.field.extent),
        **{k: getattr(scenario, k) for k in _TENSORS},
    }
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)
    return path


def load_scenario(path: str | os.PathLike) -> LakeScenario:
    """Read a scenario written by :func:`save_scenario`.

    Raises:
        ValueError: the file is not a scenario of this :data:`SCENARIO_VERSION`.
    """
    try:
        state = torch.load(path, weights_only=True)
        if state.get("version") != SCENARIO_VERSION:
            raise ValueError(f"version {state.get('version')}, expected {SCENARIO_VERSION}")
        lake = Lake(state["vertices"], state["start"], state["goal"])
        field = InformationField(state["grid"], tuple(state["extent"]))
        return LakeScenario(lake, field, *(state[k] for k in _TENSORS))
    except (
        OSError,
        RuntimeError,
        KeyError,
        TypeError,
        ValueError,
        AttributeError,
        EOFError,
        pickle.UnpicklingError,
    ) as exc:
        raise ValueError(f"{path} is not a usable lake scenario: {exc}") from exc


def cached_scenario(seed: int, cache_dir: str | os.PathLike | None = None, *, progress: bool = False) -> LakeScenario:
    """The scenario ``make_scenario(seed)``, built once and then read from ``cache_dir``
    (default :func:`default_cache_dir`). An unreadable cache file is rebuilt with a warning."""
    path = scenario_cache_path(seed, cache_dir)
    if path.exists():
        try:
            return load_scenario(path)
        except ValueError as exc:
            warnings.warn(f"rebuilding the lake scenario of seed {seed}: {exc}", RuntimeWarning, stacklevel=2)
    scenario = make_scenario(seed, progress=progress)
    try:
        save_scenario(scenario, path)
    except OSError as exc:
        warnings.warn(
            f"could not cache the lake scenario of seed {seed} in {path.parent}: {exc}", RuntimeWarning, stacklevel=2
        )
    return scenario
