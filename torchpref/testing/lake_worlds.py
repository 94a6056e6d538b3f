"""Small synthetic lake worlds for the lake tests (a real scenario takes seconds to plan)."""

import math

import torch

from torchpref.lake import InformationField, Lake


def lake_and_field(seed: int) -> tuple[Lake, InformationField]:
    """A random lake and a coarse (``60 x 80``) random field over it, from ``seed``."""
    g = torch.Generator().manual_seed(seed)
    lake = Lake.random(generator=g)
    xmin, xmax, ymin, ymax = lake.bounds
    field = InformationField.random(generator=g, extent=(xmin - 5, xmax + 5, ymin - 5, ymax + 5), shape=(60, 80))
    return lake, field


def bent_paths(lake: Lake, offsets: torch.Tensor, T: int = 20) -> torch.Tensor:
    """``len(offsets) x T x 2`` paths from start to goal, each bent sideways by a half sine of
    amplitude ``offset``."""
    t = torch.linspace(0, 1, T, dtype=torch.float64).unsqueeze(-1)
    d = lake.goal - lake.start
    n = torch.stack([-d[1], d[0]]) / d.norm()
    return torch.stack([lake.start + t * d + o * torch.sin(math.pi * t) * n for o in offsets])
