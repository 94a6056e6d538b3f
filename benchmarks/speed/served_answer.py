r"""CPU per served answer: a session's ``tell`` and the next question (``ask``), as ``serve`` runs
them for each answer, under the default selector and under the paper's UCBC, in the same run.

Each of ``--sessions`` seeded sessions (``--items`` uniform items in ``[0, 1]^d``, ``d = --dim``,
rated on 5 levels, no file) is answered ``--answers`` times by a scripted person (a hidden utility
``sin(3 x . w)``: a rating's level from it, a choice of its best item); the two selectors' sessions
of a seed run alternately, answer by answer, so that whatever else the machine does falls on both
alike. One torch thread, float64 (``torch.set_default_dtype``: the documented path), CPU time of
this process (``time.process_time``) around ``tell`` + ``ask``; one throwaway session of each
selector first (imports, the compiled path's load). Timings are indicative: the load average
before and after is recorded beside them.

Writes ``results/served_answer/served_answer.json`` (settings, load, per selector p50 / p99 / max
/ mean in ms, stamped) and ``served_answer.csv`` (one row per answer).

Usage::

    OMP_NUM_THREADS=1 nice python benchmarks/speed/served_answer.py [--sessions 10] [--answers 12]
"""

from __future__ import annotations

import argparse
import csv
import os
import statistics
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
SELECTORS = ("default", "ucbc")


def person(seed: int, items: int, dim: int):
    """The items and a scripted person's answer to a query (seeded)."""
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(items, dim, generator=g)
    w = torch.randn(dim, generator=g)

    def answer(q) -> int:
        u = torch.sin(3 * q.items @ w)
        return int((1 + 4 * torch.special.ndtr(u[0])).round()) if q.kind == "rating" else int(u.argmax())

    return X, answer


def sessions(seed: int, args: argparse.Namespace) -> dict:
    """One session per selector over the same items and person: ``{name: (session, answer)}``."""
    import torchpref
    from torchpref.selection.defaults import named_selector

    X, answer = person(seed, args.items, args.dim)
    return {
        name: (
            torchpref.PreferenceSession(
                X, selector=named_selector(name, args.items, 5), num_queries=args.answers, seed=seed
            ),
            answer,
        )
        for name in SELECTORS
    }


def served(session, answer) -> tuple[float, float, str]:
    """Answer the pending question and ask the next: ``(tell ms, ask ms, the next question's kind)``."""
    q = session.ask()  # pending: asked when the previous answer was served
    a = answer(q)
    t0 = time.process_time()
    session.tell(q, a)
    t1 = time.process_time()
    nxt = session.ask()
    t2 = time.process_time()
    return 1000 * (t1 - t0), 1000 * (t2 - t1), nxt.kind if nxt.kind == "rating" else f"best of {len(nxt.items)}"


def pct(values: list[float], q: float) -> float:
    v = sorted(values)
    return round(v[min(len(v) - 1, int(q * len(v)))], 2)


def run(args: argparse.Namespace) -> tuple[dict, list[dict]]:
    rows = []
    warm = sessions(10_000, args)  # imports, the compiled path's load: not measured
    for s, a in warm.values():
        s.ask()
        served(s, a)
    for seed in range(args.seed, args.seed + args.sessions):
        now = sessions(seed, args)
        for s, _ in now.values():
            s.ask()  # the first question: before any answer, not an answer served
        for k in range(args.answers):
            for name in SELECTORS if (seed + k) % 2 == 0 else SELECTORS[::-1]:
                s, a = now[name]
                tell_ms, ask_ms, kind = served(s, a)
                rows.append(
                    {
                        "selector": name,
                        "session": seed,
                        "answer": k + 1,
                        "next_question": kind,
                        "tell_ms": round(tell_ms, 3),
                        "ask_ms": round(ask_ms, 3),
                        "served_ms": round(tell_ms + ask_ms, 3),
                    }
                )
    summary = {}
    for name in SELECTORS:
        mine = [r for r in rows if r["selector"] == name]
        total = [r["served_ms"] for r in mine]
        summary[name] = {
            "answers": len(total),
            "served_ms_p50": pct(total, 0.5),
            "served_ms_p99": pct(total, 0.99),
            "served_ms_max": round(max(total), 2),
            "served_ms_mean": round(statistics.fmean(total), 2),
            "tell_ms_p50": pct([r["tell_ms"] for r in mine], 0.5),
            "ask_ms_p50": pct([r["ask_ms"] for r in mine], 0.5),
        }
    return summary, rows


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sessions", type=int, default=10)
    ap.add_argument("--answers", type=int, default=12)
    ap.add_argument("--items", type=int, default=100)
    ap.add_argument("--dim", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(HERE.parent / "results" / "served_answer"))
    args = ap.parse_args(argv)
    if min(args.sessions, args.answers, args.dim) < 1 or args.items < 3:
        raise ValueError("need --sessions, --answers, --dim >= 1 and --items >= 3.")
    return args


def main(argv: list[str] | None = None) -> None:
    from torchpref.experiments.results import write_json
    from torchpref.inference import fast_path

    args = parse_args(argv)
    torch.set_num_threads(1)
    torch.set_default_dtype(torch.float64)
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    summary, rows = run(args)
    res = {
        "settings": vars(args),
        "what": "CPU ms of tell + the next ask per answer, one torch thread, float64",
        "fast_path": fast_path.status().splitlines()[0],
        "compiled_path_loaded": fast_path.loads(),
        "load_average": [round(x, 2) for x in (*load0, *os.getloadavg())],
        "load_average_note": "1/5/15-minute averages before the run, then after it",
        "cpu_count": os.cpu_count(),
        "wall_s": round(time.perf_counter() - t0, 1),
        "summary": summary,
        "default_over_ucbc_p50": round(summary["default"]["served_ms_p50"] / summary["ucbc"]["served_ms_p50"], 2),
    }
    out = Path(args.out)
    write_json(out / "served_answer.json", res, measured="user")
    with open(out / "served_answer.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    print(res["load_average"], summary)


if __name__ == "__main__":
    main()
