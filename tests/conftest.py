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


# --- a recorded test run (issue 53): the counts and the wall time of the run that docs/install.md quotes
#: where a run writes its record: ``TORCHPREF_RECORD_TESTS=benchmarks/results/test_runs/default.json make test``
RECORD_ENV = "TORCHPREF_RECORD_TESTS"
_OUTCOMES = ("passed", "failed", "skipped", "xfailed", "xpassed", "error")


def pytest_sessionstart(session):
    import time

    session.config._torchpref_record_start = time.perf_counter()


def pytest_sessionfinish(session, exitstatus):
    """With ``TORCHPREF_RECORD_TESTS`` naming a path, write the run's counts, wall time and pytest
    arguments there as a stamped JSON (``torchpref.experiments.results.write_json``, path ``"user"``)."""
    import os
    import time

    path = os.environ.get(RECORD_ENV)
    if not path:
        return
    start = getattr(session.config, "_torchpref_record_start", None)
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    stats = reporter.stats if reporter is not None else {}
    counts = {k: len(stats.get(k, [])) for k in _OUTCOMES}  # as pytest's summary line counts them
    from torchpref.experiments.results import write_json

    write_json(
        path,
        {
            "counts": {**{k: v for k, v in counts.items() if k != "error"}, "errors": counts["error"]},
            "wall_s": round(time.perf_counter() - start, 1) if start is not None else None,
            "exit_status": int(exitstatus),
            "args": list(session.config.invocation_params.args),
            "markexpr": session.config.getoption("markexpr") or "",
            "cpu_count": os.cpu_count(),
        },
        measured="user",
    )
