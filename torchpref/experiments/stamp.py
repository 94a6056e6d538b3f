r"""Stamped results: every results file says what it measured, on what, and whether it still holds.

A *stamp* (:func:`make_stamp`) is a dictionary written into a results file under ``"stamp"``:

* ``commit`` (``git rev-parse HEAD`` of the checkout, or ``None``) and ``dirty`` (uncommitted
  changes to the sources below);
* ``sources``: ``{path: sha256}`` of the files the result depends on: the script that wrote it and
  every ``torchpref`` module loaded in the process when it was written, and in every process it
  started under :func:`recording_subprocesses` (what the measured code actually ran; packages'
  ``__init__`` files, which only re-export names, left out), paths relative to the repository root;
* ``code``: ``{path: digest}`` of the same files' *code*: a Python file's syntax tree without its
  docstrings, comments and formatting (:func:`code_digest`), so that a change to a page of
  documentation, a comment or the layout of a line leaves a result fresh;
* ``versions`` of Python, torch, GPyTorch, BoTorch, NumPy and torchpref;
* ``load_avg`` (1, 5, 15 minutes) and ``cpu_count`` when it was written;
* ``wall_s`` and ``cpu_s``: the process's wall time since it started and its CPU time (user +
  system, children included) when the file was written;
* ``path``: *what was measured*: ``"user"`` (the documented user path) or ``"harness: ..."``
  naming a test harness (a count under a harness is labelled so beside the user-path count).

:func:`status` compares a stamp's ``code`` (``sources`` for stamps written before it existed)
with the files as they are now: a result is ``"fresh"`` when every source's code is unchanged, ``"stale"`` (with the files that changed or went)
otherwise, and ``"unstamped"`` without a stamp. ``make results-status`` lists every results file
so (``benchmarks/results_status.py``); the docs mark a figure read from a stale file.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

#: The repository root: the folder holding the ``torchpref`` package (a source checkout).
ROOT = Path(__file__).resolve().parents[2]
_T0 = time.time()  # the process's start where /proc cannot tell it


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def code_digest(path: Path) -> str:
    """A digest of what a file does: for Python, its syntax tree with every docstring removed,
    dumped without line numbers (comments and formatting never reach the tree); for anything
    else (data), its bytes. A file that does not parse is digested as bytes."""
    import ast

    if path.suffix != ".py":
        return _sha256(path)
    try:
        tree = ast.parse(path.read_bytes())
    except (SyntaxError, ValueError):
        return _sha256(path)
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body:
            first = body[0]
            if (
                isinstance(first, ast.Expr)
                and isinstance(first.value, ast.Constant)
                and isinstance(first.value.value, str)
            ):
                node.body = body[1:] or [ast.Pass()]
    return "code:" + hashlib.sha256(ast.dump(tree, include_attributes=False).encode()).hexdigest()


SUBPROCESS_VAR = "TORCHPREF_STAMP_SOURCES"
"""When set (to a folder), each process that imports torchpref writes the files of its loaded
torchpref modules there at exit (:func:`record_at_exit`), for the stamp of the measurement that
started it (:func:`recording_subprocesses`)."""


def record_at_exit() -> None:
    """Write this process's loaded torchpref modules' files to ``$TORCHPREF_STAMP_SOURCES/PID.json``
    when it exits (called by ``import torchpref`` only where the variable is set)."""
    import atexit

    folder = os.environ.get(SUBPROCESS_VAR)
    if not folder:
        return

    def write() -> None:
        files = [f for name, m in list(sys.modules.items()) if (f := _module_file(name, m)) is not None]
        try:
            Path(folder, f"{os.getpid()}.json").write_text(json.dumps(files))
        except OSError:
            pass

    atexit.register(write)


def _module_file(name: str, module: Any) -> str | None:
    f = getattr(module, "__file__", None)
    # a package's __init__ only re-exports its modules' names (docs/architecture.md): not hashed,
    # so that adding a public name does not make every result stale
    if (name == "torchpref" or name.startswith("torchpref.")) and f and not f.endswith("__init__.py"):
        return str(f)
    return None


class recording_subprocesses:
    """``with recording_subprocesses():`` every process started inside (and any it starts) that
    imports torchpref records its loaded modules, and a stamp written inside hashes them too."""

    def __enter__(self) -> recording_subprocesses:
        import tempfile

        self._before = os.environ.get(SUBPROCESS_VAR)
        self.folder = tempfile.mkdtemp(prefix="torchpref-stamp-")
        os.environ[SUBPROCESS_VAR] = self.folder
        return self

    def __exit__(self, *exc: object) -> None:
        import shutil

        if self._before is None:
            os.environ.pop(SUBPROCESS_VAR, None)
        else:
            os.environ[SUBPROCESS_VAR] = self._before
        shutil.rmtree(self.folder, ignore_errors=True)  # read by the stamps written inside; not after


def _subprocess_files() -> set[Path]:
    folder = os.environ.get(SUBPROCESS_VAR)
    out: set[Path] = set()
    if not folder or not Path(folder).is_dir():
        return out
    for f in Path(folder).glob("*.json"):
        try:
            out.update(Path(p).resolve() for p in json.loads(f.read_text()))
        except (OSError, ValueError, TypeError):
            continue
    return out


def _relative(path: Path, root: Path) -> str | None:
    try:
        return path.resolve().relative_to(root.resolve()).as_posix()
    except ValueError:
        return None


def loaded_sources(root: Path = ROOT, extra: Iterable[str | os.PathLike] = ()) -> dict[str, str]:
    """``{path: sha256}`` of the running script (``sys.argv[0]`` when it is a file under ``root``),
    of ``extra`` files, and of every loaded ``torchpref`` module's file under ``root``."""
    files: set[Path] = set()
    main = Path(sys.argv[0]) if sys.argv and sys.argv[0] else None
    if main is not None and main.suffix == ".py" and main.is_file():
        files.add(main.resolve())
    files.update(Path(p).resolve() for p in extra)
    for name, module in list(sys.modules.items()):
        if (loaded := _module_file(name, module)) is not None:
            files.add(Path(loaded).resolve())
    files.update(_subprocess_files())  # what processes started under recording_subprocesses() ran
    out = {}
    for f in sorted(files):
        rel = _relative(f, root)
        if rel is not None and f.is_file():
            out[rel] = _sha256(f)
    return out


def _git(root: Path, *args: str) -> str | None:
    try:
        done = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def _versions() -> dict[str, str | None]:
    from importlib.metadata import PackageNotFoundError, version

    out: dict[str, str | None] = {"python": platform.python_version()}
    for name in ("torch", "gpytorch", "botorch", "numpy", "torchpref"):
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = None
    return out


def _process_wall_s() -> float:
    """Seconds since this process started (Linux: from /proc; elsewhere since this module loaded)."""
    try:
        start_ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return uptime - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return time.time() - _T0


def _process_cpu_s() -> float:
    try:
        import resource  # Unix
    except ImportError:
        return time.process_time()
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def make_stamp(
    path: str = "user", *, sources: Iterable[str | os.PathLike] = (), root: Path = ROOT, **extra: Any
) -> dict[str, Any]:
    """A stamp for a result written now (see the module docstring).

    Args:
        path: ``"user"`` (the documented user path) or ``"harness: <name>"``.
        sources: files the result depends on beyond the script and the loaded ``torchpref``
            modules (data files, a peer's script).
        root: the repository root the source paths are relative to.
        extra: further entries (e.g. ``note="quiet machine"``).
    """
    if path != "user" and not path.startswith("harness: "):
        raise ValueError(f'path must be "user" or "harness: <name>", got {path!r}.')
    hashed = loaded_sources(root, sources)
    dirty = _git(root, "status", "--porcelain", "--", *hashed) if hashed else None
    return {
        "commit": _git(root, "rev-parse", "HEAD"),
        "dirty": bool(dirty),
        "sources": hashed,
        "code": {rel: code_digest(root / rel) for rel in hashed},
        "versions": _versions(),
        "load_avg": [round(x, 2) for x in os.getloadavg()],
        "cpu_count": os.cpu_count(),
        "wall_s": round(_process_wall_s(), 3),
        "cpu_s": round(_process_cpu_s(), 3),
        "path": path,
        "written": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        **extra,
    }


def status(file: str | os.PathLike, root: Path = ROOT) -> tuple[str, str]:
    """``(state, reason)`` of a results file: ``"fresh"``, ``"stale"`` (naming the sources that
    changed or are gone) or ``"unstamped"``."""
    try:
        data = json.loads(Path(file).read_text())
    except (OSError, ValueError) as err:
        return "unstamped", f"not readable as JSON ({type(err).__name__})"
    stamp = data.get("stamp") if isinstance(data, dict) else None
    if not isinstance(stamp, dict) or not isinstance(stamp.get("sources"), dict):
        return "unstamped", "no stamp"
    changed = []
    code = stamp.get("code") if isinstance(stamp.get("code"), dict) else None
    for rel, digest in sorted((code or stamp["sources"]).items()):
        f = root / rel
        if not f.is_file():
            changed.append(f"{rel} (gone)")
        elif (code_digest(f) if code is not None else _sha256(f)) != digest:
            changed.append(rel)
    if changed:
        return "stale", "changed since the stamp: " + ", ".join(changed[:6]) + (" ..." if len(changed) > 6 else "")
    return "fresh", f"measured at {str(stamp.get('commit'))[:10]} ({stamp.get('path')})"


def stamped(obj: dict[str, Any], path: str = "user", **kwargs: Any) -> dict[str, Any]:
    """``obj`` with a stamp (:func:`make_stamp`) under ``"stamp"`` (an existing one is replaced)."""
    if not isinstance(obj, dict):
        raise TypeError(f"only a dictionary can carry a stamp, got {type(obj).__name__}.")
    return {**obj, "stamp": make_stamp(path, **kwargs)}
