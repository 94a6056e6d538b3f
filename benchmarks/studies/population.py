r"""Population prior on real people (issue 31): leave-people-out on the electricity and Dutch rail
choices (``benchmarks/studies/data``; :mod:`torchpref.experiments.replay` loads them).

People are split into ``--folds`` seeded folds. For each fold, the population is fitted
(:func:`torchpref.fit_population`, hyperparameters by the evidence) on all the other folds' people
(``--train-people`` caps them, a seeded sample; by default all), all their choices. Each person of
the fold with at least 8 choices left after holding out a third (at least 3) is then scored on the
held-out choices after revealing k = 0, 1, 2, 4, 8 of their own choices (a seeded order), by

* **population**: ``pop.person_model(their items + k answers)``, the exact fit (the mean at every
  distinct training item);
* **population, inducing**: the same with the mean at ``--inducing`` inducing items (issue 47);
* **own GP**: the person's own GP of the replay study (RBF lengthscale ``sqrt(d)/2``,
  outputscale 1, ``sigma_R = 1``, fixed) on the k answers;
* **pooled**: one GP of every training answer pooled as if one person's (kernel ``k_m + k_g``
  of the population fit), which ignores the new person's answers.

Score: held-out comparison accuracy (each best-of-m as its m - 1 comparisons; 1/2 for an exact
tie) and log loss. Paired two-sided Wilcoxon over people per k. Writes
``benchmarks/results/population/`` ``population.json`` (stamped), ``population.csv``,
``population_rows.csv`` and ``population.png``.

Run: ``OMP_NUM_THREADS=1 nice -n 10 python benchmarks/studies/population.py``.
"""

from __future__ import annotations

import argparse
import csv
import os
import time
from pathlib import Path

import torch
from gpytorch.kernels import AdditiveKernel

import torchpref
from torchpref.data.preference_data import PreferenceData
from torchpref.experiments.replay import Person, load, score
from torchpref.models.kernels import fixed_rbf_kernel
from torchpref.models.recipe import NO_TIES_OFFERED

KS = (0, 1, 2, 4, 8)
METHODS = ("population", "population, inducing", "own GP", "pooled")
DATA = Path(__file__).resolve().parent / "data"
OUT = Path(__file__).resolve().parents[1] / "results" / "population"


def comparisons(choices) -> list[list[int]]:
    """Each best-of-m choice as its m - 1 comparisons ``[chosen, other]``."""
    return [[rows[j], r] for rows, j in choices for r in rows if r != rows[j]]


def person_data(p: Person, choices) -> PreferenceData:
    C = comparisons(choices)
    return PreferenceData.create(p.X, torch.tensor(C, dtype=torch.long) if C else None)


def split(p: Person, seed: int):
    g = torch.Generator().manual_seed(seed * 100_003 + int(p.pid) % 100_000 if p.pid.isdigit() else seed)
    order = torch.randperm(len(p.choices), generator=g).tolist()
    n_held = max(3, len(order) // 3)
    return [p.choices[i] for i in order[:n_held]], [p.choices[i] for i in order[n_held:]]


def own_gp(p: Person, choices) -> torchpref.PreferenceGP:
    C = comparisons(choices)
    kernel = fixed_rbf_kernel(0.5 * p.X.shape[-1] ** 0.5, 1.0, p.X)
    return torchpref.PreferenceGP(p.X, torch.tensor(C) if C else None, covar_module=kernel, comparison_noise=1.0)


def pooled_gp(pop, train: list[Person]) -> torchpref.PreferenceGP:
    """All training answers on the distinct items, as one person's."""
    U = torch.unique(torch.cat([p.X for p in train]), dim=0)
    rows = []
    for p in train:
        idx = [int((U == x).all(-1).nonzero()[0]) for x in p.X]
        rows += [[idx[a], idx[b]] for a, b in comparisons(p.choices)]
    kernel = AdditiveKernel(pop.k_m, pop.k_g)
    return torchpref.PreferenceGP(U, torch.tensor(rows), covar_module=kernel, comparison_noise=1.0)


def fit_both(train: list[Person], max_iter: int, inducing: int) -> tuple[dict, dict]:
    """The exact population and the one with its mean at ``inducing`` items, and their fit stats."""
    data = [person_data(p, p.choices) for p in train]
    pops, stats = {}, {}
    for method, where in (("population", None), ("population, inducing", inducing)):
        t0 = time.time()
        pops[method] = torchpref.fit_population(data, max_iter=max_iter, inducing=where, model=NO_TIES_OFFERED)
        stats[method] = dict(seconds=round(time.time() - t0, 1), **pops[method].stats)
    return pops, stats


def run_fold(name, people, test, train, seed, max_iter, inducing) -> tuple[list[dict], dict]:
    pops, stats = fit_both(train, max_iter, inducing)
    pooled = pooled_gp(pops["population"], train)
    out = []
    for p in test:
        held, pool = split(p, seed)
        if len(pool) < max(KS):
            continue
        for k in KS:
            models = {m: pop.person_model(person_data(p, pool[:k])) for m, pop in pops.items()}
            models["own GP"] = own_gp(p, pool[:k])
            models["pooled"] = pooled
            for method, model in models.items():
                acc, loss, _ = score(model, p.X, held)
                out.append(dict(dataset=name, person=p.pid, k=k, method=method, accuracy=acc, log_loss=loss))
    print(f"{name}: fold of {len(test)} people, population of {len(train)}: {stats}", flush=True)
    return out, stats


def summarise(rows: list[dict]) -> dict:
    from scipy import stats

    out: dict = {}
    for ds in sorted({r["dataset"] for r in rows}):
        out[ds] = {}
        for k in KS:
            here = {(r["person"], r["method"]): r for r in rows if r["dataset"] == ds and r["k"] == k}
            people = sorted({pid for pid, _ in here})
            entry: dict = {"people": len(people)}
            for m in METHODS:
                entry[m] = {x: sum(here[(pid, m)][x] for pid in people) / len(people) for x in ("accuracy", "log_loss")}
            for base in ("own GP", "pooled", "population, inducing"):
                d = [here[(pid, "population")]["accuracy"] - here[(pid, base)]["accuracy"] for pid in people]
                nz = [x for x in d if abs(x) > 1e-12]
                p = float(stats.wilcoxon(nz).pvalue) if len(nz) >= 5 else float("nan")
                entry[f"vs {base}"] = dict(
                    diff=sum(d) / len(d), wins=sum(x > 1e-12 for x in d), losses=sum(x < -1e-12 for x in d), p=p
                )
            out[ds][str(k)] = entry
    return out


def plot(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(summary), figsize=(5 * len(summary), 3.8), squeeze=False)
    for ax, (ds, per) in zip(axes[0], summary.items()):
        for m in METHODS:
            ax.plot(KS, [per[str(k)][m]["accuracy"] for k in KS], marker="o", label=m)
        ax.set_title(f"{ds}: held-out accuracy ({per['0']['people']} people)")
        ax.set_xlabel("own answers revealed (k)")
        ax.set_xticks(KS)
        ax.grid(alpha=0.3)
    axes[0][0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument(
        "--train-people",
        nargs="+",
        default=[],
        help="per data set, the most training people a population is fitted on (name=count; default all)",
    )
    ap.add_argument(
        "--inducing",
        nargs="+",
        default=["electricity=16", "rail=256"],
        help="per data set, the inducing items of the inducing population (name=M)",
    )
    ap.add_argument("--max-iter", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--datasets", nargs="+", default=["electricity", "rail"])
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args()
    torch.set_num_threads(1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    start, load0 = time.time(), os.getloadavg()[0]
    rows: list[dict] = []
    fits: dict[str, list] = {}
    for ds in args.datasets:
        people = load(ds, DATA)
        perm = torch.randperm(len(people), generator=torch.Generator().manual_seed(args.seed)).tolist()
        folds = [[people[i] for i in perm[f :: args.folds]] for f in range(args.folds)]
        for f in range(args.folds):
            others = [p for g, fold in enumerate(folds) if g != f for p in fold]
            pick = torch.randperm(len(others), generator=torch.Generator().manual_seed(args.seed + f))
            cap = int(dict(x.split("=") for x in args.train_people).get(ds, len(others)))
            train = [others[i] for i in sorted(pick[:cap].tolist())]
            M = int(dict(x.split("=") for x in args.inducing)[ds])
            fold_rows, stats = run_fold(ds, people, folds[f], train, args.seed, args.max_iter, M)
            rows += fold_rows
            fits.setdefault(ds, []).append(dict(fold=f, train_people=len(train), **stats))
    summary = summarise(rows)
    with open(out / "population_rows.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    with open(out / "population.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(
            [
                "dataset",
                "k",
                "people",
                *[f"{m} accuracy" for m in METHODS],
                "p vs own GP",
                "p vs pooled",
                "inducing - exact",
            ]
        )
        for ds, per in summary.items():
            for k in KS:
                e = per[str(k)]
                accs = [round(e[m]["accuracy"], 4) for m in METHODS]
                gap = round(e["population, inducing"]["accuracy"] - e["population"]["accuracy"], 4)
                w.writerow([ds, k, e["people"], *accs, e["vs own GP"]["p"], e["vs pooled"]["p"], gap])
    meta = dict(vars(args), seconds=round(time.time() - start, 1), cpu_count=os.cpu_count())
    meta["load_average_start_end"] = [round(load0, 2), round(os.getloadavg()[0], 2)]
    from torchpref.experiments.results import write_json

    write_json(
        out / "population.json",
        {"meta": meta, "summary": summary, "fits": fits},
        measured="harness: benchmarks/studies/population.py",
    )
    plot(summary, out / "population.png")
    for ds, per in summary.items():
        for k in KS:
            e = per[str(k)]
            accs = "  ".join(f"{m} {e[m]['accuracy']:.4f}" for m in METHODS)
            print(f"{ds} k={k}: {accs}  p(own)={e['vs own GP']['p']:.3g} p(pooled)={e['vs pooled']['p']:.3g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
