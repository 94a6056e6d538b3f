"""Shared helpers for torchpref's tests and benchmarks, and for users who test code built on it.

* seeded float64 samples (:func:`rand`, :func:`randn`) and random comparisons
  (:func:`random_comparisons`), with no global dtype switch;
* :func:`assert_evidence_gradient`: the Laplace evidence's autograd gradient against central
  differences of the re-solved evidence;
* :mod:`torchpref.testing.problems`: the hostile problems of the fuzz and the hostile-start fits;
* :mod:`torchpref.testing.lake_worlds`: small synthetic lake worlds;
* :mod:`torchpref.testing.serve`: ``torchpref serve`` run as a process, with a scripted answerer.

Nothing here is imported by the rest of the package; ``pytest`` is not needed to import it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from torchpref.models.preference_gp import PreferenceGP

__all__ = ["DTYPE", "SEED", "assert_evidence_gradient", "rand", "randn", "random_comparisons"]

SEED = 20170517
DTYPE = torch.float64


def rand(*shape, generator: torch.Generator, low: float = 0.0, high: float = 1.0) -> torch.Tensor:
    """Uniform float64 samples on ``[low, high)``."""
    return low + (high - low) * torch.rand(*shape, generator=generator, dtype=DTYPE)


def randn(*shape, generator: torch.Generator) -> torch.Tensor:
    """Standard normal float64 samples."""
    return torch.randn(*shape, generator=generator, dtype=DTYPE)


def random_comparisons(n: int, p: int, generator: torch.Generator) -> torch.Tensor:
    """``p x 2`` long tensor of random distinct pairs of indices in ``0..n-1``."""
    i = torch.randint(0, n, (p,), generator=generator)
    j = (i + torch.randint(1, n, (p,), generator=generator)) % n
    return torch.stack([i, j], dim=-1)


def assert_evidence_gradient(model: PreferenceGP, params: dict, h: float = 1e-5, rtol: float = 1e-5) -> None:
    """Autograd's gradient of ``model.log_marginal_likelihood()`` in each raw parameter of
    ``params`` (name -> tensor) against central differences of the re-solved evidence, element by
    element; each parameter is put back, so the evidence is unchanged afterwards."""
    value = model.log_marginal_likelihood()
    grads = torch.autograd.grad(value, list(params.values()), allow_unused=True)
    for (name, p), g in zip(params.items(), grads):
        assert g is not None, f"no gradient for {name}"
        for k in range(p.numel()):
            with torch.no_grad():
                p.view(-1)[k] += h
                up = float(model.log_marginal_likelihood().detach())  # re-solves the mode
                p.view(-1)[k] -= 2 * h
                down = float(model.log_marginal_likelihood().detach())
                p.view(-1)[k] += h
            fd = (up - down) / (2 * h)
            gk = float(g.reshape(-1)[k])
            assert abs(gk - fd) <= rtol * max(abs(fd), 1e-2), f"{name}[{k}]: autograd {gk} vs FD {fd}"
    assert abs(float(model.log_marginal_likelihood().detach()) - float(value.detach())) < 1e-10  # restored
