r"""Does the ordinal likelihood help for Likert answers, and do ties help? (issue 14)

Two paired studies; in each trial every arm sees the same items and the same answers.

* **Likert raters**: 20 random queries (alternately a rating of one item and a best-of-5 choice),
  answered by a simulated user whose ratings are quantised to 5 levels:
  ``wave`` (the paper's 1-D wave users, Beta noise, then the level whose bin holds the rating),
  ``bump`` (the same for random 2-D sums of three Gaussian bumps), ``partial`` (wave users who
  never give 1 or 5: levels clipped to 2..4) and ``lake`` (the paper's lake operator, noise-free
  levels of 400 planned paths). Arms: ``beta`` (levels as bin centres ``(k - 1/2)/5`` under the
  Beta likelihood: the paper's choice and the default before this study), ``ordinal`` (fixed cut
  points at the Beta link's bin edges) and ``ordinal-learned`` (cut points fitted by
  ``fit_gpytorch_mll``, kernel fixed). Metrics on the test points: WRMS of the expected level
  on the level scale (``(level - 1/2) / 5``, eq. 14), top-15 true positives and regret of the
  model's best point (its true utility's shortfall from the best, over the utility's range).
* **Ties**: 30 random pairs answered by a user who says "no preference" when the perceived
  utilities (noise ``sigma_R = 0.05`` each) differ by less than a margin (10 % or 25 % of the
  utility's range on the grid). Arms: ``ignored`` (no-preference answers add nothing: the
  behaviour before this study), ``used`` (tie likelihood, ``tau`` = the margin, strict answers
  as the tie's upper category: ``ties_offered=True``), ``default`` (the same with the default
  ``tau = 0.1``, what a session that does not know the margin gets), ``learned`` (``tau`` fitted,
  starting from 0.1). Metrics: WRMS of the expected rating on
  ``[0, 1]`` (as the wave experiment), top-15 true positives, regret.

Run ``nice -n 10 python benchmarks/studies/ordinal.py [--trials 100]``; writes
``benchmarks/results/ordinal.{json,csv,png}``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
import warnings
from pathlib import Path

import torch
from botorch.fit import fit_gpytorch_mll
from tqdm import tqdm

from torchpref.data.preference_data import best_of_m, likert_to_unit, unit_to_likert
from torchpref.experiments.results import paired_tests, write_json
from torchpref.experiments.runner import make_model as fixed_model
from torchpref.experiments.runner import single_threaded, trial_seeds
from torchpref.models.preference_gp import LaplaceMarginalLogLikelihood
from torchpref.simulation.metrics import true_positives, wrms
from torchpref.simulation.users import SimulatedUser
from torchpref.simulation.utility_functions import WaveFunction, evaluation_grid

RESULTS = Path(__file__).resolve().parents[1] / "results"
K = 5
#: model settings: the wave experiment's for wave, bump and partial; the lake experiment's for the lake
WAVE = {
    "lengthscale": 0.02,
    "outputscale": 0.36,
    "comparison_noise": 0.2,
    "rating_scale": 0.8,
    "rating_precision": 60.0,
}
BUMP = dict(WAVE, lengthscale=0.15, outputscale=1.0)
LAKE = {"lengthscale": 0.15, "outputscale": 1.0, "comparison_noise": 0.1, "rating_scale": 1.0, "rating_precision": 20.0}
LIKERT_ARMS = ["beta", "ordinal", "ordinal-learned"]
TIE_ARMS = ["ignored", "used", "default", "learned"]


# ------------------------------------------------------------------------------- worlds
class Bumps:
    """A random sum of three Gaussian bumps on ``[0, 1]^2``, scaled to span ``[-1.5, 1.5]`` on a grid."""

    def __init__(self, g: torch.Generator):
        u = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
        self.c, self.h, self.w = u(3, 2), 0.3 + 0.7 * u(3), 0.08 + 0.15 * u(3)
        raw = self._raw(grid_2d())
        self.lo, self.hi = raw.min(), raw.max()

    def _raw(self, X):
        d2 = ((X.unsqueeze(-2) - self.c) ** 2).sum(-1)
        return (self.h * torch.exp(-0.5 * d2 / self.w**2)).sum(-1)

    def __call__(self, X):
        return 3 * (self._raw(X) - self.lo) / (self.hi - self.lo) - 1.5


def grid_2d(n: int = 21) -> torch.Tensor:
    t = torch.linspace(0, 1, n, dtype=torch.float64)
    return torch.cartesian_prod(t, t)


def world(kind: str, g: torch.Generator, lake=None):
    """``(utility on items, test points, true utility there, true expected level there, settings,
    level function of a rating, item sampler)``."""
    if kind == "lake":
        Z, level = lake
        f_true = level.to(torch.float64)
        return None, Z, f_true, f_true, LAKE, None, lambda n: torch.randint(0, Z.shape[0], (n,), generator=g)
    truth = Bumps(g) if kind == "bump" else WaveFunction.random(generator=g)
    utility = truth if kind == "bump" else (lambda X: truth(X, noise=False))
    X_test = grid_2d() if kind == "bump" else evaluation_grid(101)
    settings = BUMP if kind == "bump" else WAVE
    f_true = utility(X_test)
    lo, hi = (2, 4) if kind == "partial" else (1, K)
    quantise = lambda u: unit_to_likert(u, K).clamp(lo, hi)  # noqa: E731
    level = expected_user_level(f_true, 0.8, 80.0, quantise)
    d = X_test.shape[-1]
    return (
        utility,
        X_test,
        f_true,
        level,
        settings,
        quantise,
        lambda n: torch.rand(n, d, generator=g, dtype=torch.float64),
    )


def expected_user_level(f: torch.Tensor, sigma_B: float, nu: float, quantise) -> torch.Tensor:
    """``E[level]`` of the simulated user at latent ``f``: Beta rating (eqs. 4-7) then ``quantise``."""
    from scipy import stats

    mu = torch.special.ndtr(f / (math.sqrt(2) * sigma_B)).numpy()
    edges = torch.linspace(0, 1, K + 1, dtype=torch.float64)[1:-1].numpy()
    cdf = torch.as_tensor(stats.beta.cdf(edges[:, None], nu * mu[None], nu * (1 - mu[None])))  # K-1 x n
    p = torch.cat([cdf[:1], cdf[1:] - cdf[:-1], 1 - cdf[-1:]])  # K x n
    levels = quantise(likert_to_unit(torch.arange(1, K + 1, dtype=torch.float64), K)).to(torch.float64)
    return (levels.unsqueeze(-1) * p).sum(0)


# ------------------------------------------------------------------------------- metrics
def scores(est_rating: torch.Tensor, est_utility: torch.Tensor, u_true: torch.Tensor, f_true: torch.Tensor) -> dict:
    """WRMS of ``est_rating`` against ``u_true`` (both on ``[0, 1]``), top-15 true positives and the
    regret of ``est_utility``'s best point in ``f_true`` (over ``f_true``'s range)."""
    best = int(est_utility.argmax())
    # true levels tie (the lake): count the estimated top 15 that have the best true value
    top = est_utility.topk(15).indices
    tp = (
        true_positives(est_utility, f_true, k=15)
        if f_true.unique().numel() > K
        else (f_true[top] == f_true.max()).sum()
    )
    return {
        "wrms": float(wrms(est_rating, u_true)),
        "tp": float(tp),
        "regret": float((f_true.max() - f_true[best]) / (f_true.max() - f_true.min())),
    }


def fit_likelihood(model, *names: str) -> int:
    """Fit the likelihood parameters ``names`` alone (the kernel is fixed); returns the number of
    optimiser warnings."""
    for n, p in model.named_parameters():
        p.requires_grad_(n.split(".")[-1] in names)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fit_gpytorch_mll(LaplaceMarginalLogLikelihood(model))
    return len(caught)


# ----------------------------------------------------------------------------- studies
def likert_trial(kind: str, seed: int, queries: int, lake=None) -> dict:
    g = torch.Generator().manual_seed(seed)
    utility, X_test, f_true, level_true, settings, quantise, draw = world(kind, g, lake)
    if kind == "lake":
        Z = lake[0]
        idx = draw(1 + queries // 2 + 5 * (queries - queries // 2))
        X = Z[idx]
        answers_f = f_true[idx] + 1e-6 * torch.arange(idx.numel())  # operator: best level, then first shown
        levels_of = lambda rows: level_true[idx[rows]]  # noqa: E731
        choose = lambda rows: int(answers_f[rows].argmax())  # noqa: E731
    else:
        user = SimulatedUser(utility, 0.05, 0.8, 80.0, generator=torch.Generator().manual_seed(seed + 1))
        X = draw(1 + queries // 2 + 5 * (queries - queries // 2))
        levels_of = lambda rows: quantise(torch.tensor([user.rate(X[r]) for r in rows]))  # noqa: E731
        choose = lambda rows: user.choose(X[rows])  # noqa: E731
    # query j: even -> a rating of the next item, odd -> a best-of-5 choice among the next five
    rated, comparisons, pos = [], [], 1
    for j in range(queries):
        if j % 2 == 0:
            rated.append(pos)
            pos += 1
        else:
            rows = list(range(pos, pos + 5))
            comparisons.append(best_of_m(rows[choose(rows)], rows))
            pos += 5
    rated = torch.tensor(rated)
    levels = levels_of(rated.tolist()).to(torch.float64)
    C = torch.cat(comparisons)
    u_true = (level_true - 0.5) / K
    out = {}
    for arm in LIKERT_ARMS:
        if arm == "beta":
            model = fixed_model(X, C, settings)
            model.add_observations(ratings=likert_to_unit(levels, K), rating_index=rated)
        else:
            model = level_model(X, C, settings, learn=arm == "ordinal-learned")
            model.add_observations(ratings=levels, rating_index=rated)
            if arm == "ordinal-learned":
                out["fit_warnings"] = fit_likelihood(model, "raw_cut_points")
        with torch.no_grad():
            mean, _ = model.marginals(X_test)
            est = model.expected_rating(X_test)  # both on the level scale's [0, 1]: (E[level] - 1/2) / K
        out[arm] = scores(est, est if kind == "lake" else mean, u_true, f_true)
    return out


def level_model(X, C, settings: dict, learn: bool):
    """A fixed-kernel model with 5-level ordinal ratings (cut points trainable with ``learn``)."""
    base = fixed_model(X, C, settings)
    from torchpref.models.preference_gp import PreferenceGP

    model = PreferenceGP(
        X,
        C,
        covar_module=base.covar_module,
        comparison_noise=settings["comparison_noise"],
        rating_scale=settings["rating_scale"],
        rating_precision=settings["rating_precision"],
        rating_levels=K,
        learn_likelihood=learn,
    )
    return model


def tie_trial(kind: str, margin_share: float, seed: int, queries: int) -> dict:
    g = torch.Generator().manual_seed(seed)
    utility, X_test, f_true, _, settings, _, draw = world(kind, g)
    margin = margin_share * float(f_true.max() - f_true.min())
    X = draw(2 * queries)
    f = utility(X)
    noise = 0.05 * torch.randn(2 * queries, generator=torch.Generator().manual_seed(seed + 1), dtype=torch.float64)
    d = (f + noise)[0::2] - (f + noise)[1::2]
    pairs = torch.arange(2 * queries).reshape(queries, 2)
    tie = d.abs() < margin
    C = torch.where((d > 0).unsqueeze(-1), pairs, pairs.flip(-1))[~tie]
    T = pairs[tie]
    u_true = torch.special.ndtr(f_true / (math.sqrt(2) * settings["rating_scale"]))
    out = {"tie_share": float(tie.double().mean())}
    for arm in TIE_ARMS:
        base = fixed_model(X, C, settings)
        if arm == "ignored":
            model = base
        else:
            from torchpref.models.preference_gp import PreferenceGP

            model = PreferenceGP(
                X,
                C,
                covar_module=base.covar_module,
                ties=T,
                learn_likelihood=arm == "learned",
                tie_threshold=margin if arm == "used" else 0.1,
                ties_offered=True,
                comparison_noise=settings["comparison_noise"],
                rating_scale=settings["rating_scale"],
                rating_precision=settings["rating_precision"],
            )
            if arm == "learned":  # tau fitted (fitting sigma_R too diverges: both grow without bound)
                out["fit_warnings"] = fit_likelihood(model, "raw_tie_threshold")
                out["tau_learned"] = float(model.likelihood.tie.tie_threshold.detach())
        with torch.no_grad():
            mean, _ = model.marginals(X_test)
            est = model.expected_rating(X_test)
        out[arm] = scores(est, mean, u_true, f_true)
    out["margin"] = margin
    return out


# ---------------------------------------------------------------------------- summary
def summarise(results: dict, arms: list[str], pairs: list[tuple[str, str]]) -> dict:
    out = {}
    for name, trials in results.items():
        entry = {}
        for arm in arms:
            for metric in ("wrms", "tp", "regret"):
                vals = torch.tensor([t[arm][metric] for t in trials], dtype=torch.float64)
                entry[f"{arm}/{metric}"] = [float(vals.mean()), float(vals.std() / math.sqrt(len(vals)))]
        for a, b in pairs:
            for metric in ("wrms", "tp", "regret"):
                entry[f"{a} - {b}/{metric}"] = paired_tests(
                    [t[a][metric] for t in trials], [t[b][metric] for t in trials]
                )
        out[name] = entry
    return out


def write_csv(path: Path, summary: dict, arms: list[str]) -> None:
    lines = ["study,scenario,arm,wrms_mean,wrms_sem,tp_mean,tp_sem,regret_mean,regret_sem"]
    for study, per in summary.items():
        for name, entry in per.items():
            for arm in arms[study]:
                vals = [f"{v:.5g}" for m in ("wrms", "tp", "regret") for v in entry[f"{arm}/{m}"]]
                lines.append(",".join([study, name, arm, *vals]))
    path.write_text("\n".join(lines) + "\n")


def plot(path: Path, summary: dict, arms: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(13, 7))
    for row, study in enumerate(("likert", "ties")):
        names = list(summary[study])
        for col, metric in enumerate(("wrms", "tp", "regret")):
            ax = axes[row, col]
            width = 0.8 / len(arms[study])
            for a, arm in enumerate(arms[study]):
                m = [summary[study][n][f"{arm}/{metric}"][0] for n in names]
                s = [summary[study][n][f"{arm}/{metric}"][1] for n in names]
                ax.bar([i + a * width for i in range(len(names))], m, width, yerr=s, label=arm, capsize=2)
            ax.set_xticks([i + 0.4 - width / 2 for i in range(len(names))], names, fontsize=8)
            ax.set_title(f"{study}: {metric} (mean ± s.e.)")
            if col == 0:
                ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def run_likert(seeds: list[int], lake_trials: int, seed: int) -> dict:
    from torchpref.lake.operator import LakeOperator
    from torchpref.lake.scenario import make_scenario

    likert = {
        kind: [likert_trial(kind, s, 20) for s in tqdm(seeds, desc=f"likert {kind}")]
        for kind in ("wave", "bump", "partial")
    }
    scenario = make_scenario(seed)
    lo, hi = scenario.train_X.min(0).values, scenario.train_X.max(0).values
    lake = ((scenario.train_X - lo) / (hi - lo), LakeOperator().level(scenario.train_X))
    likert["lake"] = [likert_trial("lake", s, 20, lake) for s in tqdm(seeds[:lake_trials], desc="likert lake")]
    return likert


def run_ties(seeds: list[int]) -> dict:
    return {
        f"{kind} {int(100 * share)}%": [tie_trial(kind, share, s, 30) for s in tqdm(seeds, desc=f"ties {kind} {share}")]
        for kind in ("wave", "bump")
        for share in (0.1, 0.25)
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--lake-trials", type=int, default=40)
    parser.add_argument("--seed", type=int, default=14)
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument(
        "--studies",
        default="likert,ties",
        help="studies to run; the others' trials are read back from OUT/ordinal.json",
    )
    args = parser.parse_args(argv)
    studies = set(args.studies.split(","))
    single_threaded()
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    seeds = trial_seeds(args.seed, args.trials)
    previous = None if studies >= {"likert", "ties"} else json.loads((args.out / "ordinal.json").read_text())
    likert = run_likert(seeds, args.lake_trials, args.seed) if "likert" in studies else previous["likert"]
    ties = run_ties(seeds) if "ties" in studies else previous["ties"]
    arms = {"likert": LIKERT_ARMS, "ties": TIE_ARMS}
    summary = {
        "likert": summarise(
            likert, LIKERT_ARMS, [("ordinal", "beta"), ("ordinal-learned", "beta"), ("ordinal-learned", "ordinal")]
        ),
        "ties": summarise(
            ties, TIE_ARMS, [("used", "ignored"), ("default", "ignored"), ("learned", "ignored"), ("learned", "used")]
        ),
    }
    for name, trials in ties.items():
        summary["ties"][name]["tie_share"] = sum(t["tie_share"] for t in trials) / len(trials)
        summary["ties"][name]["tau_learned_mean"] = sum(t["tau_learned"] for t in trials) / len(trials)
        summary["ties"][name]["margin_mean"] = sum(t["margin"] for t in trials) / len(trials)
    meta = {
        "trials": args.trials,
        "lake_trials": args.lake_trials,
        "seed": args.seed,
        "wall_time_s": time.perf_counter() - t0,
    }
    write_json(args.out / "ordinal.json", {"meta": meta, "summary": summary, "likert": likert, "ties": ties})
    write_csv(args.out / "ordinal.csv", summary, arms)
    plot(args.out / "ordinal.png", summary, arms)
    print(f"done in {meta['wall_time_s']:.0f} s; files in {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
