r"""The compiled path under load, and for a population's person models (issue 42).

Two measurements, one thread for torch (``--threads``, default 1), CPU time and wall time of every
call recorded, medians kept:

* ``load``: the compiled fit (``fit_gpytorch_mll`` of ``bench_common``'s comparisons model,
  ``TORCHPREF_FAST_PATH=on``) at each ``--sizes`` ``n``, quiet and under load side by side: each
  repeat times the fit with the machine as it is, then with ``--busy`` CPU-bound processes (default
  2: a busy loop each, started before and ended after that repeat's timings). Both with the
  compiled calls' BLAS limited to torch's threads (the library's behaviour) and, as
  ``unlimited``, with the libraries left at their own counts (the behaviour before issue 42), each
  variant in a fresh process of its own.
  Reported per ``n``: CPU and wall medians of each (condition, variant), the ratio of loaded to
  quiet CPU time and the ratio of CPU to wall time. Issue 42 asks, for the limited fit at n = 100
  and 200: loaded CPU within 1.5x of quiet, and CPU never above 1.2x wall.
* ``person``: a population's person model (``Population.person_model``: the population's prior
  mean and covariance, comparisons ``p = 2 n`` and ``n / 4`` Beta ratings) at each
  ``--person-sizes`` ``n``, compiled (``on``) against the torch solver (``off``), alternating
  within each repeat: ``fit`` is building the model and solving its posterior mode (what a session
  does after each answer: a person model's hyperparameters are the population's), ``solve`` the
  mode alone on a ready factor (:func:`torchpref.inference.laplace.find_mode`). Issue 42 asks for
  the fit at n = 20-200 at least 3x faster compiled.

Writes ``results/fast_path/speed_fast_path.{json,csv,png}`` (the JSON stamped, with the load
average at the start and end, and which threads were limited). Needs the compiled path built
(``torchpref fast-path build``). ``--quick``: n = 20 and 100, 3 repeats.

Usage::

    .venv/bin/python benchmarks/speed/speed_fast_path.py [--sizes 20 50 100 200] [--person-sizes 20 50 100 200]
        [--repeats 7] [--busy 2] [--threads 1] [--out benchmarks/results/fast_path]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import subprocess
import sys
import time
import warnings
from pathlib import Path

import torch
from tqdm import tqdm

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import bench_common as bc  # noqa: E402
from speed_pairwise import blas_threads  # noqa: E402

from torchpref.data.preference_data import PreferenceData  # noqa: E402
from torchpref.experiments.stamp import stamped  # noqa: E402
from torchpref.inference import fast_path as fp  # noqa: E402
from torchpref.inference.laplace import find_mode  # noqa: E402
from torchpref.models.defaults import default_covar_module  # noqa: E402
from torchpref.population.fit import fit_population  # noqa: E402

RESULTS = HERE.parent / "results" / "fast_path"
BUSY = "while True:\n    pass\n"


def timed(fn) -> dict[str, float]:
    c0, w0 = time.process_time(), time.perf_counter()
    fn()
    return {"cpu": time.process_time() - c0, "wall": time.perf_counter() - w0}


def medians(times: list[dict[str, float]]) -> dict[str, float]:
    return {k: statistics.median(t[k] for t in times) for k in ("cpu", "wall")}


class Busy:
    """``count`` CPU-bound processes (a busy loop each), running inside the ``with`` block; ended
    (by their ids) when it exits."""

    def __init__(self, count: int):
        self.count, self.procs = count, []

    def __enter__(self) -> Busy:
        self.procs = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(self.count)]
        time.sleep(0.5)  # scheduled and spinning before the timings
        return self

    def __exit__(self, *exc: object) -> None:
        for p in self.procs:
            p.kill()
        for p in self.procs:
            p.wait()


class Unlimited:
    """The compiled calls without their BLAS limit (the libraries at their own thread counts)."""

    def __enter__(self) -> None:
        self.saved = fp.BLAS_THREADS.run
        fp.BLAS_THREADS.run = lambda fn, *args: fn(*args)  # type: ignore[method-assign]

    def __exit__(self, *exc: object) -> None:
        fp.BLAS_THREADS.run = self.saved  # type: ignore[method-assign]


def fit_once(n: int) -> None:
    X, C = bc.make_comparisons(n, 2 * n)
    bc.fit_torchpref(bc.mode_torchpref(X, C))


def load_variant(variant: str, sizes: list[int], repeats: int, busy: int) -> dict:
    """In this process: one variant's fits (``limited`` or ``unlimited``), quiet and loaded
    alternating within each repeat: ``{n: {condition: [times]}}``."""
    out: dict = {}
    with Unlimited() if variant == "unlimited" else _null():
        for n in sizes:
            fit_once(n)  # warm-up: caches, first-call costs
            times: dict[str, list] = {"quiet": [], "loaded": []}
            for _ in range(repeats):
                for condition in ("quiet", "loaded"):
                    with Busy(busy) if condition == "loaded" else _null():
                        times[condition].append(timed(lambda: fit_once(n)))
            out[n] = times
    return out


def measure_load(sizes: list[int], repeats: int, busy: int, threads: int, bar) -> list[dict]:
    """Each variant in a fresh process of its own (OpenBLAS's pool threads, once woken by an
    unlimited call, spin for a while and would be counted in the next call's CPU time)."""
    found = {}
    for variant in ("limited", "unlimited"):
        cmd = [sys.executable, __file__, "--child-load", variant, "--threads", str(threads), "--busy", str(busy)]
        cmd += ["--repeats", str(repeats), "--sizes", *map(str, sizes)]
        out = subprocess.run(
            cmd, capture_output=True, text=True, check=True, env={**os.environ, "TORCHPREF_FAST_PATH": "on"}
        )
        found[variant] = json.loads(out.stdout.strip().splitlines()[-1])
        bar.update(len(sizes) * repeats * 2)
    rows = []
    for n in sizes:
        row: dict = {"task": "compiled fit", "n": n, "p": 2 * n}
        for variant, by_n in found.items():
            for condition, t in by_n[str(n)].items():
                m = medians(t)
                row[f"{condition}_{variant}_cpu_s"], row[f"{condition}_{variant}_wall_s"] = m["cpu"], m["wall"]
                row[f"{condition}_{variant}_cpu_over_wall_max"] = max(x["cpu"] / x["wall"] for x in t)
            row[f"{variant}_loaded_over_quiet_cpu"] = row[f"loaded_{variant}_cpu_s"] / row[f"quiet_{variant}_cpu_s"]
        rows.append(row)
    return rows


class _null:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: object) -> None:
        return None


def population(seed: int = 0):
    """A population of 30 people, 12 items each from a shared pool of 120 (8 comparisons and 3
    Beta ratings each), with fixed kernels (its prior mean and covariance are what is timed)."""
    g = torch.Generator().manual_seed(seed)
    pool = torch.rand(120, bc.DIM, generator=g, dtype=bc.DTYPE)
    people = []
    for _ in range(30):
        idx = torch.randperm(120, generator=g)[:12]
        people.append(person_data(pool[idx], 8, 3, g))
    k_m, k_g = default_covar_module(bc.DIM).double(), default_covar_module(bc.DIM).double()
    k_m.base_kernel.lengthscale, k_g.base_kernel.lengthscale, k_g.outputscale = 0.3, 0.5, 0.3
    return fit_population(people, k_m=k_m, k_g=k_g, fit=False)


def person_data(X: torch.Tensor, p: int, q: int, g: torch.Generator) -> PreferenceData:
    n = X.shape[0]
    u = bc.utility(X) + 0.3 * torch.randn(n, generator=g, dtype=bc.DTYPE)
    i = torch.randint(0, n, (p,), generator=g)
    j = (i + torch.randint(1, n, (p,), generator=g)) % n
    first = u[i] + torch.randn(p, generator=g, dtype=bc.DTYPE) > u[j]
    C = torch.stack([torch.where(first, i, j), torch.where(first, j, i)], -1)
    idx = torch.randperm(n, generator=g)[:q]
    r = torch.special.ndtr(u[idx] / 1.6).clamp(0.02, 0.98)
    return PreferenceData.create(X, C, r, idx)


def measure_person(pop, sizes: list[int], repeats: int, bar) -> list[dict]:
    rows = []
    for n in sizes:
        g = torch.Generator().manual_seed(n)
        data = person_data(torch.rand(n, bc.DIM, generator=g, dtype=bc.DTYPE), 2 * n, max(1, n // 4), g)

        def fit() -> None:
            _ = pop.person_model(data).mode

        model = pop.person_model(data)
        state = model._state()
        L, obs = state.pred.L, state.obs

        def solve() -> None:
            find_mode(L, obs)

        fns = {"fit": fit, "solve": solve}
        times: dict[tuple[str, str], list] = {}
        for setting in ("on", "off"):  # warm-up
            with fp.fast_path(setting):
                fit(), solve()
        for _ in range(repeats):
            for task, fn in fns.items():
                for setting in ("on", "off"):
                    with fp.fast_path(setting):
                        times.setdefault((task, setting), []).append(timed(fn))
                    bar.update(1)
        for task in fns:
            row: dict = {"task": f"person {task}", "n": n, "p": 2 * n, "ratings": max(1, n // 4)}
            for setting, name in (("on", "compiled"), ("off", "torch")):
                m = medians(times[(task, setting)])
                row[f"{name}_cpu_s"], row[f"{name}_wall_s"] = m["cpu"], m["wall"]
            row["speedup_cpu"] = row["torch_cpu_s"] / row["compiled_cpu_s"]
            row["speedup_wall"] = row["torch_wall_s"] / row["compiled_wall_s"]
            rows.append(row)
    return rows


def plot(load_rows: list[dict], person_rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.5))
    for variant, style in (("limited", "-"), ("unlimited", ":")):
        for condition, color in (("quiet", "C0"), ("loaded", "C3")):
            a.plot(
                [r["n"] for r in load_rows],
                [1e3 * r[f"{condition}_{variant}_cpu_s"] for r in load_rows],
                style,
                color=color,
                marker="o",
                label=f"{condition}, BLAS {variant}",
            )
    a.set(
        xlabel="items n",
        ylabel="CPU ms per fit (median)",
        yscale="log",
        title="compiled fit, quiet vs 2 busy processes",
    )
    a.legend(fontsize=8)
    for task, style in (("person fit", "-"), ("person solve", "--")):
        rows = [r for r in person_rows if r["task"] == task]
        for name, color in (("compiled", "C2"), ("torch", "C1")):
            label = f"{name}: {'build + mode' if task == 'person fit' else 'mode on a ready factor'}"
            b.plot(
                [r["n"] for r in rows],
                [1e3 * r[f"{name}_cpu_s"] for r in rows],
                style,
                marker="o",
                color=color,
                label=label,
            )
    b.set(xlabel="items n", ylabel="CPU ms (median)", yscale="log", title="a population's person model")
    b.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def arguments() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[20, 50, 100, 200])
    ap.add_argument("--person-sizes", type=int, nargs="+", default=[20, 50, 100, 200])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--busy", type=int, default=2, help="CPU-bound processes of the loaded condition")
    ap.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    ap.add_argument("--quick", action="store_true", help="n = 20 and 100, 3 repeats")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--child-load", choices=("limited", "unlimited"), help=argparse.SUPPRESS)
    return ap.parse_args()


def main() -> None:
    args = arguments()
    if args.quick:
        args.sizes, args.person_sizes, args.repeats = [20, 100], [20, 100], 3
    torch.set_num_threads(args.threads)
    warnings.simplefilter("ignore")
    fp.set_fast_path("on")
    if fp.warm_up() is None:
        sys.exit(f"the compiled path is not available: {fp.status()}")
    if args.child_load:
        print(json.dumps(load_variant(args.child_load, args.sizes, args.repeats, args.busy)))
        return
    load_start = os.getloadavg()
    pop = population()
    total = len(args.sizes) * args.repeats * 4 + len(args.person_sizes) * args.repeats * 4
    with tqdm(total=total, desc="speed_fast_path") as bar:
        load_rows = measure_load(args.sizes, args.repeats, args.busy, args.threads, bar)
        person_rows = measure_person(pop, args.person_sizes, args.repeats, bar)
    meta = {
        "torch_threads": torch.get_num_threads(),
        "blas": blas_threads(),
        "busy_processes": args.busy,
        "repeats": args.repeats,
        "statistic": "median",
        "cpus": os.cpu_count(),
        "load_average_at_start": load_start,
        "load_average_at_end": os.getloadavg(),
        "population": {"people": 30, "pool": 120, "items_each": 12, "N": int(pop.U.shape[0])},
    }
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "speed_fast_path.json", "w") as fh:
        json.dump(stamped({"meta": meta, "load": load_rows, "person": person_rows}), fh, indent=2)
    with open(args.out / "speed_fast_path.csv", "w", newline="") as fh:
        keys = list(dict.fromkeys(k for r in load_rows + person_rows for k in r))
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        for r in load_rows + person_rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    plot(load_rows, person_rows, args.out / "speed_fast_path.png")
    for r in load_rows:
        print(
            f"fit n={r['n']}: CPU quiet {1e3 * r['quiet_limited_cpu_s']:.1f} ms, loaded {1e3 * r['loaded_limited_cpu_s']:.1f} ms "
            f"({r['limited_loaded_over_quiet_cpu']:.2f}x; unlimited {r['unlimited_loaded_over_quiet_cpu']:.2f}x), "
            f"CPU/wall max {max(r['quiet_limited_cpu_over_wall_max'], r['loaded_limited_cpu_over_wall_max']):.2f}"
        )
    for r in person_rows:
        print(
            f"{r['task']} n={r['n']}: compiled {1e3 * r['compiled_cpu_s']:.2f} ms, torch {1e3 * r['torch_cpu_s']:.2f} ms CPU ({r['speedup_cpu']:.1f}x)"
        )
    print(f"wrote {args.out / 'speed_fast_path'}.json, .csv, .png; load {load_start} -> {os.getloadavg()}")


if __name__ == "__main__":
    from torchpref.experiments.stamp import recording_subprocesses

    with recording_subprocesses():  # the stamp hashes the code of every process it starts too
        main()
