r"""A whole study over HTTP with kills (issue 46's reliability): ``--participants`` scripted
participants (40) answer ``--answers`` questions each (6), ``--active`` (10) at a time, against
``torchpref study serve`` run as a process, arriving ``--arrival`` (5) seconds apart on average
and thinking 0.5-1.5 s per answer; meanwhile the server is killed (SIGKILL) ``--kills``
times (10) at random moments, preferring the moments a population refit is running, and
restarted on the same folder. At the end:

* every acknowledged answer is in its session file, in force (0 lost);
* after every kill the population file in force loads (``torchpref.load_population``); the kills
  start once the first population is in force;
* the population was refitted at least once per 5 finished participants;
* the export's answer rows are the session files' answer records;
* the report opens in Chromium with its figures (where Chromium and Playwright are installed).

Writes ``results/study/NAME.json`` (stamped): ``study_run`` without kills (``--kills 0``: how
often the population is refitted as participants finish), ``study_run_kills`` with them.

    nice -n 10 .venv/bin/python benchmarks/durability/study_run.py [--participants 40] [--kills 10]
"""

from __future__ import annotations

import argparse
import os
import queue
import random
import tempfile
import threading
import time
from pathlib import Path

from torchpref.experiments.results import write_json
from torchpref.testing.serve import (
    CHROMIUM,
    CHROMIUM_ARGS,
    Server,
    acknowledged_in_file,
    choose,
    get_json,
    post,
    records,
    write_items,
)

OUT = Path(__file__).resolve().parents[1] / "results" / "study"


def participant(base: str, n: int, k0: int, acked: dict, lock: threading.Lock, stop: threading.Event) -> None:
    """One scripted participant: a new session, ``n`` answers, each retried until acknowledged
    (a killed server is retried, as the page does)."""
    sid = None
    while sid is None and not stop.is_set():
        try:
            status, reply, _ = post(base + "api/new", {}, timeout=30)
            sid = reply.get("sid") if status == 200 else None
        except OSError:
            time.sleep(0.5)
    k = 0
    while k < n and not stop.is_set():
        try:
            st = get_json(f"{base}s/{sid}/state", timeout=30)
            if st["answered"] >= n or st["question"] is None:
                break
            a = choose(st["question"], k0 + st["answered"])
            status, reply, _ = post(f"{base}s/{sid}/answer", {"qid": st["qid"], "answer": a}, timeout=30)
            if status == 200:
                with lock:
                    acked.setdefault(sid, []).append((st["qid"], a))
                k = reply["answered"]
            else:
                time.sleep(0.2)
        except OSError:  # the server is down: the page retries
            time.sleep(0.5)
        time.sleep(random.uniform(0.5, 1.5))  # the participant "thinks" (as the soak's do)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--participants", type=int, default=40)
    ap.add_argument("--answers", type=int, default=10)
    ap.add_argument("--active", type=int, default=10)
    ap.add_argument("--kills", type=int, default=10)
    ap.add_argument("--arrival", type=float, default=5.0, help="mean seconds between two participants' arrivals")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument(
        "--name", default="study_run", help="the results file's name (study_run_kills for the run with kills)"
    )
    args = ap.parse_args()
    random.seed(args.seed)
    tmp = Path(tempfile.mkdtemp(prefix="torchpref-study-"))
    items = write_items(tmp / "src", n=30, d=3, pictures=False)
    study = tmp / "study"
    srv = Server(
        [str(study), "--features", str(items), "--queries", str(args.answers)], tmp, command=("study", "serve")
    )
    t0, load0 = time.time(), os.getloadavg()[0]
    srv.start()
    acked: dict = {}
    lock, stop = threading.Lock(), threading.Event()
    todo: queue.Queue = queue.Queue()
    for i in range(args.participants):
        todo.put(i)

    arrivals = threading.Lock()
    next_arrival = [time.time()]

    def worker() -> None:
        while not stop.is_set():
            try:
                i = todo.get_nowait()
            except queue.Empty:
                return
            with arrivals:  # participants arrive one after another, --arrival seconds apart on average
                wait = next_arrival[0] - time.time()
                next_arrival[0] = max(next_arrival[0], time.time()) + random.expovariate(1.0 / args.arrival)
            time.sleep(max(0.0, wait))
            participant(srv.url, args.answers, i, acked, lock, stop)

    threads = [threading.Thread(target=worker, daemon=True) for _ in range(args.active)]
    for t in threads:
        t.start()
    kills, loadable, during_refit = 0, [], 0
    deadline = time.time() + 600  # the kills start once a population is in force (so each can break it)
    while time.time() < deadline and not (study / "population" / "current.json").is_file():
        time.sleep(0.5)
    while any(t.is_alive() for t in threads) and kills < args.kills:
        deadline = time.time() + random.uniform(2.0, 8.0)
        while time.time() < deadline and not _refitting(study):  # a kill during a refit where one runs
            time.sleep(0.1)
        time.sleep(random.uniform(0.0, 1.5))  # a random moment of it
        during_refit += _refitting(study)
        srv.kill()
        kills += 1
        loadable.append(_current_loads(study))
        srv.start()
    for t in threads:
        t.join()
    # the last participants' refit: wait until the current population has everyone finished
    deadline = time.time() + 600
    while time.time() < deadline and not _all_fitted(study):
        time.sleep(1)
    loadable.append(_current_loads(study))
    srv.stop()
    problems, answers_in_files = [], 0
    for f in sorted((study / "sessions").glob("*.session.jsonl")):
        sid = f.name.split(".")[0]
        recs = records(f)
        answers_in_files += sum(r["type"] == "answer" for r in recs)
        problems += [f"{sid}: {p}" for p in acknowledged_in_file(acked.get(sid, []), recs)]
    from torchpref.study.export import answer_rows, participant_rows
    from torchpref.study.folder import StudyFolder
    from torchpref.study.report import report

    folder = StudyFolder(study)
    rows = answer_rows(folder)
    events = folder.events()
    finished = sum(r["status"] == "finished" for r in participant_rows(folder))
    refits = sum(e["event"] == "refit" for e in events)
    page = report(folder)
    figures = _report_figures(page)
    result = {
        "participants": args.participants,
        "answers_each": args.answers,
        "acknowledged": sum(len(v) for v in acked.values()),
        "lost": problems,
        "kills": kills,
        "kills_during_refit": during_refit,
        "population_loadable_after_each_kill": loadable,
        "finished": finished,
        "refits": refits,
        "refits_per_5_finished": round(refits / max(1, finished / 5), 2),
        "export_rows": len(rows),
        "answer_records_in_files": answers_in_files,
        "report_figures_shown_in_chromium": figures,
        "seconds": round(time.time() - t0, 1),
        "load_average_start_end": [round(load0, 2), round(os.getloadavg()[0], 2)],
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / f"{args.name}.json", result, measured="harness: benchmarks/durability/study_run.py")
    print(result)
    ok = not problems and all(x in (True, None) for x in loadable) and len(rows) == answers_in_files
    return 0 if ok else 1


def _refitting(study: Path) -> bool:
    """Whether a refit runs now: its worker holds the population's lock while it fits."""
    import fcntl

    lock = study / "population" / ".lock"
    if not lock.exists():
        return False
    with open(lock) as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            return True
        fcntl.flock(fh, fcntl.LOCK_UN)
    return False


def _current_loads(study: Path) -> bool | str | None:
    """Whether the population in force loads (``None``: none yet)."""
    import json

    import torchpref

    current = study / "population" / "current.json"
    if not current.is_file():
        return None
    try:
        torchpref.load_population(study / "population" / json.loads(current.read_text())["file"])
        return True
    except Exception as exc:
        return f"{type(exc).__name__}: {exc}"


def _all_fitted(study: Path) -> bool:
    """Whether the current population was fitted on every finished participant (and no refit runs)."""

    from torchpref.study.export import participant_rows
    from torchpref.study.folder import StudyFolder

    folder = StudyFolder(study)
    finished = {r["participant"] for r in participant_rows(folder) if r["status"] == "finished"}
    pointer = folder.current()
    if pointer is None:
        return False
    fitted = set(pointer.participants)
    return finished <= fitted and not _refitting(study)


def _report_figures(page: Path) -> int | None:
    """How many of the report's figures Chromium shows (``None`` without Chromium / Playwright)."""
    if not os.path.exists(CHROMIUM):
        return None
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return None
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        pg = b.new_page()
        pg.goto(page.as_uri())
        n = pg.evaluate("[...document.images].filter(i => i.complete && i.naturalWidth > 100).length")
        b.close()
    return int(n)


if __name__ == "__main__":
    from torchpref.experiments.stamp import recording_subprocesses

    with recording_subprocesses():  # the stamp hashes the code of every process it starts too
        raise SystemExit(main())
