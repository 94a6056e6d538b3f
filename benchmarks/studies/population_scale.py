r"""How long a population of many simulated people takes to fit (issue 31: 1,000 people x 20
answers in under 10 minutes on this 2-core machine).

Each simulated person answers 20 questions about items drawn from a shared pool of ``--pool``
items in ``d`` dimensions (15 comparisons of random pairs and 5 Beta ratings), from a utility
``m(x) + g_p(x)``: a shared smooth mean and a person's smaller smooth deviation. The fit is
:func:`torchpref.fit_population` (evidence of all answers, ``--max-iter`` L-BFGS iterations).
Records the wall and CPU seconds, the load average and the CPU count, and how well the fitted
population mean ranks the pool against the true mean (Spearman).

Run: ``OMP_NUM_THREADS=1 nice -n 10 python benchmarks/studies/population_scale.py``; writes
``benchmarks/results/population/population_scale.json`` (stamped).
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

import torch
from tqdm.auto import tqdm

import torchpref
from torchpref.data.preference_data import PreferenceData

OUT = Path(__file__).resolve().parents[1] / "results" / "population"


def smooth(X: torch.Tensor, W: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """A random smooth function: a sum of cosines of random directions ``W`` (``k x d``), phases ``b``."""
    return (torch.cos(3.0 * X @ W.T + b) / math.sqrt(W.shape[0])).sum(-1)


def simulate(
    people: int, pool: int, d: int, seed: int, spread: float = 0.5
) -> tuple[list[PreferenceData], torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    P = torch.rand(pool, d, generator=g, dtype=torch.float64)
    Wm, bm = torch.randn(8, d, generator=g, dtype=torch.float64), 6.3 * torch.rand(8, generator=g, dtype=torch.float64)
    mean = 2.0 * smooth(P, Wm, bm)
    out = []
    for _ in tqdm(range(people), desc="simulate", mininterval=5):
        Wg, bg = (
            torch.randn(4, d, generator=g, dtype=torch.float64),
            6.3 * torch.rand(4, generator=g, dtype=torch.float64),
        )
        rows = torch.randperm(pool, generator=g)[:30]
        X = P[rows]
        f = mean[rows] + spread * smooth(X, Wg, bg)
        pairs = torch.randint(0, 30, (15, 2), generator=g)
        pairs = pairs[pairs[:, 0] != pairs[:, 1]]
        noisy = f.unsqueeze(0) + torch.randn(len(pairs), 30, generator=g, dtype=torch.float64)
        win = noisy.gather(1, pairs[:, :1]).squeeze(1) > noisy.gather(1, pairs[:, 1:]).squeeze(1)
        C = torch.where(win.unsqueeze(-1), pairs, pairs.flip(-1))
        rated = torch.randperm(30, generator=g)[:5]
        r = torch.special.ndtr(f[rated] + 0.2 * torch.randn(5, generator=g, dtype=torch.float64)).clamp(0.02, 0.98)
        out.append(PreferenceData.create(X, C, r, rated))
    return out, P, mean


def spearman(a: torch.Tensor, b: torch.Tensor) -> float:
    ra, rb = a.argsort().argsort().double(), b.argsort().argsort().double()
    return float(torch.corrcoef(torch.stack([ra, rb]))[0, 1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--people", type=int, default=1000)
    ap.add_argument("--pool", type=int, default=300)
    ap.add_argument("--d", type=int, default=3)
    ap.add_argument("--max-iter", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument(
        "--executor",
        choices=["none", "threads", "processes"],
        default="none",
        help="fit over shards of people on a thread or process pool (none: in process)",
    )
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--shards", type=int, default=4)
    args = ap.parse_args()
    torch.set_num_threads(1)
    people, P, mean = simulate(args.people, args.pool, args.d, args.seed)
    load0, t0, c0 = os.getloadavg(), time.time(), time.process_time()
    if args.executor == "none":
        pop = torchpref.fit_population(people, max_iter=args.max_iter, progress=True)
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

        spawn = {"mp_context": multiprocessing.get_context("spawn")}  # forked children can deadlock in torch
        ex = (
            ThreadPoolExecutor(args.workers)
            if args.executor == "threads"
            else ProcessPoolExecutor(args.workers, **spawn)
        )
        with ex:
            pop = torchpref.fit_population(
                people, max_iter=args.max_iter, progress=True, executor=ex, shards=args.shards
            )
    wall, cpu = time.time() - t0, time.process_time() - c0
    load1 = os.getloadavg()
    with torch.no_grad():
        fitted = pop.mean()(P)
    result = dict(
        config=vars(args),
        answers=sum(p.num_observations for p in people),
        distinct_items=pop.stats["items"],
        fit_wall_seconds=round(wall, 1),
        fit_cpu_seconds=round(cpu, 1),  # this process only (not the pool's worker processes)
        spearman_mean_vs_truth=round(spearman(fitted, mean), 4),
        spread_s2=round(pop.spread, 4),
        mean_outputscale=round(float(pop.k_m.outputscale.detach()), 4),
        load_average_start=[round(x, 2) for x in load0],
        load_average_end=[round(x, 2) for x in load1],
        cpu_count=os.cpu_count(),
        threads=torch.get_num_threads(),
        note="2 cores; the load averages at the start and the end say what else ran (above about 1.5: other jobs)",
    )
    from torchpref.experiments.results import write_json

    out = Path(args.out)
    name = "population_scale.json" if args.executor == "none" else f"population_scale_{args.executor}.json"
    write_json(out / name, result, measured="harness: benchmarks/studies/population_scale.py")
    print(result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
