r"""Optional dependencies: which extra installs what, and the one-line message when one is missing.

torchpref's core needs torch, GPyTorch, BoTorch, NumPy and tqdm. Drawing figures needs the
``plot`` extra (matplotlib), the notebook widget the ``widgets`` extra (ipywidgets). A feature
that needs a missing one raises :class:`MissingExtraError` (an ``ImportError``) whose message is
one line naming the extra to install, e.g. ``pip install "torchpref[plot]"``; the command line
and the demo check before any work starts (:func:`missing`) and print that line.

This module imports nothing beyond the standard library, so the command line can check before
torch is loaded. It is the floor of the package's stages: every stage may import it.
"""

from __future__ import annotations

import importlib
import importlib.util
from collections.abc import Iterable
from types import ModuleType

EXTRAS: dict[str, str] = {
    "matplotlib": "plot",
    "ipywidgets": "widgets",
    "starlette": "serve",
    "uvicorn": "serve",
    "jinja2": "serve",
    "numba": "fast",
}
"""Importable module -> the extra of ``pyproject.toml`` that installs it."""


class MissingExtraError(ImportError):
    """An optional dependency is not installed; the message names the extra that installs it."""


def install_hint(extra: str) -> str:
    """The command that installs ``extra``: ``pip install "torchpref[EXTRA]"``."""
    return f'pip install "torchpref[{extra}]"'


def message(module: str, what: str, extra: str | None = None) -> str:
    """The one-line message: ``WHAT needs MODULE, which is not installed: pip install "torchpref[EXTRA]"``."""
    extra = extra if extra is not None else EXTRAS.get(module.split(".")[0])
    if extra is None:
        raise ValueError(f"no extra of torchpref installs {module!r}; known: {sorted(EXTRAS)}")
    return f"{what} needs {module}, which is not installed: {install_hint(extra)}"


def is_installed(module: str) -> bool:
    """Whether ``module`` can be imported, found without importing it."""
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # a parent that is missing, or a module blocked in sys.modules
        return False


def missing(modules: Iterable[str], what: str) -> str | None:
    """The one-line message for the first of ``modules`` that is not installed, or ``None``."""
    for module in modules:
        if not is_installed(module):
            return message(module, what)
    return None


def require(module: str, what: str, extra: str | None = None) -> ModuleType:
    """Import and return ``module``.

    Raises:
        MissingExtraError: ``module`` (or a module it needs) is not installed; the message is
            :func:`message`'s one line.
    """
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        raise MissingExtraError(message(module, what, extra), name=exc.name) from None
