"""Helpers for the ``torchpref serve`` tests and benchmarks that run the server as a process:
an items CSV with pictures, a server started (and killed) on a free loopback port, Chromium's
path and flags, and a scripted answerer over HTTP that keeps what was acknowledged."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict

if TYPE_CHECKING:
    from starlette.testclient import TestClient
    from torch import Tensor
    from typing_extensions import Unpack

    from torchpref.frontends.serve.items import ServeItems
    from torchpref.frontends.serve.store import SessionStore


class ItemOptions(TypedDict, total=False):
    """:class:`~torchpref.frontends.serve.items.ServeItems`' fields besides the items and names."""

    labels: list[str] | None
    render: Callable[[Tensor, int], object] | None
    noun: str
    metadata: dict
    picture_dir: Path | None


class AppOptions(TypedDict, total=False):
    """:func:`~torchpref.frontends.serve.app.create_app`'s keywords."""

    token: str | None
    allowed_hosts: list[str] | None
    extra_routes: list | None


CHROMIUM = os.environ.get("TORCHPREF_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
START_S = 180  # a loaded machine imports torch, gpytorch and botorch slowly
ROOT = Path(__file__).resolve().parents[2]  # the folder holding the torchpref package


TEST_BASE_URL = "http://127.0.0.1:8000"  # the in-process test client's address (an allowed Host)


def random_items(n: int = 24, d: int = 3, seed: int = 0, **kwargs: Unpack[ItemOptions]) -> ServeItems:
    """``n`` seeded random items in ``[0, 1]^d`` with objectives ``f0, f1, ...`` as
    :class:`~torchpref.frontends.serve.items.ServeItems` (``kwargs``: its other arguments)."""
    import torch

    from torchpref.frontends.serve.items import ServeItems

    g = torch.Generator().manual_seed(seed)
    return ServeItems(torch.rand(n, d, generator=g, dtype=torch.float64), [f"f{k}" for k in range(d)], **kwargs)


def serve_client(store: SessionStore, **kwargs: Unpack[AppOptions]) -> TestClient:
    """Starlette's in-process test client of the page over ``store`` (``kwargs``: ``create_app``'s,
    e.g. ``token``, ``allowed_hosts``), at :data:`TEST_BASE_URL`; needs the ``serve`` extra and httpx."""
    import warnings

    from torchpref.frontends.serve.app import create_app

    with warnings.catch_warnings():  # starlette's note that a later httpx is preferred
        warnings.simplefilter("ignore")
        from starlette.testclient import TestClient

        return TestClient(create_app(store, **kwargs), base_url=TEST_BASE_URL)


def free_port() -> int:
    """A loopback port free now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_items(folder: Path, n: int = 40, d: int = 3, seed: int = 0, pictures: bool = True) -> Path:
    """``folder/items.csv``: ``n`` items, ``d`` objectives in [0, 1] from a seeded generator, a
    name column and (``pictures``) a column naming a small PNG bar chart of each item."""
    import torch

    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, d, generator=g, dtype=torch.float64)
    folder.mkdir(parents=True, exist_ok=True)
    names = ["speed", "comfort", "price", "range", "noise"][:d] + [f"x{k}" for k in range(5, d)]
    head = ["name", *names] + (["picture"] if pictures else [])
    lines = [",".join(head)]
    if pictures:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        (folder / "images").mkdir(exist_ok=True)
    for i in range(n):
        row = [f"option {i + 1}", *(f"{float(v):.4f}" for v in X[i])]
        if pictures:
            fig = Figure(figsize=(2.4, 1.6), dpi=60)
            FigureCanvasAgg(fig)
            ax = fig.add_subplot()
            ax.bar(range(d), X[i].tolist(), color=["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd"][:d])
            ax.set_ylim(0, 1)
            ax.set_xticks(range(d), names, fontsize=7)
            fig.tight_layout()
            fig.savefig(folder / "images" / f"item{i}.png")
            row.append(f"images/item{i}.png")
        lines.append(",".join(row))
    path = folder / "items.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


class Server:
    """``torchpref serve`` as a child process on a fixed free port; :meth:`kill` sends SIGKILL,
    :meth:`start` starts it again on the same port and folder."""

    def __init__(self, args: list[str], folder: Path, port: int | None = None, command: tuple[str, ...] = ("serve",)):
        self.args, self.folder, self.command = args, folder, command
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}/"
        self.proc: subprocess.Popen | None = None
        self.starts = 0

    def start(self) -> None:
        """Start the server process and wait until it answers."""
        env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}", MPLBACKEND="Agg")
        log = open(self.folder / f"server-{self.starts}.log", "w")
        cmd = [sys.executable, "-m", "torchpref.cli", *self.command, *self.args, "--port", str(self.port)]
        self.proc = subprocess.Popen(cmd, cwd=self.folder, env=env, stdout=log, stderr=subprocess.STDOUT)
        log.close()
        self.starts += 1
        deadline = time.monotonic() + START_S
        while True:
            try:
                with urllib.request.urlopen(self.url, timeout=5) as r:
                    if r.status == 200:
                        return
            except (OSError, urllib.error.URLError):
                pass
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the server did not start:\n{self.log()[-3000:]}")
            time.sleep(0.2)

    def log(self) -> str:
        """What the server process printed so far."""
        return "\n".join(p.read_text() for p in sorted(self.folder.glob("server-*.log")))

    def kill(self) -> None:
        """SIGKILL the server process and wait for it."""
        if self.proc is not None and self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=30)

    def stop(self) -> None:
        """Stop the server process (SIGINT, then SIGKILL if it lingers)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.kill()


def post(url: str, body: dict, timeout: float = 60) -> tuple[int, dict, dict]:
    """``(status, JSON reply, headers)`` of a same-origin JSON POST."""
    req = urllib.request.Request(
        url, data=json.dumps(body).encode(), headers={"Content-Type": "application/json"}, method="POST"
    )
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, json.loads(r.read()), dict(r.headers)
    except urllib.error.HTTPError as err:
        return err.code, json.loads(err.read() or b"{}"), dict(err.headers)


def get_json(url: str, timeout: float = 60) -> dict:
    """``GET url`` as JSON."""
    with urllib.request.urlopen(url, timeout=timeout) as r:
        return json.loads(r.read())


def records(path: Path) -> list[dict]:
    """The JSON records of a session file (header first)."""
    return [json.loads(line) for line in path.read_text().splitlines()[1:] if line.strip()]


def choose(question: dict, k: int) -> int | None:
    """A deterministic, varied answer to question ``k``: levels cycle, choices cycle, a tie now and then."""
    if question["kind"] == "rating":
        return 1 + (k * 3) % question["levels"]
    if question.get("ties") and k % 7 == 3:
        return None
    return k % len(question["options"])


def acknowledged_in_file(acked: list[tuple[str, object]], recs: list[dict]) -> list[str]:
    """The problems (none: an empty list) with acknowledged answers ``[(qid, answer), ...]``
    against a session file's records: each must be the answer record at its question's position,
    with that answer, and still in force."""
    from torchpref.sessions.records import records_in_force

    active = {r["seq"] for r in records_in_force(recs)}
    problems = []
    for qid, answer in acked:
        p = int(qid.split(".")[0])
        rec = recs[p] if p < len(recs) else None
        if rec is None or rec["type"] != "answer" or rec["answer"] != answer or rec["seq"] not in active:
            problems.append(f"{qid} ({answer!r}): {rec!r:.200}")
    return problems


def _retried(url: str, body: dict) -> dict:
    """The reply to ``body`` sent again until the restarted server answers (bounded, as the page's)."""
    for _ in range(100):
        try:
            status, data, _ = post(url, body)
        except OSError:
            time.sleep(0.2)
            continue
        break
    assert status == 200, data
    return data


def _killed_in_flight(srv: Server, url: str, body: dict, delay: float) -> list:
    """Send ``body`` and SIGKILL the server ``delay`` seconds later, then start it again; returns
    ``[reply]`` or ``[the exception]`` of the answer in flight."""
    import threading

    result: list = []

    def send() -> None:
        try:
            result.append(post(url, body, timeout=30))
        except OSError as exc:  # the connection died with the server
            result.append(exc)

    t = threading.Thread(target=send)
    t.start()
    time.sleep(delay)
    srv.kill()
    t.join(timeout=60)
    srv.start()
    return result


def kill_run(folder: Path, kills: int = 20, seed: int = 0, progress: Callable[[int], object] | None = None) -> dict:
    """Answer a session over HTTP while the server is killed (SIGKILL) ``kills`` times, each time
    with an answer in flight after a random delay, and restarted; an answer whose reply was lost
    is sent again (as the page does). Returns what happened and the problems with acknowledged
    answers (:func:`acknowledged_in_file`: none expected)."""
    import random

    rng = random.Random(seed)
    items = write_items(folder, n=40, d=3, seed=seed, pictures=False)
    srv = Server(["--features", str(items), "--sessions", "sessions", "--queries", "500"], folder)
    srv.start()
    acked: list[tuple[str, object]] = []
    outcome = {"acknowledged before the kill": 0, "already recorded on retry": 0, "recorded on retry": 0}
    delays = []
    try:
        sid = post(srv.url + "api/new", {})[1]["sid"]
        base = f"{srv.url}s/{sid}/"
        k = 0

        def body_for() -> tuple[dict, object]:
            st = get_json(base + "state")
            a = choose(st["question"], k)
            return {"qid": st["qid"], "answer": a, "response_time": 0.1 * (k % 30)}, a

        for n in range(kills):
            for _ in range(rng.randint(1, 2)):  # answers between kills
                body, a = body_for()
                status, _, _ = post(base + "answer", body)
                assert status == 200
                acked.append((body["qid"], a))
                k += 1
            body, a = body_for()
            delays.append(rng.uniform(0.0, 0.3))
            result = _killed_in_flight(srv, base + "answer", body, delays[-1])
            if result and isinstance(result[0], tuple) and result[0][0] == 200:
                outcome["acknowledged before the kill"] += 1
            else:
                data = _retried(base + "answer", body)
                outcome["already recorded on retry" if data.get("duplicate") else "recorded on retry"] += 1
            acked.append((body["qid"], a))
            k += 1
            if progress is not None:
                progress(n + 1)
    finally:
        srv.stop()
    path = folder / "sessions" / f"{sid}.session.jsonl"
    recs = records(path)
    return {
        "kills": kills,
        "acknowledged": len(acked),
        "answers_in_file": sum(r["type"] == "answer" for r in recs),
        "lost": acknowledged_in_file(acked, recs),
        "outcomes": outcome,
        "partial_lines_repaired": Path(str(path) + ".dropped").exists(),
        "kill_delays_s": delays,
        "server_starts": srv.starts,
    }
