"""Execute every notebook under ``notebooks/`` (headless, with this interpreter's kernel)."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")
pytest.importorskip("ipywidgets")
pytest.importorskip("matplotlib")

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))
TIMEOUT = 600  # seconds per notebook cell: generous, as a loaded machine runs the lake scenario 50x slower


@pytest.fixture(scope="module")
def kernel_env(tmp_path_factory):
    """Make the ``python3`` kernelspec start *this* interpreter.

    The ``python3`` spec that ipykernel installs says ``python``, which jupyter_client replaces by
    ``sys.executable``; a spec found elsewhere (user or system dirs) may point at another Python.
    If it does not resolve to this interpreter, a spec in a temporary directory that does is put
    first on ``JUPYTER_PATH``.
    """
    from jupyter_client.kernelspec import KernelSpecManager, NoSuchKernel
    from jupyter_client.manager import KernelManager

    def resolved() -> str | None:
        try:
            KernelSpecManager().get_kernel_spec("python3")
            cmd = KernelManager(kernel_name="python3").format_kernel_cmd()
        except NoSuchKernel:
            return None
        return cmd[0]

    old = os.environ.get("JUPYTER_PATH")
    exe = resolved()
    if exe is None or os.path.realpath(exe) != os.path.realpath(sys.executable):
        root = tmp_path_factory.mktemp("jupyter")
        spec_dir = root / "kernels" / "python3"
        spec_dir.mkdir(parents=True)
        spec = {
            "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
            "display_name": "Python 3 (test)",
            "language": "python",
        }
        (spec_dir / "kernel.json").write_text(json.dumps(spec))
        os.environ["JUPYTER_PATH"] = os.pathsep.join([str(root)] + ([old] if old else []))
        exe = resolved()
    assert exe is not None and os.path.realpath(exe) == os.path.realpath(sys.executable), exe
    yield
    if old is None:
        os.environ.pop("JUPYTER_PATH", None)
    else:
        os.environ["JUPYTER_PATH"] = old


def test_notebooks_found():
    assert [p.name for p in NOTEBOOKS] == [
        "01_likelihoods_and_posterior.ipynb",
        "02_active_learning_wave.ipynb",
        "03_lake_world.ipynb",
        "04_botorch_loop.ipynb",
    ]


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_executes(path, kernel_env, tmp_path, monkeypatch):
    nb = nbformat.read(path, as_version=4)
    # committed without outputs
    assert all(not c.get("outputs") and c.get("execution_count") is None for c in nb.cells if c.cell_type == "code")
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    client = nbclient.NotebookClient(
        nb, timeout=TIMEOUT, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    )
    t0 = time.perf_counter()
    client.execute()
    elapsed = time.perf_counter() - t0
    assert elapsed < TIMEOUT, f"{path.name} took {elapsed:.0f} s"
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"]
    assert not errors
    images = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if "image/png" in o.get("data", {})]
    assert images, f"{path.name} shows no figure"
