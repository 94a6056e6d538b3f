r"""When sharding a population over machines pays (issue 47): the same fit in process and on a
local Dask cluster of ``--workers`` worker processes, as the number of people grows.

Every person has their own 10 items and answers 20 questions (``population_scale.py
--own-items 10``); the mean is at ``--inducing`` items. For each number of people the fit runs
``--max-iter`` L-BFGS iterations in process (one thread) and on the cluster (one thread per
worker, two shards per worker; the cluster is started once, before the timings). Records the
wall seconds per evidence evaluation and per Newton step, and the bytes that cross per Newton step
(:class:`torchpref.population.hosts.Traffic`).

The cost model fitted to the measurements: an evaluation takes ``t_1(P) = a_1 + b P`` in process
and ``t_k(P) = a_k + b P / (e k)`` on ``k`` workers, ``e`` the parallel efficiency measured on this
cluster and ``a_k`` its overhead (the master's ``M^3``, a round's latency, the ``O(M^2)`` bytes);
``k`` machines are faster from ``P* = (a_k - a_1) / (b (1 - 1 / (e k)))`` people.

Run (quietly; the load average is recorded):
``OMP_NUM_THREADS=1 nice -n 10 python benchmarks/studies/population_shards.py``; writes
``benchmarks/results/population/population_shards.json`` (stamped), ``.csv`` and ``.png``.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time
from pathlib import Path
from typing import Any

import torch

import torchpref

sys.path.insert(0, str(Path(__file__).resolve().parent))
from population_scale import simulate

OUT = Path(__file__).resolve().parents[1] / "results" / "population"


def timed_fit(people: list, args: argparse.Namespace, executor: Any) -> dict:
    load0, t0 = os.getloadavg()[0], time.time()
    shards = None if executor is None else 2 * args.workers
    pop = torchpref.fit_population(
        people, max_iter=args.max_iter, inducing=args.inducing, executor=executor, shards=shards
    )
    wall, s = time.time() - t0, pop.stats
    return dict(
        wall_s=round(wall, 2),
        evaluations=s["evaluations"],
        newton_steps=s["newton_steps"],
        s_per_evaluation=round(wall / s["evaluations"], 3),
        s_per_newton_step=round(wall / s["newton_steps"], 4),
        bytes_per_newton_step=s["bytes_per_newton_step"],
        bytes_per_evaluation_besides=s["bytes_per_evaluation_besides"],
        shards=s["shards"],
        load_start_end=[round(load0, 2), round(os.getloadavg()[0], 2)],
    )


def line(P: list[float], t: list[float]) -> tuple[float, float]:
    """Least-squares ``t = a + b P``."""
    A = torch.tensor([[1.0, p] for p in P], dtype=torch.float64)
    a, b = torch.linalg.lstsq(A, torch.tensor(t, dtype=torch.float64).unsqueeze(-1)).solution.squeeze(-1).tolist()
    return a, b


def cost_model(rows: list[dict], workers: int) -> dict:
    """The model of the module docstring fitted to the rows, and ``P*`` for k machines."""
    here = [r for r in rows if r["host"] == "in process"]
    there = [r for r in rows if r["host"] != "in process"]
    a1, b = line([r["people"] for r in here], [r["s_per_evaluation"] for r in here])
    ak, bk = line([r["people"] for r in there], [r["s_per_evaluation"] for r in there])
    e = b / (workers * bk) if bk > 0 else float("nan")
    pays: dict[str, int | None] = {}
    for k in (2, 4, 8, 16):
        gain = b * (1 - 1 / (e * k))  # seconds saved per person; none if e k <= 1
        pays[str(k)] = max(0, round((ak - a1) / gain)) if gain > 0 else None
    return dict(a_1=a1, b=b, a_k=ak, b_k=bk, efficiency=e, pays_from_people=pays)


def plot(rows: list[dict], model: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for host in sorted({r["host"] for r in rows}):
        pts = [r for r in rows if r["host"] == host]
        ax.plot([r["people"] for r in pts], [r["s_per_evaluation"] for r in pts], marker="o", label=host)
    P = sorted({r["people"] for r in rows})
    ax.plot(P, [model["a_1"] + model["b"] * p for p in P], ls=":", color="grey", label="model, in process")
    ax.set_xlabel("people (10 own items, 20 answers each)")
    ax.set_ylabel("seconds per evidence evaluation")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--people", type=int, nargs="+", default=[1000, 5000, 20000])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--max-iter", type=int, default=3)
    ap.add_argument("--inducing", type=int, default=256)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args()
    torch.set_num_threads(1)
    from distributed import Client, LocalCluster

    rows = []
    with (
        LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        for P in args.people:
            people = simulate(P, 1, 3, args.seed, own_items=10)[0]
            for host, ex in (("in process", None), (f"Dask, {args.workers} workers", client)):
                row = dict(people=P, host=host, **timed_fit(people, args, ex))
                print(row, flush=True)
                rows.append(row)
    model = cost_model(rows, args.workers)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "population_shards.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=[k for k in rows[0] if k != "load_start_end"], extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    from torchpref.experiments.results import write_json

    result = dict(config=vars(args), rows=rows, model=model, cpu_count=os.cpu_count())
    write_json(out / "population_shards.json", result, measured="harness: benchmarks/studies/population_shards.py")
    plot(rows, model, out / "population_shards.png")
    print(model)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
