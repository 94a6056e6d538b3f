r"""Which solver runs: the compiled small-problem path (:mod:`torchpref.inference._compiled`,
numba) or the torch solver, and the setting that forces either (docs/speed.md, "The compiled path").

The setting, in order of precedence: :func:`fast_path` as a context manager (``with
torchpref.fast_path("off"): ...``) or called once (``torchpref.fast_path("on")``), else the
environment variable ``TORCHPREF_FAST_PATH``, else ``"auto"``:

* ``"off"``: the torch solver everywhere.
* ``"on"``: the compiled path wherever it applies (compiling it now if no on-disk cache exists).
* ``"auto"``: the compiled path where it applies and is faster (up to :data:`MODE_MAX_ITEMS`
  items for a mode, :data:`FIT_MAX_ITEMS` for a fit). It is loaded at the second fit of a process
  (:data:`LOAD_AT_FIT`: loading numba, 0.5-1 s, pays back over a loop of fits, not over one), or
  by :func:`warm_up`; modes use it once it is loaded, so a program that fits once or only
  predicts (``torchpref elicit``, ``serve``) runs as before. It
  is loaded only from numba's on-disk cache: where that does not exist yet (the first use after
  installing), a background process compiles it while the torch solver answers, so no call
  waits for the compiler.

It applies to one problem (no batch), on the CPU, in float64, with probit comparisons only, and,
for a fit, the stationary kernels :mod:`torchpref.models.fast_fit` lists. numba is imported on the
first solve that uses it, never at ``import torchpref``. Without numba (the ``fast`` extra) every
setting gives the torch solver.
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import threading
from pathlib import Path
from types import ModuleType
from typing import Any

import torch
from torch import Tensor

from torchpref.inference.observations import Observations

ENV = "TORCHPREF_FAST_PATH"
SETTINGS = ("auto", "on", "off")
#: ``auto`` solves modes compiled up to this many items, and fits (measured: at 300 items the
#: compiled fit took 0.84 of the torch fit's time, at 500 items 1.11; the mode 0.54 and 0.88):
#: from 500 items on ``auto`` is the torch solver, as before (docs/speed.md)
MODE_MAX_ITEMS = 400
FIT_MAX_ITEMS = 400
#: the compiled functions whose on-disk cache ``auto`` waits for
ENTRY_POINTS = ("newton", "fit_lbfgs", "mode_and_evidence")

_override: list[str] = []
_lock = threading.Lock()
#: ``auto`` loads the compiled path at a process's second fit: the first fit is the torch solver's,
#: as before, so a program that fits once never pays numba's import (0.5-1 s); a loop that refits
#: pays it once, at its second fit
LOAD_AT_FIT = 2
_state: dict[str, Any] = {"module": None, "warming": None, "fits": 0}


def _check(value: str) -> str:
    if value not in SETTINGS:
        raise ValueError(f"the fast-path setting must be one of {SETTINGS}, got {value!r}.")
    return value


def setting() -> str:
    """The current setting: ``"auto"``, ``"on"`` or ``"off"``."""
    if _override:
        return _override[-1]
    env = os.environ.get(ENV, "").strip().lower()
    if not env:
        return "auto"
    if env not in SETTINGS:
        raise ValueError(f"{ENV} must be one of {SETTINGS}, got {env!r}.")
    return env


class fast_path:  # lower case: used as a function and a context manager, like torch.no_grad
    """Force the compiled path (``"on"``), the torch solver (``"off"``) or let each call choose
    (``"auto"``). As a context manager it applies inside the block; called alone, until changed."""

    def __init__(self, mode: str):
        self.mode = _check(mode)
        self._previous = list(_override)
        _override[:] = [self.mode]

    def __enter__(self) -> fast_path:
        return self

    def __exit__(self, *exc: object) -> None:
        _override[:] = self._previous


def available() -> bool:
    """Whether numba is installed (the ``fast`` extra) and not blocked (``sys.modules["numba"] = None``)."""
    if "numba" in sys.modules:
        return sys.modules["numba"] is not None
    try:
        return importlib.util.find_spec("numba") is not None
    except (ImportError, ValueError):
        return False


def _cache_dirs() -> list[Path]:
    """Where numba keeps this package's cache: ``NUMBA_CACHE_DIR`` if set, else beside the module
    (or, where that is not writable, numba's user-wide cache folder)."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return [Path(os.environ["NUMBA_CACHE_DIR"])]
    home = Path.home()
    if sys.platform == "darwin":
        user = home / "Library" / "Caches" / "numba"
    elif sys.platform == "win32":
        user = Path(os.environ.get("LOCALAPPDATA", home)) / "numba" / "numba" / "Cache"
    else:
        user = Path(os.environ.get("XDG_CACHE_HOME", home / ".cache")) / "numba"
    return [Path(__file__).resolve().parent / "__pycache__", user]


def cached_on_disk() -> bool:
    """Whether numba's on-disk cache holds every entry point (judged by its index files)."""
    tag = f"py{sys.version_info.major}{sys.version_info.minor}"
    for name in ENTRY_POINTS:
        pattern = f"_compiled.{name}-*.{tag}.nbi"
        if not any(any(d.rglob(pattern)) for d in _cache_dirs() if d.is_dir()):
            return False
    return True


def _warm_in_background() -> None:
    """Compile (and cache) the entry points in a separate process, once per process."""
    if _state["warming"] is not None:
        return
    cmd = [sys.executable, "-c", "import torchpref.inference.fast_path as f; f.warm_up()"]
    try:
        _state["warming"] = subprocess.Popen(
            cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
        )
    except OSError:
        _state["warming"] = False


def compiled(load: bool = False) -> ModuleType | None:
    """:mod:`torchpref.inference._compiled` if the setting and the installation allow it now, else
    ``None``: for ``"off"`` or without numba. For ``"on"`` it is loaded (compiled, where no on-disk
    cache exists) on first use. For ``"auto"`` only once loaded, or when ``load`` (a fit) from the
    :data:`LOAD_AT_FIT`-th fit of the process on, and only from the on-disk cache: while there is
    none, a background process compiles it and the torch solver answers."""
    mode = setting()
    if mode == "off" or not available():
        return None
    module = _state["module"]
    if module is not None:
        return module
    if mode == "auto" and not load:
        return None
    with _lock:
        if _state["module"] is None:
            if mode == "auto":
                if not cached_on_disk():
                    _warm_in_background()
                    return None
                _state["fits"] += 1
                if _state["fits"] < LOAD_AT_FIT:
                    return None
            _state["module"] = importlib.import_module("torchpref.inference._compiled")
    return _state["module"]


def warm_up() -> ModuleType | None:
    """Load (compiling where no on-disk cache exists) every compiled entry point now, e.g. at
    the start of a program that will fit many small models; ``None`` without numba."""
    if not available():
        return None
    import numpy as np

    module = importlib.import_module("torchpref.inference._compiled")
    X = np.array([[0.0, 0.0], [0.5, 0.2], [0.9, 0.7]])
    C = np.array([[0, 1], [2, 1]], dtype=np.int64)
    spec = np.array([0.0, 2.0, 2.0, 1e-4, 0.0, 1.0, 1.7, 1.7, 2.0, 2.0, 1.0, 1.0, -1.5, 0.0])
    module.fit_lbfgs(np.zeros(3), X, C, 1.4, 0, spec, np.zeros(3), 1e-11, 100)
    L = np.linalg.cholesky(module.kernel_matrix(X, np.ones(2), 1.0, 0))
    module.newton(L, C, 1.4, np.zeros((1, 3)), 1e-11, 100)
    module.mode_and_evidence(X, C, 1.4, 3, np.ones(2), 1.0, np.zeros(0), 1e-11, 100)
    _state["module"] = module
    return module


def known_probit(likelihood: object) -> bool:
    """Whether ``likelihood`` is one the compiled path computes: its class declares
    ``compiled_kind = "probit"`` itself (not inherited) and no derivative is replaced on the object."""
    if type(likelihood).__dict__.get("compiled_kind") != "probit":
        return False
    own = getattr(likelihood, "__dict__", {})
    return not any(name in own for name in ("derivatives", "third_derivative", "_scale", "log_prob"))


def probit_scale(obs: Observations) -> float | None:
    """``sqrt 2 sigma_R`` when ``obs`` is one problem's unmasked probit comparisons (the one
    kind the compiled path knows), else ``None``."""
    if obs.batch != 1 or len(obs.terms) != 1:
        return None
    term = obs.terms[0]
    lik = term.likelihood
    if not known_probit(lik) or term.coef != (1.0, -1.0) or term.target is not None:
        return None
    if term.offset is not None:  # a prior mean (a population's): the torch solver's
        return None
    if term.mask is not None and not bool(term.mask.all()):
        return None
    return float(lik.scale)  # type: ignore[attr-defined]


def mode_applies(L: Tensor, obs: Observations) -> bool:
    """Whether the mode of ``L`` (``1 x n x n``) and ``obs`` may be solved compiled (before the
    setting and the installation are asked)."""
    n = L.shape[-1]
    if L.dtype != torch.float64 or L.device.type != "cpu" or L.shape[0] != 1 or n == 0:
        return False
    return setting() == "on" or n <= MODE_MAX_ITEMS
