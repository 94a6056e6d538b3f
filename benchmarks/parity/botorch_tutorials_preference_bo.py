"""BoTorch's ``preference_bo`` tutorial (EUBO against random pairs), rewritten as a script and run
with PairwiseGP and PreferenceGP in the same run; only the model and MLL lines differ
(``botorch_tutorials_common.fit_preference_model``).

The tutorial: a latent utility ``sum_i sqrt(i) x_i`` on ``[0, 1]^4``; one noisy comparison
(``sigma = 0.1`` on each utility) of two random points to start; then 30 rounds, each proposing a
pair (EUBO: ``optimize_acqf`` with 3 restarts and 512 raw samples; random: two uniform points),
comparing it once, refitting the model from scratch and recording the best utility seen.

Per seed and model we record the best-value curve of both arms, how often EUBO proposes a pair
it has already had compared, and the whole loop's wall time. Results:
``benchmarks/results/botorch_tutorials_preference_bo.{jsonl,json,csv,png}``.

Usage: ``nice -n 10 python benchmarks/parity/botorch_tutorials_preference_bo.py [--seeds 10] [--batches 30]``
"""

from __future__ import annotations

import argparse
import csv
import json
from itertools import combinations

import matplotlib

matplotlib.use("Agg")
import numpy as np
import torch
from botorch.acquisition.preference import AnalyticExpectedUtilityOfBestOption
from botorch.optim import optimize_acqf
from botorch_tutorials_common import (
    MODELS,
    RESULTS,
    Record,
    fit_preference_model,
    paired_summary,
    phase,
    phase_summary,
    plot_curves,
    seed_all,
    timed,
)
from tqdm import tqdm

from torchpref.experiments.results import write_json

DIM, NOISE, Q, Q_COMP = 4, 0.1, 2, 1
NUM_RESTARTS, RAW_SAMPLES = 3, 512


def utility(X: torch.Tensor) -> torch.Tensor:
    """The tutorial's latent utility: ``sum_i sqrt(i) x_i`` (maximum ``sum sqrt(i)`` at ``1``)."""
    return (X * torch.arange(1, X.shape[-1] + 1, dtype=X.dtype).sqrt()).sum(-1)


def random_points(n: int) -> torch.Tensor:
    return torch.rand(n, DIM, dtype=torch.float64)


def compare(y: torch.Tensor, n_comp: int) -> torch.Tensor:
    """``n_comp`` distinct pairs among the items, each ordered by its noisy utilities."""
    pairs = np.array(list(combinations(range(y.shape[0]), 2)))
    pairs = pairs[np.random.choice(len(pairs), n_comp, replace=False)]
    noisy = y[pairs].numpy() + NOISE * np.random.standard_normal(pairs.shape)
    flip = noisy[:, 0] < noisy[:, 1]
    pairs[flip] = pairs[flip][:, ::-1]
    return torch.as_tensor(pairs.copy()).long()


def repeats_a_pair(next_X: torch.Tensor, X: torch.Tensor, comps: torch.Tensor, atol: float = 1e-6) -> bool:
    """Whether the proposed pair is (up to order and ``atol``) one that was already compared."""
    same = (next_X.unsqueeze(1) - X.unsqueeze(0)).abs().amax(-1) <= atol  # 2 x n
    a, b = same[0][comps], same[1][comps]  # p x 2
    return bool(((a[:, 0] & b[:, 1]) | (a[:, 1] & b[:, 0])).any())


def run(model_name: str, seed: int, batches: int, model_kwargs: dict) -> dict:
    """One trial of the tutorial (both arms) for one model."""
    seed_all(seed)
    X0 = random_points(Q)
    C0 = compare(utility(X0), Q_COMP)
    bounds = torch.stack([torch.zeros(DIM), torch.ones(DIM)])
    out = {}
    for arm in ("EUBO", "rand"):
        seed_all(1000 * seed + 1 + (arm == "rand"))  # the same answers for both models until proposals differ
        X, comps = X0, C0
        model = fit_preference_model(model_name, X, comps, **model_kwargs)
        best, repeats = [utility(X).max().item()], 0
        for _ in range(batches):
            if arm == "EUBO":
                acqf = AnalyticExpectedUtilityOfBestOption(pref_model=model)
                with phase("eubo_optimize"):
                    next_X, _ = optimize_acqf(
                        acqf, bounds=bounds, q=Q, num_restarts=NUM_RESTARTS, raw_samples=RAW_SAMPLES
                    )
                next_X = next_X.to(X)
                repeats += repeats_a_pair(next_X, X, comps)
            else:
                next_X = random_points(Q)
            comps = torch.cat([comps, compare(utility(next_X), Q_COMP) + X.shape[0]])
            X = torch.cat([X, next_X])
            model = fit_preference_model(model_name, X, comps, **model_kwargs)
            best.append(utility(X).max().item())
        out[arm] = {"best": best, "repeats": repeats}
    optimum = utility(torch.ones(1, DIM, dtype=torch.float64)).item()
    return {
        "EUBO_best": out["EUBO"]["best"],
        "rand_best": out["rand"]["best"],
        "EUBO_regret": optimum - out["EUBO"]["best"][-1],
        "rand_regret": optimum - out["rand"]["best"][-1],
        "EUBO_auc_regret": float(np.mean([optimum - b for b in out["EUBO"]["best"]])),
        "EUBO_repeats": out["EUBO"]["repeats"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--batches", type=int, default=30)
    parser.add_argument(
        "--comparison-noise",
        type=float,
        default=None,
        help="PreferenceGP's comparison_noise (default: the library default)",
    )
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    parser.add_argument("--tag", default="", help="suffix of the result files")
    args = parser.parse_args()
    model_kwargs = {} if args.comparison_noise is None else {"comparison_noise": args.comparison_noise}
    torch.set_num_threads(1)
    stem = RESULTS / f"botorch_tutorials_preference_bo{args.tag}"
    record = Record(stem.with_suffix(".jsonl"), {"batches": args.batches, **model_kwargs})
    todo = [(s, m) for s in range(args.seeds) for m in args.models if not record.done(s, m)]
    for seed, name in tqdm(todo, desc="preference_bo"):
        record.add({"seed": seed, "model": name, **timed(lambda: run(name, seed, args.batches, model_kwargs))})
    rows = record.rows
    summary = {
        "regret": paired_summary(rows, "EUBO_regret", higher_is_better=False),
        "auc_regret": paired_summary(rows, "EUBO_auc_regret", higher_is_better=False),
        "repeats": {m: int(sum(r["EUBO_repeats"] for r in rows if r["model"] == m)) for m in MODELS},
        "proposals": {m: args.batches * sum(r["model"] == m for r in rows) for m in MODELS},
        "phases": phase_summary(rows),
        "config": record.config,
    }
    write_json(stem.with_suffix(".json"), summary, measured="harness: the tutorial rewritten as a script")
    with stem.with_suffix(".csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(
            ["seed", "model", "EUBO_regret", "rand_regret", "EUBO_auc_regret", "EUBO_repeats", "wall_s", "cpu_s"]
        )
        for r in sorted(rows, key=lambda r: (r["seed"], r["model"])):
            w.writerow(
                [
                    r["seed"],
                    r["model"],
                    r["EUBO_regret"],
                    r["rand_regret"],
                    r["EUBO_auc_regret"],
                    r["EUBO_repeats"],
                    r["wall_s"],
                    r.get("cpu_s"),
                ]
            )
    plot_curves(
        rows,
        ("EUBO", "rand"),
        "{}_best",
        np.arange,
        stem.with_suffix(".png"),
        xlabel="query (q = 2, one comparison each)",
        ylabel="best utility seen",
        title="preference_bo tutorial",
        optimum=utility(torch.ones(1, DIM, dtype=torch.float64)).item(),
    )
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
