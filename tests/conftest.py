"""Shared test fixtures: a seeded generator and float64 helpers (no global dtype switch)."""

import pytest
import torch

SEED = 20170517
DTYPE = torch.float64
#: CPU always; CUDA where this machine has it (no GPU was lent to the sessions so far: the CUDA
#: cases have not run yet).
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    """Each available device in turn."""
    return torch.device(request.param)


@pytest.fixture
def generator() -> torch.Generator:
    """A fresh, seeded CPU generator for each test."""
    return torch.Generator().manual_seed(SEED)


@pytest.fixture
def tkwargs() -> dict:
    """``dtype`` / ``device`` keyword arguments for new tensors."""
    return {"dtype": DTYPE, "device": torch.device("cpu")}


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


@pytest.fixture
def helpers():
    """The helper functions above, for test files that prefer fixtures to imports."""
    return type(
        "Helpers",
        (),
        {
            "rand": staticmethod(rand),
            "randn": staticmethod(randn),
            "random_comparisons": staticmethod(random_comparisons),
        },
    )
