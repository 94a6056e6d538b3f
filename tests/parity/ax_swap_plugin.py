"""A pytest plugin (``-p ax_swap_plugin``) that runs another project's tests and counts which
model each test built (``PreferenceGP`` or BoTorch's ``PairwiseGP``), either as a user runs them
(``TORCHPREF_SWAP_BOTORCH=0``, ``TORCHPREF_SWAP_IMPORT=torchpref.integrations.ax`` and
``TORCHPREF_SWAP_CALL=torchpref.integrations.ax:use_preference_gp``: the import and the one call
docs/ax.md documents, before the tests are collected) or, as a harness, with BoTorch's
``PairwiseGP`` / ``PairwiseLaplaceMarginalLogLikelihood`` swapped for ``PreferenceGP`` /
``LaplaceMarginalLogLikelihood`` (``TORCHPREF_SWAP_BOTORCH=1``, the default).

Counting wraps each class's ``__init__`` (signature kept), so it changes no model that is built.

The harness swap is of the two names in ``botorch.models`` and ``botorch.models.pairwise_gp``, made
before the tests (and Ax or BoFire) are imported, so every ``from botorch.models.pairwise_gp
import PairwiseGP`` — in the tests and in the library under test — gets ``PreferenceGP``. Then
``torchpref.integrations.ax`` (``TORCHPREF_SWAP_IMPORT``) is imported as a user would. Each
test's outcome and the number of ``PreferenceGP`` and of original ``PairwiseGP`` models it built
are written as JSON to ``TORCHPREF_SWAP_REPORT``.
"""

from __future__ import annotations

import functools
import importlib
import inspect
import json
import os

import botorch.models
import botorch.models.pairwise_gp as pairwise_gp

from torchpref.models.preference_gp import LaplaceMarginalLogLikelihood, PreferenceGP

ORIGINAL_MODEL = pairwise_gp.PairwiseGP
ORIGINAL_MLL = pairwise_gp.PairwiseLaplaceMarginalLogLikelihood
_counts: dict[str, dict] = {}
_current: list[str | None] = [None]


def _counting(cls, key):
    init = cls.__init__

    @functools.wraps(init)
    def __init__(self, *args, **kwargs):
        if _current[0] is not None and type(self) is cls:
            _counts.setdefault(_current[0], {"PreferenceGP": 0, "PairwiseGP": 0})[key] += 1
        init(self, *args, **kwargs)

    __init__.__signature__ = inspect.signature(init)  # what Ax's getfullargspec(cls) reads
    cls.__init__ = __init__


def _names() -> dict[str, object]:
    """``TORCHPREF_SWAP_NAMES``: ``name=module:attr,...``, names to rebind in the test modules."""
    out = {}
    for entry in filter(None, os.environ.get("TORCHPREF_SWAP_NAMES", "").split(",")):
        name, target = entry.split("=")
        module, attr = target.split(":")
        out[name] = getattr(importlib.import_module(module), attr)
    return out


def pytest_configure(config):
    if os.environ.get("TORCHPREF_SWAP_BOTORCH", "1") == "1":
        for module in (botorch.models, pairwise_gp):
            module.PairwiseGP = PreferenceGP
            module.PairwiseLaplaceMarginalLogLikelihood = LaplaceMarginalLogLikelihood
    _counting(PreferenceGP, "PreferenceGP")
    _counting(ORIGINAL_MODEL, "PairwiseGP")
    for name in filter(None, os.environ.get("TORCHPREF_SWAP_IMPORT", "").split(",")):
        importlib.import_module(name)
    for target in filter(None, os.environ.get("TORCHPREF_SWAP_CALL", "").split(",")):
        module, attr = target.split(":")
        getattr(importlib.import_module(module), attr)()  # e.g. the documented use_preference_gp()


def pytest_collection_modifyitems(session, config, items):
    """Rebind ``TORCHPREF_SWAP_NAMES`` in each test module (its functions read them at call time)."""
    names = _names()
    originals: dict[int, object] = {}  # id(original object) -> its replacement
    for module in {id(m): m for m in (getattr(item, "module", None) for item in items) if m is not None}.values():
        for name, value in names.items():
            if name in vars(module):
                originals[id(vars(module)[name])] = value
                setattr(module, name, value)
    # parametrize arguments were bound at import: the same objects are swapped there
    for item in items:
        params = getattr(getattr(item, "callspec", None), "params", {})
        for key, value in list(params.items()):
            if id(value) in originals:
                params[key] = originals[id(value)]


def pytest_runtest_setup(item):
    _current[0] = item.nodeid


def pytest_runtest_logreport(report):
    entry = _counts.setdefault(report.nodeid, {"PreferenceGP": 0, "PairwiseGP": 0})
    if report.when == "call" or (report.when == "setup" and report.outcome != "passed"):
        if entry.get("outcome") != "failed":  # a failed subtest's report comes before the test's own
            entry["outcome"] = "xfailed" if hasattr(report, "wasxfail") else report.outcome
        if report.outcome == "failed":
            entry["error"] = entry.get("error", "") + str(report.longrepr)[-1500:]


def pytest_sessionfinish(session, exitstatus):
    path = os.environ.get("TORCHPREF_SWAP_REPORT")
    if path:
        with open(path, "w") as f:
            json.dump(_counts, f, indent=1, sort_keys=True)
