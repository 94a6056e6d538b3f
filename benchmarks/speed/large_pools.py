r"""Large pools: seconds and peak memory of the next question among ``N`` items (issue 54).

For each pool size ``N`` and dimension ``d``, in a fresh process (one thread), a
:class:`~torchpref.PreferenceSession` over ``N`` uniform items in ``[0, 1]^d`` is told 12 answers
(6 best-of-3 and 6 ratings of random items, answered by a fixed utility), its model is built, and
then one question is chosen and timed (process CPU seconds, wall seconds, the process's peak
resident memory) by:

* ``session``: ``session.ask()``, the session's own path (its default selector, shortlisted where
  the pool has more than ``SHORTLIST_ABOVE`` items: ``torchpref/selection/shortlist.py``);
* ``exact``: the default selector over the whole pool (its joint posterior of the ``N`` items),
  where ``N <= --exact-max``;
* ``botorch_qeubo``: BoTorch's ``qExpectedUtilityOfBestOption`` on the session's model, a pair chosen
  from the pool by BoTorch's ``optimize_acqf_discrete`` (sequential greedy, batches of 2,048),
  where ``N <= --qeubo-max``.

``setup_s`` is the session's construction (validating the pool, its header) and the 12 answers.

``--accuracy``: at pools where the exact choice fits (``N`` of 500, 1,000 and 2,000, ``d = 4``,
``--seeds`` sessions each, 12 answers as above), the default selector's choice over the pool, its
choice over the pool's shortlist (:class:`~torchpref.selection.shortlist.Shortlisted`, size 256)
from the same generator, and its choice over the pool from another generator; how often the
first two are the same question, and the value each of the others gives up against the exact
choice, valued as the exact selector values questions (its ``scorers`` on the whole pool, per
second) on independent samples (``EVAL_SAMPLES`` of them: valued on its own samples, the exact
choice would win by its own noise). The other generator's loss is the noise floor: what the exact
selector gives up against itself.

``--serve``: ``torchpref serve``'s path in process over a features CSV of 10,000 and 100,000 rows
(:func:`serve_path`).

Writes ``results/large_pools/cost.json`` / ``cost.csv`` / ``cost.png``, ``accuracy.json`` /
``accuracy.csv`` and ``serve.json`` / ``serve.csv``, stamped (load average included: timings under load are not a quiet machine's).

Usage::

    .venv/bin/python benchmarks/speed/large_pools.py [--sizes 1000 10000 100000] [--dims 4 16]
    .venv/bin/python benchmarks/speed/large_pools.py --accuracy [--seeds 10]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "benchmarks" / "results" / "large_pools"
SIZES = [1000, 3000, 10_000, 30_000, 100_000, 300_000, 1_000_000]
METHODS = ("session", "exact", "botorch_qeubo")
EVAL_SAMPLES = 2048


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def utility(X: torch.Tensor) -> torch.Tensor:
    """A smooth utility with one peak inside the cube."""
    return -((X - 0.3) ** 2).sum(-1) * 4


def answered_session(N: int, d: int, seed: int):
    """A session over ``N`` uniform items told 6 best-of-3 and 6 ratings of random items."""
    from torchpref import PreferenceSession
    from torchpref.data.queries import RankingQuery, RatingQuery

    g = torch.Generator().manual_seed(seed)
    X = torch.rand(N, d, generator=g, dtype=torch.float64)
    s = PreferenceSession(X, num_queries=14, seed=seed)
    rows = torch.randperm(N, generator=g)[:24].tolist()
    for k in range(6):
        r = rows[3 * k : 3 * k + 3]
        s.tell(RankingQuery(X[r], tuple(r)), int(utility(X[r]).argmax()))
        i = rows[18 + k]
        level = 1 + int(round(4 * float(torch.sigmoid(utility(X[i]) + 1))))
        s.tell(RatingQuery(X[i], i), level)
    s.model  # noqa: B018  (the model of the 12 answers, built before anything is timed)
    return s, X


def one(N: int, d: int, method: str, seed: int) -> dict:
    """One measurement in this process (the parent starts a fresh one for each)."""
    torch.set_num_threads(1)
    rss0 = _rss_mb()
    w0, c0 = time.perf_counter(), time.process_time()
    s, X = answered_session(N, d, seed)
    setup_s = time.perf_counter() - w0
    rss_setup = _rss_mb()
    w0, c0 = time.perf_counter(), time.process_time()
    if method == "session":
        q = s.ask()
        kind = q.kind
    elif method == "exact":
        from torchpref.selection.defaults import default_selector
        from torchpref.sessions.settings import step_generator

        sel = default_selector(N)
        q = sel.select(s.model, s.transform(X), torch.arange(N), 12, 14, step_generator(seed, 12))
        kind = q.kind
    else:
        from botorch.acquisition.preference import qExpectedUtilityOfBestOption
        from botorch.optim import optimize_acqf_discrete
        from botorch.sampling import SobolQMCNormalSampler

        acq = qExpectedUtilityOfBestOption(
            pref_model=s.model, sampler=SobolQMCNormalSampler(torch.Size([256]), seed=seed)
        )
        optimize_acqf_discrete(acq, q=2, choices=s.transform(X), max_batch_size=2048)
        kind = "ranking"
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    return dict(
        N=N, d=d, method=method, seed=seed, kind=kind, cpu_s=cpu, wall_s=wall, setup_s=setup_s,
        rss_start_mb=rss0, rss_after_setup_mb=rss_setup, peak_rss_mb=_rss_mb(),
    )  # fmt: skip


def accuracy_row(N: int, seed: int) -> dict:
    """The exact choice, the exact selector's choice with other random numbers, and the
    shortlist's, all valued by the exact selector on independent samples (more of them)."""
    import copy

    from torchpref.data.queries import RatingQuery
    from torchpref.selection.defaults import default_selector
    from torchpref.selection.shortlist import Shortlisted

    s, X = answered_session(N, 4, seed)
    Xt, idx = s.transform(X), torch.arange(N)
    sel = default_selector(N)
    gen = lambda k: torch.Generator().manual_seed(k)  # noqa: E731
    exact = sel.select(s.model, Xt, idx, 12, 14, gen(1000 + seed))
    other = sel.select(s.model, Xt, idx, 12, 14, gen(2000 + seed))
    short = Shortlisted(sel).select(s.model, Xt, idx, 12, 14, gen(1000 + seed))
    judge = copy.copy(sel)
    if hasattr(judge, "num_samples"):
        judge.num_samples = EVAL_SAMPLES
    with torch.no_grad():
        rate, rank = judge.scorers(s.model, Xt.unsqueeze(0), [gen(5000 + seed)])

    def value(q) -> float:
        if isinstance(q, RatingQuery):
            return float(rate(torch.tensor([[q.index]]))[0, 0]) / sel.query_cost(1)
        return float(rank(torch.tensor([[list(q.indices)]]))[0, 0]) / sel.query_cost(len(q.indices))

    rows = lambda q: [q.index] if isinstance(q, RatingQuery) else sorted(q.indices)  # noqa: E731
    ve, vo, vs = value(exact), value(other), value(short)
    return dict(
        N=N, seed=seed, exact_kind=exact.kind, short_kind=short.kind, same=rows(exact) == rows(short),
        exact_value=ve, other_seed_value=vo, short_value=vs,
        given_up=(ve - vs) / abs(ve) if ve else 0.0, other_seed_given_up=(ve - vo) / abs(ve) if ve else 0.0,
    )  # fmt: skip


def serve_path(N: int, d: int, folder: Path) -> dict:
    """``torchpref serve``'s path over ``N`` items in process (Starlette's test client): reading a
    ``N``-row features CSV, a new participant and the page's first question, 12 answers, the summary
    page, its plot and the three downloads, each timed (wall seconds of the request), with the
    participant's session file's size and the process's peak memory (the drawing process's not
    included)."""
    from torchpref.frontends.serve.items import items_from_csv
    from torchpref.frontends.serve.store import SessionStore
    from torchpref.testing.serve import serve_client

    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)
    X = torch.rand(N, d, generator=g, dtype=torch.float64)
    csv_path = folder / "items.csv"
    with open(csv_path, "w") as fh:
        fh.write("id," + ",".join(f"f{k}" for k in range(d)) + "\n")
        fh.writelines(f"item{i}," + ",".join(repr(v) for v in r) + "\n" for i, r in enumerate(X.tolist()))
    out: dict = {"N": N, "d": d}
    t = time.perf_counter()
    items = items_from_csv(csv_path)
    out["read_csv_s"] = time.perf_counter() - t
    store = SessionStore(items, folder / "sessions", num_queries=14)
    client = serve_client(store)

    def timed(key: str, call):
        t = time.perf_counter()
        r = call()
        out[key] = time.perf_counter() - t
        if r.status_code != 200:
            raise RuntimeError(f"{key}: {r.status_code} {r.text[:200]}")
        return r

    sid = timed("new_participant_s", lambda: client.post("/api/new", json={})).json()["sid"]
    timed("first_page_s", lambda: client.get(f"/s/{sid}/"))
    answers = []
    for _ in range(12):
        st = timed("state_s", lambda: client.get(f"/s/{sid}/state")).json()
        body = {"qid": st["qid"], "answer": 4 if st["question"]["kind"] == "rating" else 0}
        timed("answer_s", lambda: client.post(f"/s/{sid}/answer", json=body))
        answers.append(out["answer_s"])
    out["answer_median_s"], out["answer_max_s"] = sorted(answers)[6], max(answers)
    timed("summary_s", lambda: client.get(f"/s/{sid}/summary"))
    timed("utility_png_first_s", lambda: client.get(f"/s/{sid}/utility.png"))  # starts the drawing process
    timed("utility_png_s", lambda: client.get(f"/s/{sid}/utility.png?x=0&y=2"))  # another plot, process warm
    for what in ("session.jsonl", "answers.csv", "model.pt"):
        timed(f"download_{what}_s", lambda: client.get(f"/s/{sid}/download/{what}"))
    out["session_file_kb"] = store.path(sid).stat().st_size / 1024
    out["peak_rss_mb"] = _rss_mb()
    store.close()
    return out


def _spawn(args: list[str], timeout: float) -> dict | None:
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    try:
        out = subprocess.run(
            [sys.executable, __file__, *args], capture_output=True, text=True, timeout=timeout, env=env, check=False
        )
    except subprocess.TimeoutExpired:
        return None
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    if out.returncode != 0 or not lines:
        print(out.stderr[-2000:], file=sys.stderr)
        return None
    return json.loads(lines[-1])


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for method, marker in zip(METHODS, "osd"):
        for d, ls in ((4, "-"), (16, "--")):
            pts = sorted((r["N"], r["cpu_s"], r["peak_rss_mb"]) for r in rows if r["method"] == method and r["d"] == d)
            if pts:
                n, cpu, mem = zip(*pts)
                axes[0].plot(n, cpu, ls, marker=marker, label=f"{method}, d={d}")
                axes[1].plot(n, mem, ls, marker=marker, label=f"{method}, d={d}")
    axes[0].axhline(0.5, color="grey", lw=0.8)
    axes[1].axhline(1536, color="grey", lw=0.8)
    for ax, label in zip(axes, ("CPU seconds for the next question", "process peak memory (MB)")):
        ax.set(xscale="log", yscale="log", xlabel="items in the pool (N)", ylabel=label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    load = os.getloadavg()[0]
    fig.suptitle(f"The next question after 12 answers, one thread (load average {load:.1f} at the end)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def _write(name: str, rows: list[dict], summary: dict) -> None:
    from torchpref.experiments.results import write_json

    RESULTS.mkdir(parents=True, exist_ok=True)
    write_json(RESULTS / f"{name}.json", {**summary, "rows": rows}, sources=[Path(__file__)])
    if rows:
        with open(RESULTS / f"{name}.csv", "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--one", nargs=4, metavar=("N", "D", "METHOD", "SEED"))
    ap.add_argument("--accuracy-one", nargs=2, metavar=("N", "SEED"))
    ap.add_argument("--accuracy", action="store_true")
    ap.add_argument("--serve", action="store_true", help="time serve's path over 10,000 and 100,000 items")
    ap.add_argument("--serve-one", nargs=2, metavar=("N", "D"))
    ap.add_argument("--sizes", type=int, nargs="+", default=SIZES)
    ap.add_argument("--dims", type=int, nargs="+", default=[4, 16])
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    ap.add_argument("--exact-max", type=int, default=3000)
    ap.add_argument("--qeubo-max", type=int, default=100_000)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--timeout", type=float, default=600)
    args = ap.parse_args(argv)
    if args.one:
        print(json.dumps(one(int(args.one[0]), int(args.one[1]), args.one[2], int(args.one[3]))))
        return 0
    if args.serve_one:
        import tempfile

        with tempfile.TemporaryDirectory() as tmp:
            print(json.dumps(serve_path(int(args.serve_one[0]), int(args.serve_one[1]), Path(tmp))))
        return 0
    if args.accuracy_one:
        torch.set_num_threads(1)
        print(json.dumps(accuracy_row(int(args.accuracy_one[0]), int(args.accuracy_one[1]))))
        return 0
    import torchpref.selection.shortlist
    from torchpref.sessions.session import PreferenceSession  # noqa: F401

    load0 = os.getloadavg()
    if args.serve:
        import torchpref.frontends.serve.store  # noqa: F401  (for the stamp)

        rows = [r for N in (10_000, 100_000) if (r := _spawn(["--serve-one", str(N), "4"], args.timeout))]
        for r in rows:
            print(r, flush=True)
        _write("serve", rows, {"load_at_start": load0, "load_at_end": os.getloadavg(), "threads": 1})
        return 0
    if args.accuracy:
        rows = []
        for N in (500, 1000, 2000):
            for seed in range(args.seeds):
                r = _spawn(["--accuracy-one", str(N), str(seed)], args.timeout)
                if r is not None:
                    rows.append(r)
                    print(r, flush=True)
        by_n = {}
        for N in sorted({r["N"] for r in rows}):
            rs = [r for r in rows if r["N"] == N]
            by_n[str(N)] = dict(
                runs=len(rs),
                same_share=sum(r["same"] for r in rs) / len(rs),
                mean_given_up=sum(r["given_up"] for r in rs) / len(rs),
                mean_other_seed_given_up=sum(r["other_seed_given_up"] for r in rs) / len(rs),
                worst_given_up=max(r["given_up"] for r in rs),
            )
        _write("accuracy", rows, {"by_N": by_n, "load_at_start": load0, "load_at_end": os.getloadavg()})
        print(json.dumps(by_n, indent=1))
        return 0
    rows = []
    for d in args.dims:
        for N in args.sizes:
            for method in args.methods:
                if (method == "exact" and N > args.exact_max) or (method == "botorch_qeubo" and N > args.qeubo_max):
                    continue
                r = _spawn(["--one", str(N), str(d), method, "0"], args.timeout)
                if r is None:
                    print(f"N={N} d={d} {method}: failed or over {args.timeout} s", flush=True)
                    continue
                r["load_1min"] = os.getloadavg()[0]
                rows.append(r)
                print({k: round(v, 3) if isinstance(v, float) else v for k, v in r.items()}, flush=True)
    _write("cost", rows, {"load_at_start": load0, "load_at_end": os.getloadavg(), "threads": 1})
    plot(rows, RESULTS / "cost.png")
    return 0


if __name__ == "__main__":
    from torchpref.experiments.stamp import recording_subprocesses

    with recording_subprocesses():  # the stamp hashes the code of every process it starts too
        raise SystemExit(main())
