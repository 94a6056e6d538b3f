r"""A soak run of ``torchpref serve`` as a study uses it: many participants, a few at a time, then a
kill and a restart. It records the server's memory, open files and time per answer over the run.

``--sessions`` participants (60) answer ``--answers`` questions each (20), ``--active`` (10) at a
time: scripted clients over HTTP that, like the page, show each question (from the last answer's
reply) and fetch its pictures,
"think" for a seeded random 0.5-1.5 x ``--think`` seconds, send the answer, and at the end load the
summary page and its plot (drawn by the server's plot worker while the others go on answering).
A sampler reads the server's RSS, its open descriptors and how many of them are session files
(``/proc``), and the plot worker's RSS, every ``--every`` seconds.

Then ``--partial`` (10) more sessions are answered part-way, every session's state (answers and
next question) is kept, and the server is killed (SIGKILL) and restarted with sessions kept open
(``--idle-close/--finished-close 3600``), so that reopening every session measures the memory per
open session; every session must come back with the same answers and next question, and every
acknowledged answer must be in its file (0 lost).

Each answer's server time and the CPU the server's thread spent on it (the answer and the next
question: the ``Server-Timing`` header's ``answer`` and ``cpu``) are kept, with their p50 / p95 /
p99. The run is inside :func:`~torchpref.experiments.stamp.recording_subprocesses`: the server
processes record the torchpref modules they ran, so the stamp of ``soak.json`` hashes the server's
code, not only this script's.

Writes ``results/serve/soak.json`` (settings, load average, CPU count, the summary), ``soak_answers.csv``
(one row per answer), ``soak_samples.csv`` (the time series) and ``soak.png``.

Usage (Linux: it reads ``/proc``)::

    nice -n 10 .venv/bin/python benchmarks/durability/soak.py [--sessions 60] [--answers 20] [--active 10]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import queue
import random
import signal
import statistics
import subprocess
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

HERE = Path(__file__).resolve().parent
from torchpref.experiments.results import write_json  # noqa: E402
from torchpref.experiments.stamp import recording_subprocesses  # noqa: E402
from torchpref.testing.serve import Server, acknowledged_in_file, choose, get_json, post, records, write_items  # noqa: E402


# ------------------------------------------------------------------ the server from outside
def rss_kb(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:"))


def descriptors(pid: int) -> tuple[int, int]:
    """``(open descriptors, of which session files)`` of process ``pid``."""
    fds = os.listdir(f"/proc/{pid}/fd")
    files = 0
    for fd in fds:
        try:
            files += os.readlink(f"/proc/{pid}/fd/{fd}").endswith(".session.jsonl")
        except OSError:
            pass
    return len(fds), files


def children(pid: int) -> list[int]:
    """The child processes of ``pid`` (started by any of its threads)."""
    out = []
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{task}/children") as f:
                out += [int(p) for p in f.read().split()]
        except OSError:
            pass
    return out


def cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class Sampler(threading.Thread):
    """The server's RSS, descriptors, session files and the plot worker's RSS every ``every`` s."""

    def __init__(self, pid: int, t0: float, every: float, progress: dict):
        super().__init__(daemon=True)
        self.pid, self.t0, self.every, self.progress = pid, t0, every, progress
        self.rows: list[dict] = []
        self.stop = threading.Event()

    def sample(self, phase: str) -> dict:
        fds, files = descriptors(self.pid)
        workers = [rss_kb(c) for c in children(self.pid)]
        row = {
            "t": round(time.monotonic() - self.t0, 3),
            "phase": phase,
            "rss_kb": rss_kb(self.pid),
            "fds": fds,
            "session_files": files,
            "worker_rss_kb": sum(workers),
            "active": self.progress["active"],
            "finished": self.progress["finished"],
            "load1": os.getloadavg()[0],
        }
        self.rows.append(row)
        return row

    def run(self) -> None:
        while not self.stop.wait(self.every):
            try:
                self.sample(self.progress["phase"])
            except (OSError, StopIteration):
                return


# ------------------------------------------------------------------------- participants
def server_timing(headers: dict) -> dict[str, float]:
    """The ``Server-Timing`` header's metrics in ms: ``answer`` (the answer's wall time in the
    server) and ``cpu`` (the CPU its thread spent on the answer and the next question)."""
    timing = {k.lower(): v for k, v in headers.items()}.get("server-timing", "")
    out = {}
    for part in timing.split(","):
        name, _, dur = part.strip().partition(";dur=")
        if dur:
            out[name] = float(dur)
    return out


def fetch(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=300) as r:
        return r.read()


def participant(srv: Server, job: dict, rng: random.Random, think: float, ctx: dict) -> None:
    """One participant: a new session, ``job["answers"]`` answers, then (if all) the summary."""
    status, data, _ = post(srv.url + "api/new", {})
    assert status == 200, data
    sid, base = data["sid"], f"{srv.url}s/{data['sid']}/"
    job["sid"], acked = sid, []
    st = get_json(base + "state")  # then, as the page, the next question from each answer's reply
    for k in range(job["answers"]):
        for o in st["question"]["options"]:
            if o["picture"]:
                fetch(srv.url + f"picture/{o['index']}")
        time.sleep(think * rng.uniform(0.5, 1.5))
        a = choose(st["question"], k)
        t = time.monotonic()
        status, reply, headers = post(base + "answer", {"qid": st["qid"], "answer": a, "response_time": 1.0})
        t1 = time.monotonic()
        assert status == 200, reply
        acked.append((st["qid"], a))
        st = reply
        ctx["answers"].append(
            {
                "session": job["n"],
                "answer": k,
                "start_s": round(t - ctx["t0"], 4),
                "end_s": round(t1 - ctx["t0"], 4),
                "server_ms": server_timing(headers).get("answer"),
                "cpu_ms": server_timing(headers).get("cpu"),
                "client_ms": round(1000 * (t1 - t), 2),
                "load1": os.getloadavg()[0],
            }
        )
        ctx["bar"].update(1)
    job["acked"], job["done_s"] = acked, time.monotonic() - ctx["t0"]
    if job["answers"] == ctx["full"]:
        fetch(base + "summary")
        png = fetch(base + "utility.png")
        assert png.startswith(b"\x89PNG")
        job["plot_s"] = (job["done_s"], time.monotonic() - ctx["t0"])  # drawn from the last answer to here


def run_wave(srv: Server, jobs: list[dict], active: int, think: float, seed: int, ctx: dict, progress: dict) -> None:
    """The jobs, ``active`` at a time."""
    todo: queue.Queue = queue.Queue()
    for job in jobs:
        todo.put(job)
    errors: list[BaseException] = []

    def client(c: int) -> None:
        rng = random.Random(seed * 1000 + c)
        while not errors:
            try:
                job = todo.get_nowait()
            except queue.Empty:
                return
            progress["active"] += 1
            try:
                participant(srv, job, rng, think, ctx)
            except BaseException as exc:
                errors.append(exc)
            finally:
                progress["active"] -= 1
                progress["finished"] += job["answers"] == ctx["full"]

    threads = [threading.Thread(target=client, args=(c,)) for c in range(active)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]


def interrupt(srv: Server, wait: float = 60.0) -> None:
    """Stop the server as Ctrl-C does (SIGINT), so that it exits through Python's ``atexit``: it
    then records the modules it ran (:func:`recording_subprocesses`; a SIGTERM or SIGKILL would
    not). One that lingers is left to ``srv.stop()``."""
    if srv.proc is not None and srv.proc.poll() is None:
        srv.proc.send_signal(signal.SIGINT)
        try:
            srv.proc.wait(timeout=wait)
        except subprocess.TimeoutExpired:
            pass


# ------------------------------------------------------------------------------ the run
def overlapping(answers: list[dict], jobs: list[dict]) -> None:
    """Mark each answer that overlaps a summary plot being drawn (from a session's last answer
    to the end of its ``utility.png``)."""
    spans = [j["plot_s"] for j in jobs if "plot_s" in j]
    for a in answers:
        a["during_plot"] = any(s < a["end_s"] and a["start_s"] < e for s, e in spans)


def slope(xs: list[float], ys: list[float]) -> float:
    mx, my = statistics.fmean(xs), statistics.fmean(ys)
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sum((x - mx) ** 2 for x in xs)


def pct(values: list[float], q: float) -> float:
    v = sorted(values)
    return round(v[min(len(v) - 1, int(q * len(v)))], 2)


def restart_check(srv: Server, jobs: list[dict], sampler: Sampler, progress: dict, folder: Path) -> dict:
    """Kill, restart with sessions kept open, reopen each: same answers and next question?"""
    before = {j["sid"]: get_json(f"{srv.url}s/{j['sid']}/state") for j in jobs}
    srv.kill()
    srv.args += ["--idle-close", "3600", "--finished-close", "3600"]
    srv.start()
    progress["phase"] = "restart"
    sampler.pid = srv.proc.pid
    base = sampler.sample("restart")
    reopened, mismatched = [], []
    for j in jobs:
        after = get_json(f"{srv.url}s/{j['sid']}/state")
        keys = ("qid", "answered", "done", "question", "recommended")
        if any(after[k] != before[j["sid"]][k] for k in keys):
            mismatched.append(j["sid"])
        reopened.append(sampler.sample("restart"))
    lost = []
    for j in jobs:
        lost += acknowledged_in_file(j["acked"], records(folder / "sessions" / f"{j['sid']}.session.jsonl"))
    xs = list(range(1, len(reopened) + 1))
    return {
        "sessions_reopened": len(jobs),
        "mismatched_after_restart": mismatched,
        "acknowledged_answers": sum(len(j["acked"]) for j in jobs),
        "lost_answers": len(lost),
        "lost_detail": lost[:10],
        "rss_kb_after_restart": base["rss_kb"],
        "open_session_kb_slope": round(slope(xs, [r["rss_kb"] for r in reopened]), 1),
        "session_files_after_reopening_all": reopened[-1]["session_files"],
        "fds_after_reopening_all": reopened[-1]["fds"],
    }


def summarise(args, answers: list[dict], samples: list[dict], jobs: list[dict], wall: float, cpu: float) -> dict:
    full = [j for j in jobs if j["answers"] == args.answers]
    run_rows = [s for s in samples if s["phase"] == "run"]
    # RSS against sessions finished, after the first 10 (imports, first plots, caches filling)
    pts = [(s["finished"], s["rss_kb"]) for s in run_rows if s["finished"] >= min(10, len(full) // 2)]
    late = [p for p in pts if p[0] >= len(full) // 2]
    ms = [a["server_ms"] for a in answers if a["server_ms"] is not None]
    cpu_ms = [a["cpu_ms"] for a in answers if a["cpu_ms"] is not None]
    during = [a["server_ms"] for a in answers if a["during_plot"]]
    other = [a["server_ms"] for a in answers if not a["during_plot"]]
    return {
        "answers_acknowledged_in_run": len(ms),
        "wall_s": round(wall, 1),
        "sessions_per_hour_in_run": round(3600 * len(full) / wall, 1),
        "server_cpu_s_per_answer": round(cpu / max(1, len(ms)), 4),
        "participants_per_hour_cpu_bound": round(3600 / (args.answers * cpu / max(1, len(ms))), 0),
        "answer_ms_p50_p95_p99": [pct(ms, 0.5), pct(ms, 0.95), pct(ms, 0.99)],
        "answer_cpu_ms_p50_p95_p99_max": [pct(cpu_ms, 0.5), pct(cpu_ms, 0.95), pct(cpu_ms, 0.99), max(cpu_ms)]
        if cpu_ms
        else None,
        "answer_ms_during_plots_p50_p95_p99_n": [pct(during, 0.5), pct(during, 0.95), pct(during, 0.99), len(during)]
        if during
        else None,
        "answer_ms_other_p50_p95_p99": [pct(other, 0.5), pct(other, 0.95), pct(other, 0.99)] if other else None,
        "finished_session_kb_slope": round(slope([p[0] for p in pts], [p[1] for p in pts]), 1)
        if len(pts) > 2
        else None,
        "finished_session_kb_slope_second_half": round(slope([p[0] for p in late], [p[1] for p in late]), 1)
        if len(late) > 2
        else None,
        "rss_kb_first_last_max": [run_rows[0]["rss_kb"], run_rows[-1]["rss_kb"], max(s["rss_kb"] for s in run_rows)],
        "worker_rss_kb_max": max(s["worker_rss_kb"] for s in samples),
        "session_files_max_in_run": max(s["session_files"] for s in run_rows),
        "active_max": max(s["active"] for s in run_rows),
        "max_of_session_files_minus_active": max(s["session_files"] - s["active"] for s in run_rows),
        "fds_first_max": [run_rows[0]["fds"], max(s["fds"] for s in run_rows)],
    }


def figure(path: Path, answers: list[dict], samples: list[dict], res: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(9, 9.5), sharex=True)
    t = [s["t"] for s in samples]
    ax = axes[0]
    ax.plot(t, [s["rss_kb"] / 1024 for s in samples], label="server RSS")
    ax.plot(t, [s["worker_rss_kb"] / 1024 for s in samples], label="plot worker RSS")
    ax.set_ylabel("MB")
    ax2 = ax.twinx()
    ax2.plot(t, [s["finished"] for s in samples], color="grey", ls=":", label="sessions finished")
    ax2.set_ylabel("sessions finished")
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title(
        f"serve soak: {res['settings']['sessions']} sessions x {res['settings']['answers']} answers, "
        f"{res['settings']['active']} at a time; SIGKILL + restart at the dashed line"
    )
    ax = axes[1]
    ax.plot(t, [s["fds"] for s in samples], label="open descriptors")
    ax.plot(t, [s["session_files"] for s in samples], label="open session files")
    ax.plot(t, [s["active"] for s in samples], ls="--", label="participants answering")
    ax.set_ylabel("count")
    ax.legend(loc="upper left", fontsize=8)
    ax = axes[2]
    for flag, colour, label in ((False, "#1f77b4", "answer"), (True, "#d62728", "answer during a summary plot")):
        pts = [(a["end_s"], a["server_ms"]) for a in answers if a["during_plot"] == flag]
        ax.scatter([p[0] for p in pts], [p[1] for p in pts], s=6, c=colour, label=label)
    ax.axhline(150, color="k", lw=0.8, ls=":", label="150 ms")
    ax.set_yscale("log")
    ax.set_ylabel("server ms per answer")
    ax.set_xlabel("seconds since start")
    ax.legend(loc="upper left", fontsize=8)
    kill = next((s["t"] for s in samples if s["phase"] == "restart"), None)
    for a in axes:
        if kill is not None:
            a.axvline(kill, color="k", ls="--", lw=0.8)
    fig.text(0.01, 0.005, f"load average {res['load_average']}; {res['cpu_count']} CPUs", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write(out: Path, res: dict, answers: list[dict], samples: list[dict]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    write_json((out / "soak.json"), res, measured="user")
    for name, rows in (("soak_answers.csv", answers), ("soak_samples.csv", samples)):
        if rows:
            with open(out / name, "w", newline="") as f:
                w = csv.DictWriter(f, fieldnames=list(rows[0]))
                w.writeheader()
                w.writerows(rows)


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sessions", type=int, default=60)
    ap.add_argument("--answers", type=int, default=20)
    ap.add_argument("--active", type=int, default=10)
    ap.add_argument("--partial", type=int, default=10)
    ap.add_argument("--think", type=float, default=1.0, help="mean seconds between question and answer")
    ap.add_argument("--items", type=int, default=100)
    ap.add_argument("--dim", type=int, default=3)
    ap.add_argument("--every", type=float, default=0.5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-open", type=int, default=None, help="the server's --max-open (default: its own)")
    ap.add_argument("--out", default=str(HERE.parent / "results" / "serve"))
    return ap.parse_args()


def main() -> None:
    args = parse_args()
    # the server processes record the torchpref modules they ran (when they exit), and the stamp
    # written inside hashes them: the result names the server code it measured
    with recording_subprocesses():
        soak(args)


def soak(args: argparse.Namespace) -> None:
    """The run, its results written (inside :func:`recording_subprocesses`, by :func:`main`)."""
    from tqdm import tqdm

    load0 = os.getloadavg()
    rng = random.Random(args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        items = write_items(folder, n=args.items, d=args.dim, seed=args.seed, pictures=True)
        extra = [] if args.max_open is None else ["--max-open", str(args.max_open)]
        srv = Server(["--features", str(items), "--image-column", "picture", "--sessions", "sessions",
                      "--queries", str(args.answers), *extra], folder)  # fmt: skip
        srv.start()
        progress = {"active": 0, "finished": 0, "phase": "run"}
        t0 = time.monotonic()
        sampler = Sampler(srv.proc.pid, t0, args.every, progress)
        sampler.start()
        jobs = [{"n": n, "answers": args.answers} for n in range(args.sessions)]
        total = args.sessions * args.answers
        partial = [{"n": args.sessions + n, "answers": rng.randint(1, args.answers - 1)} for n in range(args.partial)]
        try:
            with tqdm(total=total + sum(j["answers"] for j in partial), desc="answers", unit="answer") as bar:
                ctx = {"answers": [], "t0": t0, "bar": bar, "full": args.answers}
                cpu0 = cpu_seconds(srv.proc.pid)
                run_wave(srv, jobs, args.active, args.think, args.seed, ctx, progress)
                cpu = cpu_seconds(srv.proc.pid) - cpu0
                wall = time.monotonic() - t0
                time.sleep(5)  # finished_close (1 s) and a sweep: what is left open after the run
                progress["phase"] = "after run"
                after = sampler.sample("after run")
                progress["phase"] = "partial"
                run_wave(srv, partial, args.active, 0.0, args.seed + 1, ctx, progress)
            restart = restart_check(srv, jobs + partial, sampler, progress, folder)
        finally:
            sampler.stop.set()
            interrupt(srv)
            srv.stop()
            if srv.proc is not None and srv.proc.poll() is None:
                os.kill(srv.proc.pid, signal.SIGKILL)
    answers = [a for a in ctx["answers"] if a["session"] < args.sessions]
    overlapping(answers, jobs)
    res = {
        "settings": vars(args),
        "load_average": [round(x, 2) for x in (*load0, *os.getloadavg())],
        "load_average_note": "1/5/15-minute averages before the run, then after it",
        "cpu_count": os.cpu_count(),
        "summary": summarise(args, answers, sampler.rows, jobs, wall, cpu),
        "after_run": after,
        "restart": restart,
    }
    write(Path(args.out), res, answers, sampler.rows)
    figure(Path(args.out) / "soak.png", answers, sampler.rows, res)
    print(json.dumps({k: res[k] for k in ("summary", "after_run", "restart", "load_average")}, indent=1))


if __name__ == "__main__":
    main()
