r"""The compiled path's on-disk cache (issue 42): which cache belongs to this installation, loading
it without ever compiling, and the explicit build that compiles it (``torchpref fast-path build``,
:func:`torchpref.inference.fast_path.build`).

numba keeps each compiled function's machine code in an index (``.nbi``) and data (``.nbc``) file
in one folder (:func:`folder`: ``NUMBA_CACHE_DIR`` if set, else ``__pycache__`` beside the module,
else numba's user-wide folder). :func:`build` removes this package's files there, compiles the
entry points (:data:`ENTRY_POINTS`) for exactly the argument types the library passes
(:mod:`torchpref.inference.fast_types`), and writes a manifest (:data:`MANIFEST`) naming the
installation it was built for (:func:`identity`: torchpref's and numba's versions, Python's, and a
hash of the compiled modules' sources) and a hash of every file. :func:`load` uses a cache only
when the manifest is this installation's and every file is as built; it then loads each entry
point from its files and switches numba's compiler off for them, so that no call can start a
compilation. Anything else raises :class:`CacheUnusable` with the reason, before numba reads a byte.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.metadata
import importlib.util
import json
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

import torchpref.inference.fast_types as ft
from torchpref.version import __version__

#: entry point -> the module that defines it
ENTRY_POINTS = {
    "newton": "torchpref.inference._compiled",
    "fit_lbfgs": "torchpref.inference._compiled_fit",
    "fit_loss": "torchpref.inference._compiled_fit",
}
#: the sources the compiled code is made of (numba checks only the entry point's own file)
SOURCES = ("_compiled.py", "_compiled_fit.py", "fast_types.py", "step_rule.py")
#: the manifest beside numba's files
MANIFEST = "torchpref-fast-path.json"
#: how a person builds the cache
COMMAND = "torchpref fast-path build"
#: the file-name prefixes of this package's cache files in the folder
PREFIXES = ("_compiled.", "_compiled_fit.")


class CacheUnusable(Exception):
    """No cache of this installation can be loaded; the message says why."""


@dataclass(frozen=True)
class Built:
    """What :func:`build` did: the cache folder, the seconds each entry point took, the files written."""

    folder: Path
    seconds: dict[str, float]
    files: tuple[str, ...]


def problem() -> str | None:
    """Why the compiled path cannot be loaded in this process (``None``: it can): numba or
    threadpoolctl (the ``fast`` extra) not installed or blocked, or a ``numba`` that is a file or
    folder in the working directory (a stray ``numba.py``, which would be run)."""
    if "numba" in sys.modules and sys.modules["numba"] is None:
        return "numba is blocked in this process"
    try:
        spec = importlib.util.find_spec("numba")
        pool = importlib.util.find_spec("threadpoolctl")
    except (ImportError, ValueError) as err:
        return f"numba cannot be found ({err})"
    if spec is None or pool is None:
        return 'numba and threadpoolctl are not installed (pip install "torchpref[fast]")'
    origin = Path(spec.origin or "").resolve()
    if spec.submodule_search_locations is None or origin.parent.parent == Path.cwd().resolve():
        return f"'numba' would be imported from {origin}, in the working directory, not from the installed package"
    return None


def installed() -> bool:
    """Whether numba and threadpoolctl can be found (even if :func:`problem` refuses them)."""
    try:
        return importlib.util.find_spec("numba") is not None and importlib.util.find_spec("threadpoolctl") is not None
    except (ImportError, ValueError):
        return False


def identity() -> dict[str, str]:
    """The installation a cache belongs to: torchpref's, numba's and Python's versions and the
    SHA-256 of the compiled modules' sources (:data:`SOURCES`)."""
    here = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for name in SOURCES:
        digest.update(name.encode() + b"\0" + (here / name).read_bytes() + b"\0")
    return {
        "torchpref": __version__,
        "numba": importlib.metadata.version("numba"),
        "python": f"{sys.version_info.major}.{sys.version_info.minor}",
        "sources": digest.hexdigest(),
    }


def example_arguments() -> dict[str, tuple]:
    """Arguments of each entry point of the types the library passes (a 3-item problem with a row
    of each kind): their numba types are the signatures compiled and loaded."""
    X = ft.floats([[0.0, 0.0], [0.5, 0.2], [0.9, 0.7]], 2)
    inf = np.inf
    ans = ft.answers(
        [0, 2, 1, 2, 0],
        [1, -1, 2, -1, 2],
        [ft.PROBIT, ft.BETA, ft.INTERVAL, ft.INTERVAL, ft.LAPSE],
        [0.0, 0.1, 0.0, 0.0, 0.0],
        [0.0, 0.6, 0.0, 0.0, 0.0],
        [1.4, 0.0, 1.4, 0.2, 1.4],
        [-inf, -inf, -0.1, -0.4, -inf],
        [inf, inf, 0.1, 0.4, inf],
        [0.0, 0.0, 0.0, 0.0, 0.05],
        1.4,
        20.0,
    )
    spec = ft.fit_spec(ft.RBF, 0, 2, 1e-4, (ft.LOG_NORMAL, 1.7, 1.7, -1.5), 2, 0.0, (ft.GAMMA, 2.0, 2.0, 0.0), 1.0)
    x0 = ft.floats(np.zeros(3))
    L = ft.floats(np.linalg.cholesky(np.eye(3) + 0.5), 2)
    return {
        "newton": (L, ans, ft.floats(np.zeros((1, 3)), 2), 1e-11, 100),
        "fit_lbfgs": (x0, X, ans, spec, ft.fit_state(np.zeros(3), 5), 1e-11, 100),
        "fit_loss": (x0, X, ans, spec, ft.fit_state(np.zeros(3), 5), 1e-11, 100),
    }


def functions() -> dict[str, Any]:
    """The entry points' numba dispatchers (imports numba and the compiled modules, compiles nothing)."""
    why = problem()
    if why is not None:
        raise CacheUnusable(why)
    import scipy.linalg.cython_lapack  # noqa: F401  (numba's LAPACK: loaded before anything counts threads)

    return {name: getattr(importlib.import_module(module), name) for name, module in ENTRY_POINTS.items()}


def folder(dispatchers: dict[str, Any]) -> Path:
    """Where numba keeps the entry points' cache; :class:`CacheUnusable` where ``NUMBA_CACHE_DIR``
    names a folder numba cannot use (numba would silently use another one)."""
    from numba.core import config

    paths = {Path(d._cache._cache_path) for d in dispatchers.values()}
    if len(paths) != 1:
        raise CacheUnusable(f"the entry points are cached in several folders: {sorted(map(str, paths))}")
    path = paths.pop()
    asked = getattr(config, "CACHE_DIR", "")
    if asked and Path(asked).resolve() not in path.resolve().parents:
        raise CacheUnusable(f"NUMBA_CACHE_DIR={asked} is not a folder numba can write to")
    return path


def _ours(path: Path) -> list[Path]:
    if not path.is_dir():
        return []
    return sorted(p for p in path.iterdir() if p.name.startswith(PREFIXES) and p.suffix in (".nbi", ".nbc"))


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _signature(args: tuple) -> tuple:
    from numba import typeof

    return tuple(typeof(a) for a in args)


def check_manifest(path: Path) -> None:
    """:class:`CacheUnusable` unless ``path`` holds a manifest of this installation whose files are
    all present and unchanged."""
    try:
        manifest = json.loads((path / MANIFEST).read_text())
    except FileNotFoundError:
        raise CacheUnusable(f"no compiled cache has been built in {path}") from None
    except (OSError, ValueError) as err:
        raise CacheUnusable(f"the cache manifest {path / MANIFEST} cannot be read ({err})") from None
    mine = identity()
    theirs = manifest.get("identity") if isinstance(manifest, dict) else None
    if theirs != mine:
        diff = [k for k in mine if not isinstance(theirs, dict) or theirs.get(k) != mine[k]]
        raise CacheUnusable(f"the cache in {path} was built for another installation (its {', '.join(diff)} differ)")
    for name, digest in manifest.get("files", {}).items():
        try:
            ok = _sha256(path / name) == digest
        except OSError as err:
            raise CacheUnusable(f"the cache file {path / name} cannot be read ({err.strerror or err})") from None
        if not ok:
            raise CacheUnusable(f"the cache file {path / name} has changed since it was built")


def load() -> tuple[dict[str, Any], Path]:
    """The entry points loaded from this installation's cache, and its folder; numba's compiler is
    switched off for them. :class:`CacheUnusable` (never a compilation) where that cannot be done."""
    try:
        dispatchers = functions()
        path = folder(dispatchers)
        check_manifest(path)
        examples = example_arguments()
        for name, d in dispatchers.items():
            if not _load_one(d, _signature(examples[name])):
                raise CacheUnusable(f"the cache in {path} has no compiled {name} of the types passed")
    except CacheUnusable:
        raise
    except Exception as err:  # anything numba or the file system raises: unusable, named
        raise CacheUnusable(f"the cache could not be loaded ({type(err).__name__}: {err})") from err
    for d in dispatchers.values():
        d.disable_compile()
    return dispatchers, path


def _load_one(dispatcher: Any, sig: tuple) -> bool:
    """Add ``dispatcher``'s overload for ``sig`` from its cache files (never compiling); whether it was there."""
    from numba.core.compiler_lock import global_compiler_lock

    with global_compiler_lock:
        if sig in dispatcher.overloads:
            return True
        cres = dispatcher._cache.load_overload(sig, dispatcher.targetctx)
        if cres is None:
            return False
        if not cres.objectmode:
            dispatcher.targetctx.insert_user_function(cres.entry_point, cres.fndesc, [cres.library])
        dispatcher.add_overload(cres)
    return True


def build(progress: Callable[[str], None] | None = None) -> tuple[Built, dict[str, Any]]:
    """Compile the entry points into the cache folder (this package's old files there removed
    first), write the manifest, and return what was done and the loaded entry points.

    Raises:
        CacheUnusable: numba is not usable here, or the folder cannot be written.
    """
    say = progress or (lambda line: None)
    dispatchers = functions()
    path = folder(dispatchers)
    try:
        for old in _ours(path) + [path / MANIFEST]:
            old.unlink(missing_ok=True)
    except OSError as err:
        raise CacheUnusable(f"the cache folder {path} cannot be written ({err.strerror or err})") from None
    examples, seconds = example_arguments(), {}
    for k, (name, d) in enumerate(dispatchers.items(), 1):
        say(f"compiling {name} ({k} of {len(dispatchers)}) into {path} ...")
        start = time.perf_counter()
        d.enable_caching()  # a fresh cache object: nothing of the removed files remembered
        d.disable_compile(False)
        sig = _signature(examples[name])
        existing = d.overloads.get(sig)
        if existing is None:
            d.compile(sig)
        else:
            d._cache.save_overload(sig, existing)
        seconds[name] = time.perf_counter() - start
        say(f"compiled {name} in {seconds[name]:.1f} s")
    files = _ours(path)
    manifest = {"identity": identity(), "files": {p.name: _sha256(p) for p in files}, "built": time.time()}
    tmp = path / f".{MANIFEST}.{os.getpid()}"
    tmp.write_text(json.dumps(manifest, indent=1))
    os.replace(tmp, path / MANIFEST)
    for d in dispatchers.values():
        d.disable_compile()
    return Built(path, seconds, tuple(p.name for p in files)), dispatchers
