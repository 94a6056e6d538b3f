r"""Does the model recover a person's rating offset, gain and lapse rate, and does fitting them
cost anything on the paper's ideal raters? (issue 24)

Each trial is one simulated person: a random 2-D utility (three Gaussian bumps, rescaled: median
item 0, best about 2, as the suite's), a pool of 40 items, and a session of random questions:
``ratings`` ratings of pool items and ``choices`` best-of-4 choices, answered by a
:class:`~torchpref.simulation.raters.RealisticUser`. Two studies, paired within each:

* **recovery**: people with offset ``b ~ U(-0.6, 0.6)``, gain ``log g ~ U(log 0.6, log 1.67)``,
  lapse rate ``eps ~ U(0, 0.3)``, rating noise ``nu ~ U(15, 80)`` (wider than the published
  ranges, so that recovery is tested across them), no drift, the whole scale. The model: the
  family's fixed kernel (lengthscale 0.15, outputscale 1), the true ``sigma_R`` and ``sigma_B``,
  then :func:`~torchpref.models.calibration.calibrate_person` and
  :func:`~torchpref.models.calibration.fit_person` (``b``, ``g``, ``nu``, ``eps``, default priors).
  Reported: each parameter's error (RMSE, mean, correlation with the truth) against the prior's
  error (always guessing ``b = 0``, ``g = 1``, ``eps = 0.1``); and the WRMS (eq. 14, on the
  reference scale) of the calibrated model against the uncalibrated one on the same answers.
* **ideal**: the paper's rater (``g = 1``, ``b = 0``, no lapses, ``nu = 40``, the model's own
  noise): does calibrating them make the model worse? WRMS, top-10 true positives and regret,
  calibrated against uncalibrated, paired Wilcoxon test.

Run ``nice -n 10 python benchmarks/studies/person_calibration.py [--trials 40] [--workers 2]``; writes
``benchmarks/results/person_calibration.json``.
"""

from __future__ import annotations

import argparse
import math
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import torch
from scipy import stats

from torchpref.data.preference_data import best_of_m
from torchpref.experiments.families import _rescaled, _unit
from torchpref.experiments.results import write_json
from torchpref.experiments.runner import make_model
from torchpref.inference.laplace import LaplaceConvergenceWarning
from torchpref.likelihoods.pairwise_beta import predictive_rating
from torchpref.models.calibration import calibrate_person, fit_person
from torchpref.simulation.metrics import true_positives, wrms
from torchpref.simulation.raters import RaterProfile, RealisticUser
from torchpref.simulation.utility_functions import GaussianBumps

POOL, M, SIGMA_R, SIGMA_B, LENGTHSCALE = 40, 4, 0.1, 0.8, 0.15


def _person(seed: int, ideal: bool) -> tuple[RealisticUser, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    c = 0.1 + 0.8 * torch.rand(3, 2, generator=g, dtype=torch.float64)
    utility = _rescaled(GaussianBumps(c, [1.0, 0.6, 0.5], [0.15, 0.2, 0.2]), _unit(2), 2, g)
    X = torch.rand(POOL, 2, generator=g, dtype=torch.float64)
    u = torch.rand(4, generator=g, dtype=torch.float64).tolist()
    if ideal:
        profile = RaterProfile(comparison_noise=SIGMA_R, rating_precision=40.0, rating_scale=SIGMA_B)
    else:
        profile = RaterProfile(
            comparison_noise=SIGMA_R,
            rating_offset=-0.6 + 1.2 * u[0],
            rating_gain=math.exp(math.log(0.6) + (math.log(1 / 0.6) - math.log(0.6)) * u[1]),
            lapse_rate=0.3 * u[2],
            rating_precision=15.0 + 65.0 * u[3],
            rating_scale=SIGMA_B,
        )
    return RealisticUser(utility, profile, torch.Generator().manual_seed(seed + 1)), X


def _answers(user: RealisticUser, X: torch.Tensor, ratings: int, choices: int, seed: int):
    g = torch.Generator().manual_seed(seed + 2)
    idx = torch.randint(0, POOL, (ratings,), generator=g)
    r = torch.tensor([user.rate(X[i]) for i in idx.tolist()], dtype=torch.float64)
    comps = []
    for _ in range(choices):
        shown = torch.randperm(POOL, generator=g)[:M]
        comps.append(best_of_m(int(shown[user.choose(X[shown])]), shown))
    return torch.cat(comps), r, idx


def _scores(model, X, f_true, u_true):
    with torch.no_grad():
        post = model.posterior(X)
        mean, var = post.mean.squeeze(-1), post.variance.squeeze(-1)
        unbiased = getattr(model.likelihood.rating, "unbiased_rating", None)  # the person's offset removed
        est = predictive_rating(mean, var, SIGMA_B) if unbiased is None else unbiased(mean, var)
        best = f_true.max()
        regret = float((best - f_true[mean.argmax()]) / (best - f_true.median()))
    return {"wrms": float(wrms(est, u_true)), "tp": float(true_positives(est, u_true, k=10)), "regret": regret}


def trial(seed: int, ideal: bool, ratings: int, choices: int, learn_gain: bool = True) -> dict:
    torch.set_num_threads(1)
    warnings.simplefilter("ignore", LaplaceConvergenceWarning)  # counted below, not lost
    user, X = _person(seed, ideal)
    comps, r, idx = _answers(user, X, ratings, choices, seed)
    settings = {
        "lengthscale": LENGTHSCALE,
        "outputscale": 1.0,
        "comparison_noise": SIGMA_R,
        "rating_scale": SIGMA_B,
        "rating_precision": 40.0,
    }
    f_true = user.latent(X)
    u_true = user.mean_rating(X)
    plain = make_model(X, comps, settings)
    plain.add_observations(ratings=r, rating_index=idx)
    out = {"seed": seed, "truth": user.profile.as_dict(), "plain": _scores(plain, X, f_true, u_true)}
    model = make_model(X, comps, settings)
    model.add_observations(ratings=r, rating_index=idx)
    t0 = time.process_time()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", LaplaceConvergenceWarning)
        calibrate_person(model)
        model.likelihood.rating.raw_rating_gain.requires_grad_(learn_gain)
        fit_person(model)
    out["fit_cpu_s"] = time.process_time() - t0
    out["convergence_warnings"] = sum(issubclass(w.category, LaplaceConvergenceWarning) for w in caught)
    lik = model.likelihood
    out["fitted"] = {
        "rating_offset": float(lik.rating.rating_offset.detach()),
        "rating_gain": float(lik.rating.rating_gain.detach()),
        "rating_precision": float(lik.rating.rating_precision.detach()),
        "lapse_rate": float(lik.comparison.lapse_rate.detach()),
    }
    out["calibrated"] = _scores(model, X, f_true, u_true)
    return out


def _errors(rows: list[dict], name: str, prior: float, log: bool = False) -> dict:
    t = torch.tensor([r["truth"][name] for r in rows], dtype=torch.float64)
    e = torch.tensor([r["fitted"][name] for r in rows], dtype=torch.float64)
    if log:
        t, e, prior = t.log(), e.log(), math.log(prior)
    return {
        "rmse": float((e - t).square().mean().sqrt()),
        "bias": float((e - t).mean()),
        "prior_rmse": float((prior - t).square().mean().sqrt()),
        "correlation": float(torch.corrcoef(torch.stack([e, t]))[0, 1]),
        "scale": "log" if log else "linear",
    }


def _paired(rows: list[dict], metric: str) -> dict:
    a = [r["calibrated"][metric] for r in rows]
    b = [r["plain"][metric] for r in rows]
    diff = [x - y for x, y in zip(a, b)]
    p = float(stats.wilcoxon(a, b).pvalue) if any(d != 0 for d in diff) else 1.0
    n = len(a)
    return {
        "calibrated": sum(a) / n,
        "plain": sum(b) / n,
        "mean_diff": sum(diff) / n,
        "se_diff": float(torch.tensor(diff).std() / math.sqrt(n)),
        "wilcoxon_p": p,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=40)
    ap.add_argument("--ratings", type=int, default=30)
    ap.add_argument("--choices", type=int, default=20)
    ap.add_argument("--seed", type=int, default=24)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--fixed-gain", action="store_true", help="learn b, nu and eps only (g = 1)")
    ap.add_argument("--out", default="benchmarks/results/person_calibration.json")
    args = ap.parse_args()
    from tqdm import tqdm

    t0 = time.perf_counter()
    jobs = [
        (args.seed * 1000 + 10 * i, ideal, args.ratings, args.choices, not args.fixed_gain)
        for ideal in (False, True)
        for i in range(args.trials)
    ]
    with ProcessPoolExecutor(args.workers) as ex:
        rows = list(tqdm(ex.map(trial, *zip(*jobs)), total=len(jobs), desc="people"))
    rec, ideal = rows[: args.trials], rows[args.trials :]
    summary = {
        "settings": vars(args)
        | {"pool": POOL, "m": M, "sigma_R": SIGMA_R, "sigma_B": SIGMA_B, "lengthscale": LENGTHSCALE},
        "wall_s": time.perf_counter() - t0,
        "recovery": {
            "rating_offset": _errors(rec, "rating_offset", 0.0),
            "rating_gain": _errors(rec, "rating_gain", 1.0, log=True),
            "lapse_rate": _errors(rec, "lapse_rate", 0.1),
            "rating_precision": _errors(rec, "rating_precision", 40.0, log=True),
            "paired": {k: _paired(rec, k) for k in ("wrms", "tp", "regret")},
        },
        "ideal": {k: _paired(ideal, k) for k in ("wrms", "tp", "regret")},
        "fit_cpu_s_mean": sum(r["fit_cpu_s"] for r in rows) / len(rows),
        "convergence_warnings": sum(r["convergence_warnings"] for r in rows),
        "trials": rows,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    write_json(Path(args.out), summary)
    for k in ("rating_offset", "rating_gain", "lapse_rate", "rating_precision"):
        print(k, {a: round(b, 3) if isinstance(b, float) else b for a, b in summary["recovery"][k].items()})
    for study in ("recovery", "ideal"):
        part = summary[study]["paired"] if study == "recovery" else summary[study]
        print(study, {k: {a: round(b, 4) for a, b in v.items()} for k, v in part.items()})
    print(f"{summary['wall_s']:.0f} s wall")


if __name__ == "__main__":
    from torchpref.experiments.stamp import recording_subprocesses

    with recording_subprocesses():  # the stamp hashes the code of every process it starts too
        main()
