r"""First-call cost of the compiled path (issues 33 and 42): the first fits of a fresh process.

Three fresh processes each build a 50-item comparisons model (``bench_common``) and time its first
three ``fit_gpytorch_mll``: with the compiled path off; with ``auto`` and the cache built for this
installation (the first fit imports numba and loads the compiled code: since issue 42 at the
first solve, not the second fit); with ``auto`` and no cache (an empty ``NUMBA_CACHE_DIR``: the
torch solver answers, one warning, nothing compiled and no process started). Also the build
itself: ``fast_path.build()`` into an empty cache folder.
Writes ``results/fast_path/first_call.json``.

Usage::

    .venv/bin/python benchmarks/speed/speed_first_call.py [--no-compile]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent

CHILD = r"""
import json, sys, time, warnings
t0 = time.perf_counter()
import torch
warnings.simplefilter("ignore")
torch.set_num_threads(1)
sys.path.insert(0, "benchmarks/speed")
import bench_common as bc
t_import = time.perf_counter() - t0
X, C = bc.make_comparisons(50, 100)
times = []
for _ in range(3):
    m = bc.mode_torchpref(X, C)
    t, c = time.perf_counter(), time.process_time()
    bc.fit_torchpref(m)
    times.append((time.perf_counter() - t, time.process_time() - c))
from torchpref.inference import fast_path as fp
print(json.dumps({"imports_s": t_import, "first_fit_wall_s": times[0][0], "first_fit_cpu_s": times[0][1],
                  "second_fit_wall_s": times[1][0], "second_fit_cpu_s": times[1][1], "third_fit_wall_s": times[2][0],
                  "compiled_loaded": fp.STATE.functions is not None, "numba_imported": "numba" in sys.modules}))
"""

COMPILE = r"""
import time
t, c = time.perf_counter(), time.process_time()
from torchpref.inference import fast_path
fast_path.build(progress=None)
import json
print(json.dumps({"compile_wall_s": time.perf_counter() - t, "compile_cpu_s": time.process_time() - c}))
"""


def run(code: str, **env: str) -> str:
    full = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", **env}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=full, cwd=ROOT, check=True)
    lines = out.stdout.strip().splitlines()
    return lines[-1] if lines else ""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--no-compile", action="store_true", help="skip timing the compile (1-2 minutes)")
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    from torchpref.experiments.results import write_json

    rows = {"off": json.loads(run(CHILD, TORCHPREF_FAST_PATH="off"))}
    run("from torchpref.inference import fast_path; fast_path.loads() or fast_path.build(None)")  # the cache exists
    rows["auto, cache on disk"] = json.loads(run(CHILD, TORCHPREF_FAST_PATH="auto"))
    with tempfile.TemporaryDirectory() as empty:
        rows["auto, no cache"] = json.loads(run(CHILD, TORCHPREF_FAST_PATH="auto", NUMBA_CACHE_DIR=empty))
    if not args.no_compile:
        with tempfile.TemporaryDirectory() as empty:
            rows["build (fast_path.build, empty cache)"] = json.loads(run(COMPILE, NUMBA_CACHE_DIR=empty))
    for k, v in rows.items():
        print(f"{k:32s} " + ", ".join(f"{a} {b:.3f}" if isinstance(b, float) else f"{a} {b}" for a, b in v.items()))
    write_json(
        ROOT / "benchmarks" / "results" / "fast_path" / "first_call.json",
        {"n": 50, "p": 100, "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "rows": rows},
        measured="user",
    )


if __name__ == "__main__":
    from torchpref.experiments.stamp import recording_subprocesses

    with recording_subprocesses():  # the stamp hashes the code of every process it starts too
        main()
