"""Shared test fixtures: a seeded generator and float64 helpers (no global dtype switch)."""

import pytest
import torch

from torchpref.testing import DTYPE, SEED, rand, randn, random_comparisons

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


@pytest.fixture
def deflated_copy():
    """``copy(src, dst)``: the ``torch.save`` archive ``src`` rewritten to ``dst`` with every record
    compressed (what the checkpoint and population loaders must refuse: it expands under ``torch.load``)."""
    import zipfile

    def copy(src, dst):
        with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as out:
            for info in zin.infolist():
                out.writestr(info.filename, zin.read(info.filename), compress_type=zipfile.ZIP_DEFLATED)
        return dst

    return copy
