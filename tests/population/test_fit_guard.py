"""fit_population fails by name, never inside torch's line search: a start whose evidence is not
finite (a lengthscale at its constraint's bound) is a FitStartError naming the hyperparameters,
and a line search that meets a non-finite loss rejects the step and goes on from the best point."""

from __future__ import annotations

import pytest
import torch

from torchpref.data.preference_data import PreferenceData
from torchpref.models.defaults import default_covar_module
from torchpref.population.fit import fit_population
from torchpref.population.lbfgs import FitStartError, minimise


def _people() -> list[PreferenceData]:
    g = torch.Generator().manual_seed(0)
    C = torch.tensor([[0, 1], [2, 3], [4, 5], [6, 7], [1, 2]])
    return [PreferenceData.create(torch.rand(8, 2, generator=g, dtype=torch.float64), C) for _ in range(4)]


def test_a_start_at_the_lengthscale_bound_fails_by_name():
    k_m = default_covar_module(2)
    k_m.base_kernel.lengthscale = 1e-4  # the constraint's bound: its raw value is -inf
    with pytest.raises(FitStartError, match=r"k_m: lengthscale \[0\.0001, 0\.0001\].*longer lengthscales"):
        fit_population(_people(), k_m=k_m, max_iter=5)
    assert issubclass(FitStartError, ValueError)


class _Bar:
    def update(self) -> None:
        pass


def test_a_non_finite_loss_in_the_line_search_rejects_the_step():
    x = torch.tensor([3.0], dtype=torch.float64, requires_grad=True)
    seen: list[float] = []

    def loss() -> torch.Tensor:
        seen.append(float(x.detach()))
        value = (x - 10.0) ** 2
        return value if seen[-1] < 8.0 else value * float("nan")  # a wall the minimum lies behind

    rejected = minimise(loss, [x], 50, _Bar(), lambda: "x")
    assert rejected >= 1 and any(v >= 8.0 for v in seen)  # it met the wall ...
    assert 7.0 < float(x.detach()) < 8.0  # ... and ended at the best finite point, near it
