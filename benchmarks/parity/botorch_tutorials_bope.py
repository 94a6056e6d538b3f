"""BoTorch's ``bope`` tutorial (Bayesian optimisation with preference exploration), rewritten as a
script and run with PairwiseGP and PreferenceGP in the same run; only the preference model and
MLL lines differ (``botorch_tutorials_common.fit_preference_model``).

The tutorial: DTLZ2 with 5 inputs and 4 outcomes, a decision maker whose utility is minus the L1
distance of the outcomes from ``(0.5, ..., 0.5)``. An outcome GP is fitted to 8 Sobol points; the
preference model starts from one comparison of two sampled outcomes. Each preference-exploration
strategy (EUBO-zeta: analytic EUBO through one outcome-model sample; Random-f: two random
designs) asks 5 x 3 comparisons, checking after every 3 the utility of the design that maximises
the posterior mean of the learned objective (``qSimpleRegret``); at the end ``qLogNEI`` through
the learned objective proposes one experiment, whose true utility is the tutorial's result.

Results: ``benchmarks/results/botorch_tutorials_bope.{jsonl,json,csv,png}``.

Usage: ``nice -n 10 python benchmarks/parity/botorch_tutorials_bope.py [--seeds 10]``
"""

from __future__ import annotations

import argparse
import csv
import json

import matplotlib

matplotlib.use("Agg")
import numpy as np
import torch
from botorch.acquisition import LearnedObjective
from botorch.acquisition.logei import qLogNoisyExpectedImprovement
from botorch.acquisition.monte_carlo import qSimpleRegret
from botorch.acquisition.preference import AnalyticExpectedUtilityOfBestOption
from botorch.fit import fit_gpytorch_mll
from botorch.models.deterministic import FixedSingleSampleModel
from botorch.models.gp_regression import SingleTaskGP
from botorch.models.transforms.input import Normalize
from botorch.optim.optimize import optimize_acqf
from botorch.sampling import SobolQMCNormalSampler
from botorch.test_functions.multi_objective import DTLZ2
from botorch.utils.sampling import draw_sobol_samples
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
from gpytorch.mlls import ExactMarginalLogLikelihood
from tqdm import tqdm

from torchpref.experiments.results import write_json

X_DIM, Y_DIM = 5, 4
NUM_RESTARTS, NUM_OUTCOME_SAMPLES, RAW_SAMPLES, BATCH_LIMIT = 8, 32, 64, 4
EVERY_N_COMPS, N_CHECKS, N_INIT = 3, 5, 8
STRATEGIES = ("EUBO-zeta", "Random-f")
PROBLEM = DTLZ2(dim=X_DIM, num_objectives=Y_DIM)


def utility(Y: torch.Tensor) -> torch.Tensor:
    """The decision maker's utility: minus the L1 distance of the outcomes from ``0.5``."""
    return -(Y - 0.5).abs().sum(-1)


def sobol_designs(n: int) -> torch.Tensor:
    return draw_sobol_samples(bounds=PROBLEM.bounds, n=1, q=n).squeeze(0)


def pair_comparisons(util: torch.Tensor) -> torch.Tensor:
    """Items ``2k, 2k + 1`` compared, the one of larger utility first."""
    comps = torch.arange(util.numel()).reshape(-1, 2)
    flip = util.reshape(-1, 2)[:, 0] < util.reshape(-1, 2)[:, 1]
    comps[flip] = comps[flip].flip(-1)
    return comps


def outcome_model_for(X: torch.Tensor, Y: torch.Tensor) -> SingleTaskGP:
    with phase("outcome_fit"):
        model = SingleTaskGP(X, Y, input_transform=Normalize(d=X.shape[-1]))
        fit_gpytorch_mll(ExactMarginalLogLikelihood(model.likelihood, model))
    return model


def candidates(outcome, objective, acqf_name: str, X_baseline: torch.Tensor) -> torch.Tensor:
    """One design from ``qLogNEI`` or ``qSimpleRegret`` through ``objective``."""
    sampler = SobolQMCNormalSampler(sample_shape=torch.Size([NUM_OUTCOME_SAMPLES]))
    if acqf_name == "qNEI":
        acqf = qLogNoisyExpectedImprovement(
            outcome, objective=objective, X_baseline=X_baseline, sampler=sampler, prune_baseline=True
        )
    else:
        acqf = qSimpleRegret(outcome, sampler=sampler, objective=objective)
    with phase("learned_objective_acqf"):
        cand, _ = optimize_acqf(
            acqf,
            q=1,
            bounds=PROBLEM.bounds,
            num_restarts=NUM_RESTARTS,
            raw_samples=RAW_SAMPLES,
            options={"batch_limit": BATCH_LIMIT},
            sequential=True,
        )
    return cand


def explore(model_name, outcome, Y, comps, strategy: str, X_baseline) -> tuple[torch.Tensor, torch.Tensor, list]:
    """Preference exploration: ``N_CHECKS`` rounds of ``EVERY_N_COMPS`` comparisons, recording
    after each round the true utility of the design maximising the learned objective's mean."""

    def check():
        pref = fit_preference_model(model_name, Y, comps)
        cand = candidates(outcome, LearnedObjective(pref_model=pref), "posterior_mean", X_baseline)
        return utility(PROBLEM(cand)).item()

    checks = [check()]
    for _ in range(N_CHECKS):
        for _ in range(EVERY_N_COMPS):
            pref = fit_preference_model(model_name, Y, comps)
            if strategy == "EUBO-zeta":
                one_sample = FixedSingleSampleModel(model=outcome)
                acqf = AnalyticExpectedUtilityOfBestOption(pref_model=pref, outcome_model=one_sample)
                with phase("eubo_optimize"):
                    cand_X, _ = optimize_acqf(
                        acqf,
                        q=2,
                        bounds=PROBLEM.bounds,
                        num_restarts=NUM_RESTARTS,
                        raw_samples=RAW_SAMPLES,
                        options={"batch_limit": BATCH_LIMIT},
                    )
                cand_Y = one_sample(cand_X)
            else:
                cand_Y = outcome.posterior(sobol_designs(2)).sample().squeeze(0)
            cand_Y = cand_Y.detach().clone()
            comps = torch.cat([comps, pair_comparisons(utility(cand_Y)) + Y.shape[0]])
            Y = torch.cat([Y, cand_Y])
        checks.append(check())
    return Y, comps, checks


def run(model_name: str, seed: int, strategies) -> dict:
    """The tutorial's closed loop for one seed and one preference model."""
    seed_all(seed)
    X = sobol_designs(N_INIT)
    outcome = outcome_model_for(X, PROBLEM(X))
    Y0 = outcome.posterior(sobol_designs(2)).sample().squeeze(0)
    C0 = pair_comparisons(utility(Y0))
    out = {}
    for k, strategy in enumerate(strategies):
        seed_all(1000 * seed + 1 + k)
        Y, comps, checks = explore(model_name, outcome, Y0.clone(), C0.clone(), strategy, X)
        pref = fit_preference_model(model_name, Y, comps)
        cand = candidates(outcome, LearnedObjective(pref_model=pref), "qNEI", X)
        out[f"{strategy}_checks"] = checks
        out[f"{strategy}_util"] = utility(PROBLEM(cand)).item()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    parser.add_argument("--strategies", nargs="+", default=list(STRATEGIES), choices=STRATEGIES)
    args = parser.parse_args()
    torch.set_num_threads(1)
    stem = RESULTS / "botorch_tutorials_bope"
    record = Record(stem.with_suffix(".jsonl"), {"strategies": args.strategies})
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    todo = [(s, m) for s in seeds for m in args.models if not record.done(s, m)]
    for seed, name in tqdm(todo, desc="bope"):
        record.add({"seed": seed, "model": name, **timed(lambda: run(name, seed, args.strategies))})
    rows = record.rows
    summary = {f"{s}_util": paired_summary(rows, f"{s}_util", higher_is_better=True) for s in args.strategies}
    summary.update(
        {
            f"{s}_last_check": paired_summary(
                [{**r, "last": r[f"{s}_checks"][-1]} for r in rows], "last", higher_is_better=True
            )
            for s in args.strategies
        }
    )
    summary["phases"] = phase_summary(rows)
    summary["config"] = record.config
    write_json(stem.with_suffix(".json"), summary, measured="harness: the tutorial rewritten as a script")
    with stem.with_suffix(".csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(
            [
                "seed",
                "model",
                *[f"{s}_util" for s in args.strategies],
                *[f"{s}_last_check" for s in args.strategies],
                "wall_s",
                "cpu_s",
            ]
        )
        for r in sorted(rows, key=lambda r: (r["seed"], r["model"])):
            w.writerow(
                [
                    r["seed"],
                    r["model"],
                    *[r[f"{s}_util"] for s in args.strategies],
                    *[r[f"{s}_checks"][-1] for s in args.strategies],
                    r["wall_s"],
                    r.get("cpu_s"),
                ]
            )
    plot_curves(
        rows,
        args.strategies,
        "{}_checks",
        lambda n: EVERY_N_COMPS * np.arange(n) + 1,
        stem.with_suffix(".png"),
        xlabel="comparisons",
        ylabel="true utility of the max-posterior-mean design",
        title="bope tutorial",
    )
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
