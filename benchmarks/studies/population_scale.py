r"""How long a population of many simulated people takes to fit, and how much memory (issues 31
and 47).

Each simulated person answers 20 questions (15 comparisons of random pairs and 5 Beta ratings)
about their items, from a utility ``m(x) + g_p(x)``: a shared smooth mean and a person's smaller
smooth deviation. The items are drawn either from a shared pool of ``--pool`` items (30 each:
issue 31's 1,000 people over 300 items) or, with ``--own-items n``, fresh for every person (issue
47's 10,000 people with their own 10 items each: 100,000 distinct items). The fit is
:func:`torchpref.fit_population` (``--max-iter`` L-BFGS iterations; the mean exact or at
``--inducing`` items). Records the wall and CPU seconds, the peak memory (this process's maximum
resident set, and the workers' for an executor) beside the fit's own estimate, the load average
and the CPU count, the bytes per Newton step, and how well the fitted mean ranks items against the
true mean (Spearman: the pool, or 2,000 fresh items for ``--own-items``).

Run (quietly: one thread, nice'd; the load average is recorded):
``OMP_NUM_THREADS=1 nice -n 10 python benchmarks/studies/population_scale.py`` (issue 31's) and
``... population_scale.py --people 10000 --own-items 10 --name own10k`` (issue 47's); writes
``benchmarks/results/population/population_scale[_NAME].json`` (stamped).
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import time
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

import torchpref
from torchpref.data.preference_data import PreferenceData

OUT = Path(__file__).resolve().parents[1] / "results" / "population"


def smooth(X: torch.Tensor, W: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """A random smooth function: a sum of cosines of random directions ``W`` (``k x d``), phases ``b``."""
    return (torch.cos(3.0 * X @ W.T + b) / math.sqrt(W.shape[0])).sum(-1)


def _answers(f: torch.Tensor, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """15 comparisons of random pairs and 5 Beta ratings of a person's items (utilities ``f``)."""
    n = f.shape[0]
    pairs = torch.randint(0, n, (15, 2), generator=g)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    noisy = f.unsqueeze(0) + torch.randn(len(pairs), n, generator=g, dtype=torch.float64)
    win = noisy.gather(1, pairs[:, :1]).squeeze(1) > noisy.gather(1, pairs[:, 1:]).squeeze(1)
    C = torch.where(win.unsqueeze(-1), pairs, pairs.flip(-1))
    rated = torch.randperm(n, generator=g)[:5]
    r = torch.special.ndtr(f[rated] + 0.2 * torch.randn(5, generator=g, dtype=torch.float64)).clamp(0.02, 0.98)
    return C, r, rated


def simulate(
    people: int, pool: int, d: int, seed: int, spread: float = 0.5, own_items: int = 0
) -> tuple[list[PreferenceData], Any, torch.Tensor]:
    """``people`` simulated people, the true mean (a function) and the items to rank with it."""
    g = torch.Generator().manual_seed(seed)
    P = torch.rand(pool, d, generator=g, dtype=torch.float64)
    Wm, bm = torch.randn(8, d, generator=g, dtype=torch.float64), 6.3 * torch.rand(8, generator=g, dtype=torch.float64)

    def mean(X: torch.Tensor) -> torch.Tensor:
        return 2.0 * smooth(X, Wm, bm)

    out = []
    for _ in tqdm(range(people), desc="simulate", mininterval=5):
        Wg, bg = (
            torch.randn(4, d, generator=g, dtype=torch.float64),
            6.3 * torch.rand(4, generator=g, dtype=torch.float64),
        )
        X = (
            torch.rand(own_items, d, generator=g, dtype=torch.float64)
            if own_items
            else P[torch.randperm(pool, generator=g)[:30]]
        )
        C, r, rated = _answers(mean(X) + spread * smooth(X, Wg, bg), g)
        out.append(PreferenceData.create(X, C, r, rated))
    ranked = torch.rand(2000, d, generator=g, dtype=torch.float64) if own_items else P
    return out, mean, ranked


def spearman(a: torch.Tensor, b: torch.Tensor) -> float:
    ra, rb = a.argsort().argsort().double(), b.argsort().argsort().double()
    return float(torch.corrcoef(torch.stack([ra, rb]))[0, 1])


def peak_rss_gb(client: Any = None) -> dict[str, float]:
    """This process's peak resident set (and each Dask worker's), in GB."""
    out = {"master": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6}
    if client is not None:

        def worker_peak() -> float:
            import resource as r

            return r.getrusage(r.RUSAGE_SELF).ru_maxrss / 1e6

        out.update({f"worker {i}": v for i, v in enumerate(client.run(worker_peak).values())})
    return {k: round(v, 3) for k, v in out.items()}


def _executor(kind: str, workers: int) -> tuple[Any, Any]:
    """``(executor, closer)`` for ``--executor`` (``None`` in process)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

    if kind == "threads":
        ex = ThreadPoolExecutor(workers)
        return ex, ex.shutdown
    if kind == "processes":  # forked children can deadlock in torch: spawn
        ex = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
        return ex, ex.shutdown
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None)
    client = Client(cluster)
    return client, lambda: (client.close(), cluster.close())


def fit(people: list[PreferenceData], args: argparse.Namespace) -> tuple[Any, dict]:
    """The fit, timed, with its peak memory."""
    inducing: Any = (
        None if args.inducing == "exact" else args.inducing if args.inducing == "auto" else int(args.inducing)
    )
    ex, close = (None, lambda: None) if args.executor == "none" else _executor(args.executor, args.workers)
    load0, t0, c0 = os.getloadavg(), time.time(), time.process_time()
    try:
        shards = None if args.executor == "none" else args.shards
        pop = torchpref.fit_population(
            people, max_iter=args.max_iter, progress=True, executor=ex, shards=shards, inducing=inducing
        )
        wall, cpu = time.time() - t0, time.process_time() - c0
        memory = peak_rss_gb(ex if args.executor == "dask" else None)
    finally:
        close()
    return pop, dict(
        fit_wall_seconds=round(wall, 1),
        fit_cpu_seconds=round(cpu, 1),  # this process only (not an executor's workers)
        peak_memory_gb=memory,
        load_average_start=[round(x, 2) for x in load0],
        load_average_end=[round(x, 2) for x in os.getloadavg()],
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--people", type=int, default=1000)
    ap.add_argument("--pool", type=int, default=300)
    ap.add_argument("--own-items", type=int, default=0, help="each person's own items (0: 30 from the pool)")
    ap.add_argument("--d", type=int, default=3)
    ap.add_argument("--max-iter", type=int, default=50)
    ap.add_argument("--inducing", default="auto", help="auto, exact, or the number of inducing items")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--name", default="", help="results file population_scale_NAME.json")
    ap.add_argument("--executor", choices=["none", "threads", "processes", "dask"], default="none")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--shards", type=int, default=4)
    args = ap.parse_args()
    torch.set_num_threads(1)
    people, mean, ranked = simulate(args.people, args.pool, args.d, args.seed, own_items=args.own_items)
    before = peak_rss_gb()["master"]  # the interpreter, torch and the people's data, before the fit
    pop, timing = fit(people, args)
    with torch.no_grad():
        fitted = pop.mean()(ranked)
    result = dict(
        config=vars(args),
        answers=sum(p.num_observations for p in people),
        distinct_items=pop.stats["items"],
        mean=pop.stats["mean"],
        inducing_items=pop.stats["inducing_items"],
        **timing,
        peak_memory_before_fit_gb=before,
        memory_estimate_gb=round(pop.stats["memory_estimate_bytes"] / 1e9, 3),
        spearman_mean_vs_truth=round(spearman(fitted, mean(ranked)), 4),
        ranked_items="the pool" if not args.own_items else f"{ranked.shape[0]} fresh items (held out)",
        spread_s2=round(pop.spread, 4),
        mean_outputscale=round(float(pop.k_m.outputscale.detach()), 4),
        stats={k: v for k, v in pop.stats.items() if k not in ("people", "items")},
        cpu_count=os.cpu_count(),
        threads=torch.get_num_threads(),
        note="2 cores; the load averages at the start and the end say what else ran (above about 1.5: other jobs)",
    )
    from torchpref.experiments.results import write_json

    name = args.name or ("" if args.executor == "none" else args.executor)
    write_json(
        Path(args.out) / f"population_scale{'_' + name if name else ''}.json",
        result,
        measured="harness: benchmarks/studies/population_scale.py",
    )
    print(result)
    return 0


if __name__ == "__main__":
    from torchpref.experiments.stamp import recording_subprocesses

    with recording_subprocesses():  # the stamp hashes the code of every process it starts too
        raise SystemExit(main())
