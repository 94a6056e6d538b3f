r"""A study run online on twins of real people (issue 46): does each new participant start better
when the population is refitted on everyone who finished before them?

For each data set (electricity, Dutch rail; the copies in ``benchmarks/studies/data``) and seed:

1. a population is fitted on ``--real`` real people's recorded choices (the twins' source);
2. ``--twins`` twins are drawn from it: each a true utility over the study's items (the data set's
   distinct items, at most ``--items``), drawn from the population's prior for a new person;
3. the twins arrive one after another, each answering ``--answers`` questions in a
   :class:`~torchpref.PreferenceSession` (the default selector; best-of-m choices with probit noise
   and Likert ratings from the true utility), twice: starting from the *online* population (fitted,
   as ``torchpref study`` does, on the twins who finished before, warm-started; none for the
   first two) and from *no* population (the session's default model);
4. after 0, 2, 5 and 10 answers, each model's accuracy is the fraction of item pairs it orders as
   the twin's true utility does.

Writes ``results/study/study_twins.json`` (stamped), ``study_twins.csv`` and ``study_twins.png``
(accuracy against arrival order, one panel per number of answers), and the refit cost as the
study grows (``--cost-sizes``: cold and warm-started fits, seconds) in the JSON.

    nice -n 10 .venv/bin/python benchmarks/studies/study_twins.py [--seeds 0 1 2] [--twins 40]
"""

from __future__ import annotations

import argparse
import copy
import csv
import os
import time
from pathlib import Path

import torch
from tqdm.auto import tqdm

import torchpref
from torchpref.experiments.replay import load
from torchpref.experiments.results import write_json
from torchpref.models.recipe import NO_TIES_OFFERED

DATA = Path(__file__).resolve().parent / "data"
OUT = Path(__file__).resolve().parents[1] / "results" / "study"
KS = (0, 2, 5, 10)
NOISE = 0.1  # the twins' probit noise on a choice (latent units)


def study_pool(people, max_items: int, g: torch.Generator) -> torch.Tensor:
    X = torch.cat([p.X for p in people]).unique(dim=0)
    return X[torch.randperm(X.shape[0], generator=g)[:max_items]] if X.shape[0] > max_items else X


def draw_twins(pop, pool: torch.Tensor, n: int, g: torch.Generator) -> torch.Tensor:
    """``n x N`` true utilities at the pool's items, from the population's prior for a new person."""
    with torch.no_grad():
        prior = pop.person_model(pool).posterior(pool)
    mean, cov = prior.mean.reshape(-1), prior.distribution.covariance_matrix
    L = torch.linalg.cholesky(cov + 1e-8 * torch.eye(cov.shape[0], dtype=cov.dtype))
    return mean + torch.randn(n, mean.shape[0], generator=g, dtype=mean.dtype) @ L.T


def concordance(pred: torch.Tensor, true: torch.Tensor) -> float:
    d_pred = pred.unsqueeze(0) - pred.unsqueeze(1)
    d_true = true.unsqueeze(0) - true.unsqueeze(1)
    mask = torch.triu(torch.ones_like(d_true, dtype=torch.bool), 1) & (d_true != 0)
    return float(((d_pred * d_true)[mask] > 0).double().mean())


def answer(q, f: torch.Tensor, g: torch.Generator):
    """A twin's answer to a session's query: a Likert level, or the best of the items shown."""
    if q.kind == "rating":
        u = torch.special.ndtr(f[q.index] / 2**0.5 + 0.1 * torch.randn((), generator=g, dtype=f.dtype))
        return int(min(5, max(1, 1 + int(5 * float(u)))))
    noisy = f[list(q.indices)] + NOISE * torch.randn(len(q.indices), generator=g, dtype=f.dtype)
    return int(noisy.argmax())


def run_twin(pool, f, population, seed, answers):
    """One twin's session; returns (accuracy after each k in KS, the session's data)."""
    lo, hi = torch.zeros(pool.shape[1], dtype=pool.dtype), torch.ones(pool.shape[1], dtype=pool.dtype)
    s = torchpref.PreferenceSession(
        pool, num_queries=answers, seed=seed, bounds=torch.stack([lo, hi]), population=population
    )
    g = torch.Generator().manual_seed(seed)
    acc = {}
    for k in range(answers + 1):
        if k in KS:
            acc[k] = concordance(s.predict(pool)[0], f)
        if k == answers:
            break
        q = s.ask()
        s.tell(q, answer(q, f, g))
    data = s.model.data
    s.close()
    return acc, data


def refit(finished, previous, max_iter_cold=60, max_iter_warm=25):
    kernels = {} if previous is None else {"k_m": copy.deepcopy(previous.k_m), "k_g": copy.deepcopy(previous.k_g)}
    t0 = time.perf_counter()
    pop = torchpref.fit_population(finished, max_iter=max_iter_warm if kernels else max_iter_cold, **kernels)
    return pop, time.perf_counter() - t0


def run(ds, seed, args, bar):
    people = load(ds, DATA)
    g = torch.Generator().manual_seed(seed)
    real = [people[i] for i in torch.randperm(len(people), generator=g)[: args.real].tolist()]
    from benchmarks_population import person_data

    base = torchpref.fit_population([person_data(p, p.choices) for p in real], max_iter=40, model=NO_TIES_OFFERED)
    pool = study_pool(people, args.items, g)
    twins = draw_twins(base, pool, args.twins, g)
    rows, finished, online, refit_s = [], [], None, []
    for t in range(args.twins):
        for cond, pop in (("online population", online), ("no population", None)):
            acc, data = run_twin(pool, twins[t], pop, seed * 1000 + t, args.answers)
            rows += [dict(dataset=ds, seed=seed, arrival=t, condition=cond, k=k, accuracy=a) for k, a in acc.items()]
            if cond == "online population":
                finished.append(data)
        if len(finished) >= 2:
            try:
                online, sec = refit(finished, online)
                refit_s.append((len(finished), sec))
            except (torch.linalg.LinAlgError, ArithmeticError, ValueError) as exc:  # as the study: the previous stays
                refit_s.append((len(finished), f"failed: {type(exc).__name__}"))
        bar.update(1)
    return rows, refit_s


def refit_cost(ds, sizes, args):
    """Seconds of a cold and of a warm-started fit as the study grows (twins of 10 answers each)."""
    people = load(ds, DATA)
    g = torch.Generator().manual_seed(99)
    from benchmarks_population import person_data

    base = torchpref.fit_population(
        [person_data(p, p.choices) for p in people[: args.real]], max_iter=40, model=NO_TIES_OFFERED
    )
    pool = study_pool(people, args.items, g)
    twins = draw_twins(base, pool, max(sizes) + 1, g)
    datas = [run_twin(pool, twins[t], None, 5000 + t, args.answers)[1] for t in range(max(sizes) + 1)]
    out = []
    for n in sizes:
        prev, cold = refit(datas[:n], None)
        _, warm = refit(datas[: n + 1], prev)
        out.append(dict(dataset=ds, participants=n, cold_s=round(cold, 2), warm_s=round(warm, 2)))
        print(f"{ds}: refit at {n} participants: cold {cold:.1f} s, warm (one more) {warm:.1f} s", flush=True)
    return out


def summarise(rows):
    from scipy import stats

    out = {}
    for ds in sorted({r["dataset"] for r in rows}):
        per = {}
        for k in KS:

            def accs(cond, later):
                return {
                    (r["seed"], r["arrival"]): r["accuracy"]
                    for r in rows
                    if r["dataset"] == ds and r["k"] == k and r["condition"] == cond and (r["arrival"] >= 20) == later
                }

            on, off = accs("online population", True), accs("no population", True)
            keys = sorted(set(on) & set(off))
            d = [on[x] - off[x] for x in keys]
            p = float(stats.wilcoxon(d).pvalue) if len(keys) >= 5 and any(d) else float("nan")
            per[str(k)] = dict(
                after_20=dict(online=_mean({x: on[x] for x in keys}), none=_mean({x: off[x] for x in keys}),
                              pairs=len(keys), p=p),
                first_20=dict(online=_mean(accs("online population", False)), none=_mean(accs("no population", False))),
            )  # fmt: skip
        out[ds] = per
    return out


def _mean(d):
    return sum(d.values()) / len(d) if d else float("nan")


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dss = sorted({r["dataset"] for r in rows})
    fig, axes = plt.subplots(len(dss), len(KS), figsize=(4 * len(KS), 3.2 * len(dss)), squeeze=False)
    for i, ds in enumerate(dss):
        for j, k in enumerate(KS):
            ax = axes[i][j]
            for cond, c in (("online population", "C0"), ("no population", "C1")):
                sel = [r for r in rows if r["dataset"] == ds and r["k"] == k and r["condition"] == cond]
                n = max(r["arrival"] for r in sel) + 1
                ys = [
                    sum(r["accuracy"] for r in sel if r["arrival"] == t) / max(1, sum(r["arrival"] == t for r in sel))
                    for t in range(n)
                ]
                ax.plot(range(1, n + 1), ys, color=c, label=cond)
            ax.set(
                title=f"{ds}: after {k} answers", xlabel="arrival order", ylabel="pairs ordered right" if j == 0 else ""
            )
            ax.axvline(20.5, color="grey", lw=0.6, ls=":")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--datasets", nargs="+", default=["electricity", "rail"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--twins", type=int, default=40)
    ap.add_argument("--answers", type=int, default=10)
    ap.add_argument("--real", type=int, default=120, help="real people the twins' population is fitted on")
    ap.add_argument("--items", type=int, default=120, help="the study's items: at most this many of the data set's")
    ap.add_argument("--cost-sizes", nargs="*", type=int, default=[10, 50, 200])
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args()
    torch.set_num_threads(1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    start, load0 = time.time(), os.getloadavg()[0]
    rows, refits = [], {}
    with tqdm(total=len(args.datasets) * len(args.seeds) * args.twins, desc="twins") as bar:
        for ds in args.datasets:
            for seed in args.seeds:
                r, c = run(ds, seed, args, bar)
                rows += r
                refits[f"{ds}/{seed}"] = c
    cost = [c for ds in args.datasets for c in refit_cost(ds, args.cost_sizes, args)] if args.cost_sizes else []
    summary = summarise(rows)
    with open(out / "study_twins.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    meta = dict(vars(args), seconds=round(time.time() - start, 1), cpu_count=os.cpu_count())
    meta["load_average_start_end"] = [round(load0, 2), round(os.getloadavg()[0], 2)]
    write_json(
        out / "study_twins.json",
        {"meta": meta, "summary": summary, "refit_cost": cost, "refits_during_study": refits},
        measured="harness: benchmarks/studies/study_twins.py",
    )
    plot(rows, out / "study_twins.png")
    for ds, per in summary.items():
        for k, e in per.items():
            a = e["after_20"]
            print(
                f"{ds} k={k}: arrivals after 20: online {a['online']:.3f} vs none {a['none']:.3f} (p={a['p']:.3g}, {a['pairs']} pairs)"
            )
    return 0


if __name__ == "__main__":
    import importlib.util
    import sys

    spec = importlib.util.spec_from_file_location("benchmarks_population", Path(__file__).with_name("population.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    sys.modules["benchmarks_population"] = module
    raise SystemExit(main())
