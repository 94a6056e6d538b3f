"""The compiled path's cache, setting and processes (issue 42): a damaged, foreign or unusable cache,
a stray ``numba.py`` in the working directory and a missing cache each leave the torch solver
answering with one warning that names the command, never a compilation in the caller nor a process;
any failure of a compiled call falls back once per process; the setting is per thread and checked
when read; compiled calls run BLAS on torch's thread count and restore the libraries' own.

The end-to-end cases run a short script (:data:`PROBE`: three fits and a mode) in a fresh process
against a copy of a built cache (:func:`built_cache`) damaged in one way each."""

import dataclasses
import json
import os
import shutil
import subprocess
import sys
import threading
import warnings
from pathlib import Path

import pytest
import torch

from torchpref.inference import fast_cache, fast_path

ROOT = Path(__file__).resolve().parents[2]
needs_numba = pytest.mark.skipif(not fast_path.available(), reason="numba is not installed (the fast extra)")
linux_only = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads processes from /proc")

#: three fits and a mode, then what happened, as JSON on the last line of stdout
PROBE = r"""
import json, os, sys, warnings
warnings.simplefilter("always")
import torch
from botorch.fit import fit_gpytorch_mll
from torchpref import PreferenceGP, LaplaceMarginalLogLikelihood
from torchpref.inference import fast_path
g = torch.Generator().manual_seed(0)
X = torch.rand(10, 2, dtype=torch.float64, generator=g)
C = torch.tensor([[0, 1], [2, 3], [4, 5], [6, 7], [8, 9], [1, 2], [3, 4], [5, 6], [7, 8], [9, 0]])
seen, values = [], []
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    for _ in range(3):
        m = PreferenceGP(X, C)
        fit_gpytorch_mll(LaplaceMarginalLogLikelihood(m))
        values.append(float(m.covar_module.outputscale.detach()))
    f = PreferenceGP(X, C).mode.f
seen = [str(w.message) for w in caught if "fast path" in str(w.message)]
compiles = 0
for name in ("torchpref.inference._compiled", "torchpref.inference._compiled_fit"):
    mod = sys.modules.get(name)
    for obj in vars(mod).values() if mod else ():
        stats = getattr(obj, "stats", None)
        compiles += sum(getattr(stats, "cache_misses", {}).values()) if stats is not None else 0
children = []
for entry in os.listdir("/proc"):
    if entry.isdigit():
        try:
            fields = open(f"/proc/{entry}/stat").read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == os.getpid():
            children.append(int(entry))
used = fast_path.STATE.functions is not None
print(json.dumps({"warnings": seen, "used": used, "compiles": compiles, "children": children,
                  "finite": all(v == v for v in values) and bool(torch.isfinite(f).all())}))
"""


def _env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", fast_path.ENV)}
    return {**env, "PYTHONPATH": str(ROOT), **extra}


def probe(cache_dir, cwd=None, code=PROBE, **extra) -> dict:
    """Run :data:`PROBE` in a fresh process with ``NUMBA_CACHE_DIR=cache_dir`` (and ``cwd``)."""
    env = _env(NUMBA_CACHE_DIR=str(cache_dir), **extra)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=cwd, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def _subfolder(root: Path) -> Path:
    """Where numba keeps the compiled modules' cache under ``NUMBA_CACHE_DIR=root``."""
    from numba.core.caching import UserProvidedCacheLocator

    import torchpref.inference as inference

    return root / UserProvidedCacheLocator.get_suitable_cache_subpath(
        str(Path(inference.__file__).parent / "_compiled.py")
    )


@pytest.fixture(scope="session")
def built_cache(tmp_path_factory) -> Path:
    """A ``NUMBA_CACHE_DIR`` holding a cache built for this installation (this process's own
    cache copied; built first if it has none: a minute)."""
    if not fast_path.loads():
        fast_path.build(progress=None)
    source = fast_path.cache_folder()
    root = tmp_path_factory.mktemp("numba-cache")
    target = _subfolder(root)
    target.mkdir(parents=True)
    for p in sorted(source.iterdir()):
        if p.name == fast_cache.MANIFEST or p.name.startswith(fast_cache.PREFIXES):
            shutil.copy2(p, target / p.name)
    return root


def _copy(built: Path, tmp_path: Path) -> tuple[Path, Path]:
    root = tmp_path / "cache"
    shutil.copytree(built, root)
    return root, _subfolder(root)


def _rewrite_manifest(folder: Path, **identity) -> None:
    path = folder / fast_cache.MANIFEST
    manifest = json.loads(path.read_text())
    manifest["identity"].update(identity)
    manifest["files"] = {p.name: fast_cache._sha256(p) for p in fast_cache._ours(folder)}
    path.write_text(json.dumps(manifest))


def _data(folder: Path, name: str = "newton") -> Path:
    return next(folder.glob(f"_compiled.{name}-*.nbc"))


def _index(folder: Path, name: str = "newton") -> Path:
    return next(folder.glob(f"_compiled.{name}-*.nbi"))


DAMAGE = {
    "index garbage": lambda f: _index(f).write_bytes(os.urandom(300)),
    "numba cannot read what the manifest vouches for": lambda f: (
        _index(f).write_bytes(b"\x80\x04garbage"),
        _rewrite_manifest(f),
    ),
    "index truncated": lambda f: _index(f).write_bytes(_index(f).read_bytes()[:40]),
    "index empty": lambda f: _index(f).write_bytes(b""),
    "data truncated": lambda f: _data(f).write_bytes(_data(f).read_bytes()[:100]),
    "data zeroed": lambda f: _data(f).write_bytes(bytes(len(_data(f).read_bytes()))),
    "data deleted": lambda f: (
        _data(f, "fit_lbfgs").unlink() if list(f.glob("_compiled.fit_lbfgs*")) else _data(f).unlink()
    ),
    "manifest not JSON": lambda f: (f / fast_cache.MANIFEST).write_text("{not json"),
}
#: in the default run: one kind numba itself fails on, one the manifest catches; the rest are slow
#: (each case is a fresh process of about 3-8 s)
SLOW_DAMAGE = {"index garbage", "index truncated", "index empty", "data zeroed", "data deleted", "manifest not JSON"}


def _answers_by_torch_once(result: dict, *words: str) -> None:
    """The fits and the mode came from the torch solver, finite, with exactly one warning (naming
    ``words``), and nothing compiled and no process started."""
    assert result["finite"] and not result["used"]
    assert len(result["warnings"]) == 1, result["warnings"]
    for word in words:
        assert word in result["warnings"][0], result["warnings"]
    assert result["compiles"] == 0 and result["children"] == []


@needs_numba
@linux_only
def test_the_built_cache_is_used_without_compiling_or_warning(built_cache):
    result = probe(built_cache)
    assert result["used"] and result["finite"] and result["warnings"] == []
    assert result["compiles"] == 0 and result["children"] == []


@needs_numba
@linux_only
@pytest.mark.parametrize("kind", [pytest.param(k, marks=pytest.mark.slow) if k in SLOW_DAMAGE else k for k in DAMAGE])
def test_a_damaged_cache_falls_back_with_one_warning(kind, built_cache, tmp_path):
    """Each kind of damage: the torch solver answers every fit, one warning names the command;
    nothing is compiled in the caller and no process is started (on the code before issue 42 a
    damaged cache broke every fit after the first with ``UnpicklingError``)."""
    root, folder = _copy(built_cache, tmp_path)
    DAMAGE[kind](folder)
    _answers_by_torch_once(probe(root), fast_cache.COMMAND)


@needs_numba
@linux_only
@pytest.mark.parametrize("field", [pytest.param("torchpref", marks=pytest.mark.slow), "sources"])
def test_another_installations_cache_is_not_used(field, built_cache, tmp_path):
    """A cache built for another version, or from other sources (an upgrade, another checkout):
    not loaded, not recompiled in the caller; one warning names what differs and the command."""
    root, folder = _copy(built_cache, tmp_path)
    _rewrite_manifest(folder, **{field: "0.0.0-another"})
    _answers_by_torch_once(probe(root), "another installation", field, fast_cache.COMMAND)


@needs_numba
@linux_only
def test_an_unusable_cache_folder_is_named_once_and_starts_nothing(tmp_path):
    """``NUMBA_CACHE_DIR`` naming a file: one warning naming it; no compile, no process (before
    issue 42 every process started a new background compiler)."""
    bad = tmp_path / "not-a-folder"
    bad.write_text("")
    _answers_by_torch_once(probe(bad), "NUMBA_CACHE_DIR", fast_cache.COMMAND)


@needs_numba
@linux_only
def test_no_cache_no_compile_no_process(tmp_path):
    """An empty cache folder (a fresh install that skipped the build): ``auto`` compiles nothing
    and starts nothing; one warning names the command."""
    _answers_by_torch_once(probe(tmp_path / "empty"), fast_cache.COMMAND)


@needs_numba
@linux_only
def test_a_numba_py_in_the_working_directory_is_never_run(built_cache, tmp_path):
    """A ``numba.py`` in the working directory of a script run as ``python -c`` (where the working
    directory is first on ``sys.path``): never imported by the fast path; one warning says why."""
    work = tmp_path / "work"
    work.mkdir()
    (work / "numba.py").write_text("open('numba-was-imported', 'w').write('yes')\n")
    result = probe(built_cache, cwd=work)
    assert not (work / "numba-was-imported").exists()
    _answers_by_torch_once(result, "working directory")


WRAPPER = r"""
import ctypes, os, subprocess, sys, time, json
ctypes.CDLL(None).prctl(36, 1, 0, 0, 0)  # PR_SET_CHILD_SUBREAPER: orphans of the script come here
subprocess.run([sys.executable, "-c", sys.argv[1]], stdout=subprocess.DEVNULL, check=True)
time.sleep(0.5)
left = []
for entry in os.listdir("/proc"):
    if entry.isdigit():
        try:
            fields = open(f"/proc/{entry}/stat").read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == os.getpid() and fields[0] != "Z":
            left.append(int(entry))
for pid in left:
    os.kill(pid, 9)
print(json.dumps(left))
"""


@needs_numba
@linux_only
def test_after_a_script_that_fits_ends_nothing_it_started_is_alive(tmp_path):
    """A script fitting three models with no cache ends; no process it started (at any depth) is
    alive then (before issue 42 each such script left a compiler of about 0.4 GB running)."""
    env = _env(NUMBA_CACHE_DIR=str(tmp_path / "empty"))
    out = subprocess.run(
        [sys.executable, "-c", WRAPPER, PROBE], capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []


@needs_numba
@linux_only
@pytest.mark.slow
def test_on_compiles_in_the_caller_with_a_progress_line(tmp_path):
    """``"on"`` without a cache: compiled in the calling process (a line on stderr says so and
    where), used by that process's fits, and kept for the next process, which compiles nothing."""
    env = _env(NUMBA_CACHE_DIR=str(tmp_path / "fresh"), TORCHPREF_FAST_PATH="on")
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=env, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    first = json.loads(out.stdout.strip().splitlines()[-1])
    assert "compiling the fast path in this process" in out.stderr
    assert first["used"] and first["finite"] and first["children"] == [] and first["compiles"] > 0
    second = probe(tmp_path / "fresh")
    assert second["used"] and second["compiles"] == 0 and second["warnings"] == []


# ----------------------------------------------------------------- in this process


@pytest.fixture
def own_state(monkeypatch):
    """This process's compiled-path state, restored after the test."""
    saved = dataclasses.replace(fast_path.STATE, warned=set(fast_path.STATE.warned))
    yield fast_path.STATE
    for f in dataclasses.fields(saved):
        setattr(fast_path.STATE, f.name, getattr(saved, f.name))


def _mode(setting: str = "on"):
    from torchpref import PreferenceGP

    X = torch.rand(12, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    C = torch.tensor([[0, 1], [2, 3], [4, 5], [6, 7], [8, 9], [10, 11], [1, 2], [3, 4]])
    with fast_path.fast_path(setting):
        return PreferenceGP(X, C).mode.f


@needs_numba
@pytest.mark.parametrize("failure", ["raises", "not finite"])
def test_a_failing_compiled_call_falls_back_once_per_process(failure, own_state):
    """A compiled call that raises anything but an arithmetic error, or returns non-finite values
    with an OK status: the torch solver answers, one warning, and the path stays off for the process."""
    functions = fast_path.warm_up() or fast_path.build(progress=None) and fast_path.STATE.functions
    real = functions["newton"]

    def broken(*args):
        if failure == "raises":
            raise SystemError("a damaged compiled function")
        a, M, w, it, status, dec = real(*args)
        return a * float("nan"), M, w, it, status, dec

    own_state.functions = {**functions, "newton": broken}
    reference = _mode("off")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        first, second = _mode(), _mode()
    assert torch.equal(first, reference) and torch.equal(second, reference)
    said = [w for w in caught if issubclass(w.category, fast_path.FastPathWarning)]
    assert len(said) == 1 and "torch solver answers" in str(said[0].message)
    assert own_state.functions is None and own_state.failed is not None
    assert fast_path.compiled() is None


def test_interleaved_blocks_in_two_threads_leave_each_its_own_setting(monkeypatch):
    """Two threads enter and leave ``fast_path`` blocks interleaved (A enters, B enters, A leaves,
    B leaves): inside, each sees its own setting; afterwards both, and the main thread, see the
    process's (before issue 42 the process stayed on whichever was entered last)."""
    monkeypatch.delenv(fast_path.ENV, raising=False)
    steps = [threading.Event() for _ in range(4)]
    seen: dict[str, list[str]] = {"A": [], "B": []}

    def thread(name: str, mode: str, enter_after: int, leave_after: int, done: int, entered: int):
        if enter_after >= 0:
            steps[enter_after].wait(5)
        with fast_path.fast_path(mode):
            steps[entered].set()
            steps[leave_after].wait(5)
            seen[name].append(fast_path.setting())
        seen[name].append(fast_path.setting())
        steps[done].set()

    a = threading.Thread(target=thread, args=("A", "off", -1, 1, 2, 0))
    b = threading.Thread(target=thread, args=("B", "on", 0, 2, 3, 1))
    a.start(), b.start()
    a.join(10), b.join(10)
    assert seen == {"A": ["off", "auto"], "B": ["on", "auto"]}
    assert fast_path.setting() == "auto"


def test_called_alone_the_setting_is_the_process_s(monkeypatch):
    """``set_fast_path(mode)`` sets the whole process's setting at once (other threads too); a
    block inside a thread still wins there; ``set_fast_path(None)`` goes back to the environment's;
    ``fast_path(mode)`` alone (not entered) changes nothing."""
    monkeypatch.delenv(fast_path.ENV, raising=False)
    monkeypatch.setattr(fast_path.STATE, "setting", None)
    fast_path.fast_path("on")  # a context manager: nothing until entered
    assert fast_path.setting() == "auto"
    fast_path.set_fast_path("off")
    seen = []
    worker = threading.Thread(target=lambda: seen.append(fast_path.setting()))
    worker.start(), worker.join(10)
    with fast_path.fast_path("on"):
        inner = fast_path.setting()
    assert seen == ["off"] and inner == "on" and fast_path.setting() == "off"
    fast_path.set_fast_path(None)
    assert fast_path.setting() == "auto"
    with pytest.raises(ValueError, match="'of'"):
        fast_path.set_fast_path("of")


def test_a_mistyped_environment_value_is_named_at_start(monkeypatch, capsys):
    """``TORCHPREF_FAST_PATH=fsat``: reading it raises a ValueError naming the variable, the value
    and the allowed ones; ``torchpref serve`` and ``elicit`` stop at start with that line (exit 2),
    before their module is imported."""
    from torchpref import cli

    monkeypatch.setenv(fast_path.ENV, "fsat")
    for read in (fast_path.check_setting, fast_path.setting):
        with pytest.raises(ValueError, match=r"TORCHPREF_FAST_PATH='fsat'.*auto, on, off"):
            read()
    monkeypatch.setattr(cli, "_import", lambda name: pytest.fail(f"{name} was imported"))
    for argv in (["serve", "lake"], ["elicit", "lake"]):
        assert cli.main(argv) == 2
        assert "TORCHPREF_FAST_PATH='fsat'" in capsys.readouterr().err


@needs_numba
def test_compiled_calls_run_blas_on_torch_s_threads_and_restore_them(own_state):
    """During a compiled call the BLAS libraries (numpy's and SciPy's OpenBLAS, numba's LAPACK) run
    on torch's thread count; after it, and after two threads' overlapping calls, they are back
    at the user's own count."""
    from threadpoolctl import ThreadpoolController, threadpool_limits

    functions = fast_path.warm_up() or (fast_path.build(progress=None) and fast_path.STATE.functions)
    real = functions["newton"]
    inside, gate = [], threading.Barrier(2, timeout=10)

    def watched(*args):
        inside.append(
            {lib["filepath"]: lib["num_threads"] for lib in ThreadpoolController().info() if lib["user_api"] == "blas"}
        )
        if threading.current_thread() is not threading.main_thread():
            gate.wait()
        return real(*args)

    own_state.functions = {**functions, "newton": watched}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with threadpool_limits(limits=3, user_api="blas"):
            _mode()
            workers = [threading.Thread(target=_mode) for _ in range(2)]
            [w.start() for w in workers], [w.join(20) for w in workers]
            after = {
                lib["filepath"]: lib["num_threads"]
                for lib in ThreadpoolController().info()
                if lib["user_api"] == "blas"
            }
    finally:
        torch.set_num_threads(threads)
    assert len(inside) == 3 and all(set(counts.values()) == {1} for counts in inside), inside
    assert set(after.values()) == {3}, after


@needs_numba
def test_build_does_nothing_when_the_cache_is_current(monkeypatch, capsys, own_state):
    """``torchpref fast-path build`` with this installation's cache in place says so and compiles
    nothing; ``--force`` rebuilds; a build says beforehand that it takes about 2 minutes."""
    from torchpref import cli

    assert fast_path.warm_up() is not None or fast_path.build(progress=None)
    built = []
    monkeypatch.setattr(fast_path, "build", lambda progress=None: built.append(1))
    assert cli.main(["fast-path", "build"]) == 0
    out = capsys.readouterr().out
    assert "is current for this installation: nothing to build" in out and built == []
    assert cli.main(["fast-path", "build", "--force"]) == 0
    assert built == [1] and "about 2 minutes" in capsys.readouterr().out


def test_every_function_a_fast_path_message_names_exists(monkeypatch, own_state):
    """The warning of a missing cache names the command and a function to build it: that function
    exists (it once named ``torchpref.fast_path.build()``, which does not)."""
    import importlib
    import re

    from torchpref.inference import fast_cache

    def unusable():
        raise fast_cache.CacheUnusable("no compiled cache has been built here")

    monkeypatch.setattr(fast_cache, "load", unusable)
    own_state.functions, own_state.failed, own_state.missing, own_state.warned = None, None, None, set()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fast_path._load("auto")
    (message,) = [str(w.message) for w in caught if issubclass(w.category, fast_path.FastPathWarning)]
    named = re.findall(r"(torchpref(?:\.\w+)+)\(\)", message)
    assert named and fast_cache.COMMAND in message
    for dotted in named:
        module, name = dotted.rsplit(".", 1)
        assert callable(getattr(importlib.import_module(module), name)), dotted
