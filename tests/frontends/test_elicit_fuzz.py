"""A terminal fuzz test: ``torchpref elicit`` driven through a pseudo-terminal (pexpect) with
damaged files and hostile keystrokes must never print a traceback and never lose an answer it
acknowledged (an answer is acknowledged when the next prompt appears).

``TORCHPREF_FUZZ_RUNS`` sets the number of keystroke sessions (default 2, each two processes).
The damaged files go through the command line in-process here, and through the terminal in the
``slow`` test.
"""

import io
import json
import os
import random
import re
import signal
import sys
import time
from pathlib import Path

import pytest

pexpect = pytest.importorskip("pexpect")

from torchpref.sessions.records import records_in_force  # noqa: E402
from torchpref.sessions.session import read_session_file  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
CSV = "name,cost,comfort\ncar,30,8\nbike,2,4\nbus,5,5\ntrain,12,7\n\x1b[31mwalk\x1b[0m,0,3\ntaxi,40,9\n"
PROMPT = r"(Your rating \[1-5|Which is best\? \[A-([A-Z]))[^\]]*\]: "
HOSTILE = [
    "",
    " ",
    "0",
    "6",
    "4.5",
    "-1",
    "²",
    "①",
    "٣",
    "五",
    "Z",
    "AB",
    "a b",
    "\x1b[A",
    "\x1b[2J",
    "\t",
    "=" * 3,
    "x" * 3000,
    "💥",
    "None",
    "true",
    "1e1",
    "3.0",
    "?",
    "h",
]


def spawn(*args, timeout=120):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    child = pexpect.spawn(
        sys.executable,
        ["-m", "torchpref.cli", "elicit", *map(str, args)],
        cwd=str(REPO),
        encoding="utf-8",
        timeout=timeout,
        dimensions=(50, 200),
        env=env,
    )
    child.logfile_read = io.StringIO()  # everything it printed
    return child


def finish(child) -> str:
    """Wait for the end; everything the child printed."""
    child.expect(pexpect.EOF)
    child.close()
    return child.logfile_read.getvalue()


def no_traceback(child, text: str) -> None:
    assert "Traceback" not in text and "Error:" not in text.replace("SessionFileError", ""), text[-3000:]


def answers_in_file(path) -> list:
    _, records, _ = read_session_file(path)
    return [r["answer"] for r in records_in_force(records)]


def drive(child, rng: random.Random, acked: list, max_steps: int = 40) -> str:
    """Answer queries with hostile keystrokes mixed in; ``acked`` is kept as the answers in force.
    Ends with q, Ctrl-C, end of input, or the last query; returns how it ended."""
    pending = None  # the answer sent, until the next prompt acknowledges it
    log = ""
    for _ in range(max_steps):
        i = child.expect([PROMPT, r"Thank you: \d+ answers?\.", r"Undid your answer", r"Nothing to undo"])
        log += child.before + child.after
        if i == 2:
            acked.pop()
            continue
        if i == 3:
            continue
        if pending is not None and "could not be used" not in child.before:
            acked.append(pending[1])
        pending = None
        if i == 1:
            return "done"
        ranking = child.match.group(2) is not None
        m = "ABCDEFGHIJKLMNOPQRSTUVWXYZ".index(child.match.group(2)) + 1 if ranking else 0
        roll = rng.random()
        if roll < 0.35:
            child.sendline(rng.choice(HOSTILE))
        elif roll < 0.42 and acked:
            child.sendline("u")
        elif roll < 0.46:
            child.sendline("q")
            return "quit"
        elif roll < 0.50:
            child.sendcontrol("c")
            return "interrupt"
        elif roll < 0.52:
            child.sendeof()
            return "eof"
        elif ranking:
            k = rng.randrange(m + 1)
            child.sendline("=" if k == m else "abcdefghij"[k] if rng.random() < 0.5 else "ABCDEFGHIJ"[k])
            pending = ("answer", None if k == m else k)
        else:
            level = rng.randint(1, 5)
            child.sendline(str(level))
            pending = ("answer", level)
    child.sendline("q")
    return "quit"


@pytest.mark.slow  # a long loop (27-38 s here): make test-slow, which CI runs
@pytest.mark.parametrize("run", range(int(os.environ.get("TORCHPREF_FUZZ_RUNS", "2"))))
def test_hostile_keystrokes_lose_nothing(tmp_path, run):
    rng = random.Random(1000 + run)
    items, session = tmp_path / "items.csv", tmp_path / "s.jsonl"
    items.write_text(CSV)
    acked: list = []
    for attempt in range(2):  # a second run resumes the first one's file
        child = spawn("--features", items, "--session", session, "--queries", 8, "--seed", run)
        if attempt == 1:
            child.expect(r"resuming with \d+ answers?|a new session")
        how = drive(child, rng, acked)
        text = finish(child)
        no_traceback(child, text)
        assert "\x1b[31m" not in text  # the label's escape sequence is not printed raw
        if how == "interrupt":
            assert child.exitstatus == 130 or child.signalstatus is not None
        else:
            assert child.exitstatus == 0, text[-2000:]
        assert answers_in_file(session) == acked, (how, text[-2000:])
        if how == "done":
            break


def test_ctrl_c_during_start_up(tmp_path):
    items = tmp_path / "items.csv"
    items.write_text(CSV)
    for delay in (0.5, 2.0):
        child = spawn("--features", items, "--session", tmp_path / "s.jsonl")
        child.expect([pexpect.TIMEOUT, PROMPT], timeout=delay)
        child.sendcontrol("c")
        text = finish(child)
        no_traceback(child, text)
        assert child.exitstatus in (0, 130) or child.signalstatus is not None, text


def damaged_files(tmp_path, valid: bytes) -> dict:
    """Session files damaged in ways a person, an editor or a crash could."""
    lines = valid.splitlines(keepends=True)
    header = json.loads(lines[0])
    no_bounds = dict(header)
    del no_bounds["bounds"]
    answer = json.loads(lines[1])
    bad = {
        "partial last line": valid[:-15],
        "garbage in the middle": lines[0] + b"{not json\n" + b"".join(lines[1:]),
        "header without bounds": (json.dumps(no_bounds) + "\n").encode() + b"".join(lines[1:]),
        "seed as text": (json.dumps(dict(header, seed="0")) + "\n").encode() + b"".join(lines[1:]),
        "answer as text": lines[0] + (json.dumps(dict(answer, answer=str(answer["answer"]))) + "\n").encode(),
        "deeply nested": valid + b"[" * 50_000 + b"]" * 50_000 + b"\n",
        "binary": b"\x00\xff\xfe" * 100,
        "empty header object": b"{}\n",
        "a list": b"[1, 2, 3]\n",
    }
    return {name: data for name, data in bad.items()}


def good_session(tmp_path) -> tuple[Path, Path, list]:
    """A CSV and a session file with two answers in force, written through the terminal."""
    items, good = tmp_path / "items.csv", tmp_path / "good.jsonl"
    items.write_text(CSV)
    child = spawn("--features", items, "--session", good, "--queries", 4)
    acked: list = []
    while len(acked) < 2:
        child.expect(PROMPT)
        ranking = child.match.group(2) is not None
        child.sendline("A" if ranking else "3")
        acked.append(0 if ranking else 3)
    child.expect(PROMPT)
    child.sendline("q")
    no_traceback(child, finish(child))
    assert answers_in_file(good) == acked
    return items, good, acked


def test_damaged_session_files_are_one_line_errors(tmp_path, monkeypatch, capsys):
    from torchpref.cli import main

    items, good, _ = good_session(tmp_path)
    for name, data in damaged_files(tmp_path, good.read_bytes()).items():
        path = tmp_path / f"{re.sub(r'[^a-z]+', '-', name)}.jsonl"
        path.write_bytes(data)
        for reply in ("n\n", "y\nq\n"):  # refuse, or accept, a repair where one is offered
            path.write_bytes(data)
            monkeypatch.setattr(sys, "stdin", io.StringIO(reply))
            code = main(["elicit", "--features", str(items), "--session", str(path), "--queries", "4"])
            out, err = capsys.readouterr()
            assert "Traceback" not in out + err
            if "Repair the file now" in out:
                assert code == (0 if reply.startswith("y") else 2), (name, out, err)
            else:
                assert code == 2 and len(err.strip().splitlines()) == 1 and err.startswith("torchpref elicit: "), (
                    name,
                    err,
                )
    code = main(["elicit", "--features", str(items), "--session", str(tmp_path)])
    assert code == 2 and "is a directory" in capsys.readouterr().err


@pytest.mark.slow
def test_damaged_session_files_through_the_terminal(tmp_path):
    items, good, _ = good_session(tmp_path)
    rng = random.Random(7)
    for name, data in damaged_files(tmp_path, good.read_bytes()).items():
        path = tmp_path / f"{re.sub(r'[^a-z]+', '-', name)}.jsonl"
        path.write_bytes(data)
        child = spawn("--features", items, "--session", path, "--queries", 4)
        i = child.expect([r"Repair the file now.*\]: ", pexpect.EOF, PROMPT])
        if i == 0:  # only a crash-like last line is offered a repair
            child.sendline(rng.choice(["n", "y"]))
            i = child.expect([pexpect.EOF, PROMPT])
            if i == 1:
                child.sendline("q")
                child.expect(pexpect.EOF)
        elif i == 2:
            child.sendline("q")
            child.expect(pexpect.EOF)
        child.close()
        text = child.logfile_read.getvalue()
        no_traceback(child, text)
        assert child.exitstatus in (0, 2), (name, text)
    child = spawn("--features", items, "--session", tmp_path)  # a directory
    text = finish(child)
    no_traceback(child, text)
    assert "is a directory" in text and child.exitstatus == 2


# ------------------------------------------------------------------ a kill of the terminal front end
@pytest.mark.slow  # SIGKILLs (51 s here at load 6-8): make test-slow, which CI runs
def test_sigkill_of_torchpref_elicit_loses_no_acknowledged_answer(tmp_path):
    items, session = tmp_path / "items.csv", tmp_path / "s.jsonl"
    items.write_text(CSV)
    rng = random.Random(7)
    acked: list = []  # answers acknowledged by the next prompt
    repairs = 0
    for run in range(5):
        child = spawn("--features", items, "--session", session, "--queries", 30)
        if child.expect([PROMPT, "Repair the file now"]) == 1:
            repairs += 1
            child.sendline("y")
            child.expect(PROMPT)
        in_file = answers_in_file(session) if session.exists() else []
        # every acknowledged answer is there; the one in flight at the kill is there or not, whole
        assert in_file[: len(acked)] == acked and len(in_file) <= len(acked) + 1, (run, in_file, acked)
        acked = in_file
        for k in range(rng.randint(1, 3) + 1):
            answer = 0 if child.match.group(2) is not None else 3
            child.sendline("A" if answer == 0 else "3")
            if k == 0 and run % 2:  # kill right after the keystroke: inside tell or its write
                time.sleep(rng.uniform(0.0, 0.05))
                break
            child.expect(PROMPT)
            acked.append(answer)
        child.kill(signal.SIGKILL)
        child.close(force=True)
    final = answers_in_file(session)
    assert final[: len(acked)] == acked and len(final) <= len(acked) + 1 and len(final) >= 5
