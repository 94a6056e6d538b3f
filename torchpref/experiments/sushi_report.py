r"""``torchpref reproduce sushi --data DIR``: real people who both rated and ranked, replayed
(:mod:`torchpref.experiments.sushi`), and the rating model chosen on them.

Steps, each writing under ``--out``:

1. **The rating model** (``rating_model.json``): for each Beta precision ``nu`` of a grid, on
   ``--calibration`` people who are neither replayed nor in the population, the evidence of their
   ratings and ranking (all 10 items; a session's default model otherwise) and how well a model of
   one split's 6 askable items' ratings and ranking orders the 4 held out. The precision a person's
   model uses (:data:`~torchpref.models.defaults.PERSON_RATING_PRECISION`) was chosen on this table.
2. **The population** of ``--train`` other people (their ratings and rankings; leave-people-out).
3. **The replay** of ``--people`` held-out people over ``--seeds`` splits, every policy of
   :data:`~torchpref.experiments.sushi.POLICIES` in both conditions, and the "all answers" references.

Files: ``sushi.json`` (stamped: per condition and policy the mean score at each number of answers
and at each budget of seconds, against the ranking and against the ratings; paired tests of the
default against the best single-kind policy at each budget, and of the combined references),
``sushi_curves.csv``, ``sushi.png``. Numbers only: no person's answers are written.
"""

from __future__ import annotations

import argparse
import csv
import os
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import torch

from torchpref.experiments import sushi
from torchpref.experiments.sushi_data import FEATURES, SOURCE, SushiData, load_sushi

__all__ = ["DATA_ENV", "PRECISIONS", "run"]

#: the environment variable naming the data folder when ``--data`` is not given
DATA_ENV = "TORCHPREF_SUSHI_DATA"
#: the Beta precisions of the rating-model table
PRECISIONS = (1.0, 2.0, 3.0, 5.0, 10.0, 20.0, 80.0)
TARGETS = ("ranking", "ratings")
#: single-kind policies: the default is compared with the best of them at each budget
SINGLE_KIND = (
    "random ratings",
    "random best-of-3",
    "random best-of-5",
    "default (ratings only)",
    "default (rankings only)",
)


def data_folder(args: argparse.Namespace) -> Path:
    """``--data``, else ``$TORCHPREF_SUSHI_DATA``; a ``FileNotFoundError`` saying where to get it."""
    folder = args.data or os.environ.get(DATA_ENV)
    if not folder:
        raise FileNotFoundError(
            f"give the SUSHI data's folder with --data DIR (or ${DATA_ENV}): download the sushi3-2016 release "
            f"from {SOURCE} and unpack it. torchpref ships none of it (its licence forbids redistribution)."
        )
    return Path(folder)


def _people(data: SushiData, args: argparse.Namespace) -> tuple[list[int], list[int], list[int]]:
    """Disjoint seeded draws of people: replayed, population, calibration."""
    n = len(data.people)
    need = args.people + args.train + args.calibration
    if n < need:
        raise ValueError(
            f"the data has {n} people; --people {args.people} + --train {args.train} + --calibration "
            f"{args.calibration} = {need} are needed: lower them."
        )
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(args.seed)).tolist()
    a, b = args.people, args.people + args.train
    return perm[:a], perm[a:b], perm[b:need]


def rating_model_table(data: SushiData, who: list[int], progress: Callable[..., Iterable[float]]) -> list[dict]:
    """Per precision: the summed evidence (ratings + ranking of all 10 items; ratings alone) and the
    held-out concordances of the three references (no population), under a session's model of that
    precision (:data:`~torchpref.models.recipe.DEFAULT_MODEL` otherwise)."""
    from dataclasses import replace

    from torchpref.models.recipe import DEFAULT_MODEL

    rows = []
    for nu in progress(PRECISIONS, desc="rating model"):
        settings = replace(DEFAULT_MODEL, rating_precision=nu)
        splits = [sushi.split(data, data.people[k], k, 0) for k in who]
        evidence = {"both": 0.0, "ratings": 0.0}
        for s in splits:
            for name, ranking in (("both", True), ("ratings", False)):
                d = sushi.person_data(s, ranking=ranking)
                m = settings.session_model(s.X)
                m.add_observations(comparisons=d.comparisons, ratings=d.ratings, rating_index=d.rating_index)
                with torch.no_grad():
                    evidence[name] += float(m.log_marginal_likelihood())
        refs = sushi.references(splits, None, settings)
        row = {"precision": nu, "evidence_both": evidence["both"], "evidence_ratings": evidence["ratings"]}
        for ref, per in refs.items():
            for t in TARGETS:
                row[f"{ref}:{t}"] = sum(p[t] for p in per) / len(per)
        rows.append(row)
    return rows


def _fit_population(data: SushiData, who: list[int], seed: int):
    from torchpref.population.fit import fit_population

    splits = [sushi.split(data, data.people[k], k, seed) for k in who]
    return fit_population([sushi.person_data(s) for s in splits], max_iter=40, feature_names=list(FEATURES))


def _mean(xs) -> float:
    xs = list(xs)
    return sum(xs) / len(xs)


def summarise(runs: dict, refs: dict) -> dict:
    """Means per condition, policy, target, answers and budget; paired tests (module notes)."""
    from torchpref.experiments.results import paired_tests

    out: dict = {"budgets": list(sushi.BUDGETS), "conditions": {}}
    for cond, per_policy in runs.items():
        c: dict = {"policies": {}, "references": {}, "tests": {}}
        for policy, people in per_policy.items():
            entry: dict = {}
            for t in TARGETS:
                curves = [p[t] for p in people]
                budgets = [sushi.at_budgets(p[t], p["seconds"]) for p in people]
                entry[t] = {
                    "by_answers": [_mean(c_[k] for c_ in curves) for k in range(len(curves[0]))],
                    "by_seconds": [_mean(b[k] for b in budgets) for k in range(len(sushi.BUDGETS))],
                }
            entry["rating_share_first6"] = _mean(p["kinds"][:6].count("rating") / 6 for p in people)
            entry["first_question_rating"] = _mean(p["kinds"][0] == "rating" for p in people)
            c["policies"][policy] = entry
        for ref, people in refs[cond].items():
            c["references"][ref] = {t: _mean(p[t] for p in people) for t in TARGETS}
        both = refs[cond]["both"]
        c["tests"]["both_vs_ratings_on_ranking"] = paired_tests(
            [p["ranking"] for p in both], [p["ranking"] for p in refs[cond]["all ratings"]]
        )
        c["tests"]["both_vs_ranking_on_ratings"] = paired_tests(
            [p["ratings"] for p in both], [p["ratings"] for p in refs[cond]["the ranking"]]
        )
        c["tests"]["both_vs_ratings_on_ratings"] = paired_tests(
            [p["ratings"] for p in both], [p["ratings"] for p in refs[cond]["all ratings"]]
        )
        c["tests"]["both_vs_ranking_on_ranking"] = paired_tests(
            [p["ranking"] for p in both], [p["ranking"] for p in refs[cond]["the ranking"]]
        )
        if "default" in per_policy:
            c["tests"]["default_vs_best_single_kind"] = _default_tests(per_policy)
        out["conditions"][cond] = c
    return out


def _default_tests(per_policy: dict) -> dict:
    """At each budget and target: the best single-kind policy (by mean) and the default's paired test against it."""
    from torchpref.experiments.results import paired_tests

    res: dict = {}
    singles = [p for p in SINGLE_KIND if p in per_policy]
    for t in TARGETS:
        rows = []
        for k, budget in enumerate(sushi.BUDGETS):

            def at(policy: str, k: int = k, t: str = t) -> list[float]:
                return [sushi.at_budgets(p[t], p["seconds"])[k] for p in per_policy[policy]]

            best = max(singles, key=lambda p: _mean(at(p)))
            test = paired_tests(at("default"), at(best))
            rows.append({"budget": budget, "best_single_kind": best, **test})
        res[t] = rows
    return res


def plot(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    conds = list(summary["conditions"])
    fig, axes = plt.subplots(len(TARGETS), len(conds), figsize=(6 * len(conds), 8), squeeze=False)
    for j, cond in enumerate(conds):
        c = summary["conditions"][cond]
        for i, t in enumerate(TARGETS):
            ax = axes[i][j]
            for policy, e in c["policies"].items():
                style = "-" if policy == "default" else ("--" if policy.startswith("default") else ":")
                ax.plot(summary["budgets"], e[t]["by_seconds"], style, marker="o", ms=3, label=policy,
                        lw=2.5 if policy == "default" else 1.2)  # fmt: skip
            for ref, v in c["references"].items():
                ax.axhline(v[t], color="grey", lw=0.8, alpha=0.6)
                ax.text(summary["budgets"][-1], v[t], f" all: {ref}", fontsize=7, va="center", color="grey")
            ax.set_title(f"{'no population' if cond == 'none' else 'population prior'}: against the person's {t}")
            ax.set_xlabel("seconds of answers (effort model)")
            ax.set_ylabel("concordance on pairs touching a held-out item")
            ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_curves(summary: dict, path: Path) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["condition", "policy", "target", "axis", "x", "concordance"])
        for cond, c in summary["conditions"].items():
            for policy, e in c["policies"].items():
                for t in TARGETS:
                    for k, v in enumerate(e[t]["by_answers"]):
                        w.writerow([cond, policy, t, "answers", k, f"{v:.6f}"])
                    for b, v in zip(summary["budgets"], e[t]["by_seconds"]):
                        w.writerow([cond, policy, t, "seconds", b, f"{v:.6f}"])


def run(args: argparse.Namespace) -> int:
    """``torchpref reproduce sushi``: the steps of the module notes, files under ``args.out``."""
    from tqdm.auto import tqdm

    from torchpref.experiments.results import write_json

    start, load0 = time.time(), os.getloadavg()[0]
    data = load_sushi(data_folder(args))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    replayed, train, calibration = _people(data, args)
    policies = list(args.policies or sushi.POLICIES)
    unknown = sorted(set(policies) - set(sushi.POLICIES))
    if unknown:
        raise ValueError(f"unknown policies {unknown}: choose from {list(sushi.POLICIES)}.")
    if calibration:
        table = rating_model_table(data, calibration, tqdm)
        write_json(out / "rating_model.json", {"people": len(calibration), "rows": table})
        _print_table(table)
    if args.rating_model_only:
        return 0
    pop = _fit_population(data, train, args.seed) if "population" in args.conditions else None
    prior = None if pop is None else sushi.population_prior(pop, data)
    runs: dict = {c: {p: [] for p in policies} for c in args.conditions}
    refs: dict = {c: {} for c in args.conditions}
    bar = tqdm(total=len(args.conditions) * args.seeds * (len(policies) + 1), desc="sushi replay")
    for seed in range(args.seeds):
        splits = [sushi.split(data, data.people[k], k, seed) for k in replayed]
        for cond in args.conditions:
            pr = prior if cond == "population" else None
            for name, per in sushi.references(splits, pr).items():
                refs[cond].setdefault(name, []).extend(per)
            bar.update()
            for policy in policies:
                runs[cond][policy].extend(sushi.replay(splits, policy, pr, args.queries, seed))
                bar.update()
    bar.close()
    summary = summarise(runs, refs)
    meta = {
        "people": len(replayed),
        "seeds": args.seeds,
        "population_people": len(train),
        "calibration_people": len(calibration),
        "queries": args.queries,
        "features": list(FEATURES),
        "seconds": round(time.time() - start, 1),
        "load_average_start_end": [round(load0, 2), round(os.getloadavg()[0], 2)],
        "cpu_count": os.cpu_count(),
    }
    write_json(out / "sushi.json", {"meta": meta, "summary": summary})
    write_curves(summary, out / "sushi_curves.csv")
    plot(summary, out / "sushi.png")
    _print(summary)
    return 0


def _print_table(rows: list[dict]) -> None:
    print("rating precision: evidence (ratings + ranking; ratings) and held-out concordance of all answers")
    for r in rows:
        refs = " ".join(f"{k}={v:.3f}" for k, v in r.items() if ":" in k)
        print(f"  nu {r['precision']:5g}: {r['evidence_both']:10.1f} {r['evidence_ratings']:10.1f}  {refs}")


def _print(summary: dict) -> None:
    print("concordance at", ", ".join(f"{b:g}" for b in summary["budgets"]), "seconds")
    for cond, c in summary["conditions"].items():
        print(f"[{cond}]")
        for t in TARGETS:
            print(f"  against the {t}:")
            for policy, e in c["policies"].items():
                print(f"    {policy:26s} " + " ".join(f"{v:.3f}" for v in e[t]["by_seconds"]))
            for ref, v in c["references"].items():
                print(f"    all answers: {ref:13s} {v[t]:.3f}")
