r"""Server time per answer of ``torchpref serve`` over 200 answers, measured against the page
with a scripted browser (Playwright driving Chromium, answering by keyboard).

The server runs as ``python -m torchpref.cli serve --features items.csv`` (a pool of ``--items``
items with ``--dim`` objectives, UCBC's questions, 5 levels, ties offered). For every answer the
benchmark keeps

* ``server_ms``: the server's time for the answer request (the ``Server-Timing`` header: the
  answer validated, told to the session, fsynced, the next question chosen, the recommended item
  found), as the page read it;
* ``round_trip_ms``: the browser's time from the key press to the next question on screen;
* the journal record's ``response_time`` (the page's seconds from showing to answering).

Writes ``results/serve/timing.{json,csv,png}``. The target: median ``server_ms`` under 100 ms at
200 answers. Times are taken on whatever machine runs it (``uptime``'s load is recorded).

Usage::

    .venv/bin/python benchmarks/durability/serve_timing.py [--answers 200] [--items 100] [--dim 3]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
from torchpref.experiments.results import write_json  # noqa: E402
from torchpref.testing.serve import CHROMIUM, CHROMIUM_ARGS, Server, choose, records, write_items  # noqa: E402

LETTERS = "ABCDEFGHIJ"


def _key(q: dict, a) -> str:
    if q["kind"] == "rating":
        return str(a)
    return "0" if a is None else LETTERS[a]


def run(answers: int, n_items: int, dim: int, out: Path) -> dict:
    from playwright.sync_api import sync_playwright
    from tqdm import tqdm

    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        items = write_items(folder, n=n_items, d=dim, pictures=False)
        srv = Server(["--features", str(items), "--sessions", "sessions", "--queries", str(answers)], folder)
        srv.start()
        rows = []
        try:
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
                page = browser.new_page(bypass_csp=True)
                page.goto(srv.url)
                page.keyboard.press("Enter")
                page.wait_for_selector("body[data-qid]", timeout=120_000)
                sid = page.url.rstrip("/").rsplit("/", 1)[1]
                for k in tqdm(range(answers), desc="answers", unit="answer"):
                    st = page.evaluate("window.torchpref.state()")
                    q = st["question"]
                    a = choose(q, k)
                    t0 = time.perf_counter()
                    page.keyboard.press(_key(q, a))
                    page.wait_for_function(f"document.body.dataset.answered === '{k + 1}'", timeout=120_000)
                    trip = 1000 * (time.perf_counter() - t0)
                    server_ms = page.evaluate("window.torchpref.log.serverMs")[-1]
                    rows.append({"answer": k + 1, "kind": q["kind"], "server_ms": server_ms, "round_trip_ms": trip})
                browser.close()
        finally:
            srv.stop()
        recs = [r for r in records(folder / "sessions" / f"{sid}.session.jsonl") if r["type"] == "answer"]
    for row, rec in zip(rows, recs, strict=True):
        row["response_time_s"] = rec["response_time"]
    server = [r["server_ms"] for r in rows]
    last = server[-50:]
    summary = {
        "answers": answers,
        "items": n_items,
        "dim": dim,
        "median_server_ms": statistics.median(server),
        "median_server_ms_last_50": statistics.median(last),
        "p90_server_ms": sorted(server)[int(0.9 * len(server))],
        "max_server_ms": max(server),
        "median_round_trip_ms": statistics.median(r["round_trip_ms"] for r in rows),
        "records_with_response_time": sum(isinstance(r["response_time_s"], float) for r in rows),
        "target_median_server_ms": 100.0,
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
        "cpus": os.cpu_count(),
    }
    summary["target_met"] = summary["median_server_ms"] < 100.0
    out.mkdir(parents=True, exist_ok=True)
    write_json((out / "timing.json"), {"summary": summary, "answers": rows}, measured="user")
    with open(out / "timing.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    _plot(rows, summary, out / "timing.png")
    return summary


def _plot(rows, summary, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.8))
    for kind, colour in (("rating", "#1f77b4"), ("ranking", "#ff7f0e")):
        pts = [(r["answer"], r["server_ms"]) for r in rows if r["kind"] == kind]
        if pts:
            ax.scatter(*zip(*pts, strict=True), s=8, c=colour, label=f"{kind} answered")
    ax.axhline(100, color="k", ls="--", lw=1, label="target: median 100 ms")
    ax.axhline(
        summary["median_server_ms"], color="#2ca02c", lw=1.5, label=f"median {summary['median_server_ms']:.1f} ms"
    )
    ax.set_xlabel("answer number")
    ax.set_ylabel("server time per answer (ms)")
    ax.set_title(f"torchpref serve: {summary['items']} items, d = {summary['dim']}, scripted Chromium")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--answers", type=int, default=200)
    ap.add_argument("--items", type=int, default=100)
    ap.add_argument("--dim", type=int, default=3)
    ap.add_argument("--out", default=str(HERE.parent / "results" / "serve"))
    args = ap.parse_args()
    summary = run(args.answers, args.items, args.dim, Path(args.out))
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    from torchpref.experiments.stamp import recording_subprocesses

    with recording_subprocesses():  # the stamp hashes the code of every process it starts too
        main()
