r"""How much of a query's value the profile selectors lose to Monte-Carlo noise.

For models after 8 queries of a few trials of several suite families (fixed hyperparameters,
the profile selector asking), the selector picks a query from the same 100 candidates with
``--seeds`` different sample seeds; each pick is then valued by a reference estimate from 16,384
joint samples (:func:`~torchpref.selection.top_profile.profile_variance_reduction`, value per effort).
Reported per state: the mean and the smallest reference value of the picks relative to the best
pick, and how often the picks agree on the query's kind. A ratio near 1 means the noise does not
change which query is worth asking; the reference best of the picks is a lower bound on the
best query, so the ratios overstate the value kept a little.

Writes ``results/profile_mc_noise.json``.

Usage::

    .venv/bin/python benchmarks/studies/profile_mc_noise.py [--samples 256 1024] [--seeds 20]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from torchpref.acquisition.functions import choice_probabilities, rating_bin_probabilities
from torchpref.data.queries import BoxCandidates
from torchpref.experiments import runner
from torchpref.experiments.families import FAMILIES, model_settings, setup
from torchpref.experiments.results import write_json
from torchpref.selection.active import run_active_learning
from torchpref.selection.samples import joint_posterior, joint_samples
from torchpref.selection.top_profile import ProfileVariancePerEffort, profile_variance_reduction, top_profile

FAMILY_NAMES = ("two-bumps", "narrow-peak", "waves", "hartmann6", "plateau")
REFERENCE_SAMPLES = 16384


def state(family_name: str, trial: int):
    """A model after 8 queries of a trial and the next 100 candidates."""
    family = FAMILIES[family_name]
    s = setup(family, 1000 + trial)
    first = s.user.choose(s.x0)
    model = runner.make_model(s.x0, torch.tensor([[first, 1 - first]]), model_settings(family))
    box = torch.tensor([[0.0] * family.dim, [1.0] * family.dim], dtype=torch.float64)
    candidates = BoxCandidates(box, 100)
    g = torch.Generator().manual_seed(s.selector_seed)
    run_active_learning(model, s.user, candidates, ProfileVariancePerEffort(), 8, generator=g)
    return model, candidates.draw(g)[0]


def reference_value(q, X, F, V, lik, sel) -> float:
    """A query's value per effort from the reference samples ``F`` and profile ``V``."""
    rows = [int((X == x).all(-1).nonzero()) for x in q.items]
    if q.kind == "rating":
        P, cost = rating_bin_probabilities(F[:, rows[0]], lik.rating, sel.num_bins), sel.rating_cost
    else:
        P, cost = choice_probabilities(F[:, rows], lik.comparison.comparison_noise), sel.ranking_cost
    return float(profile_variance_reduction(P.reshape(1, 1, *P.shape), V)) / cost


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", type=int, nargs="+", default=[256])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--trials", type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = []
    for name in FAMILY_NAMES:
        for trial in range(args.trials):
            model, X = state(name, trial)
            lik = model.likelihood
            with torch.no_grad():
                mean, cov = joint_posterior(model, X.unsqueeze(0))
                F = joint_samples(mean, cov, [torch.Generator().manual_seed(999)], REFERENCE_SAMPLES)[0][0]
            for clipped in (False, True):
                V = top_profile(F.unsqueeze(0), round(0.2 * X.shape[0]), lik.rating, clipped)
                for S in args.samples:
                    sel = ProfileVariancePerEffort(num_samples=S, clipped=clipped)
                    picks = [
                        sel.select(model, X, None, 8, 20, torch.Generator().manual_seed(k)) for k in range(args.seeds)
                    ]
                    vals = torch.tensor([reference_value(q, X, F, V, lik, sel) for q in picks])
                    kinds = [q.kind for q in picks]
                    rows.append(
                        {
                            "family": name,
                            "trial": trial,
                            "clipped": clipped,
                            "samples": S,
                            "mean_ratio": float((vals / vals.max()).mean()),
                            "min_ratio": float(vals.min() / vals.max()),
                            "share_same_kind": max(kinds.count("rating"), kinds.count("ranking")) / len(kinds),
                        }
                    )
                    print(rows[-1], flush=True)
    summary = {
        f"{'clipped' if c else 'profile'} S={S}": sum(
            r["mean_ratio"] for r in rows if r["clipped"] == c and r["samples"] == S
        )
        / sum(1 for r in rows if r["clipped"] == c and r["samples"] == S)
        for c in (False, True)
        for S in args.samples
    }
    print(summary)
    out = Path(__file__).resolve().parents[1] / "results" / "profile_mc_noise.json"
    write_json(
        out,
        {
            "summary_mean_ratio": summary,
            "states": rows,
            "seeds": args.seeds,
            "reference_samples": REFERENCE_SAMPLES,
        },
        measured="user",
    )


if __name__ == "__main__":
    main()
