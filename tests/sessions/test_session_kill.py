"""Kill a session process (SIGKILL) at random moments during 50 answers, restart it from its file
each time, and check that nothing is lost or doubled and the posterior is the uninterrupted one.

Writes are slowed (half a record, a pause, the rest) so that kills can land mid-write; two of the
kills wait for a write to start, so the partial-line path is always exercised: the restarted
process must detect it, report it, repair it, and ask that question again.

Also killed: a process half-way through writing an undo (the undo is dropped on repair, every
answer stays in force), one half-way through ``save_model`` (the file holds the last complete
checkpoint), and ``torchpref elicit`` in a terminal (no acknowledged answer is lost).
"""

import importlib.util
import os
import queue
import random
import signal
import subprocess
import sys
import threading
import time

import pytest
import torch

pytestmark = [  # processes killed with SIGKILL: make test-slow (CI runs it)
    pytest.mark.slow,
    pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs POSIX signals"),
]

TOTAL = 50
SEED = 11
NUM_KILLS = 7
MID_WRITE_KILLS = (1, 4)  # which kills wait for a write to be half done

CHILD = r'''
import sys
import time
import warnings

import torch

import torchpref.sessions.journal as journal
import torchpref.sessions.session as ts


def make_pool(seed):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(60, 2, generator=g, dtype=torch.float64) * torch.tensor([400.0, 200.0], dtype=torch.float64)


def utility(X, seed):
    g = torch.Generator().manual_seed(seed + 1)
    centre = torch.rand(2, generator=g, dtype=torch.float64)
    Z = X / torch.tensor([400.0, 200.0], dtype=torch.float64)
    return -((Z - centre) ** 2).sum(-1)


def answer(query, seed):
    """A deterministic simulated person: a Likert level from the utility, or the best item."""
    if query.kind == "rating":
        u = float(utility(query.item, seed))
        return int(min(5, max(1, 5 + int(u * 10))))
    return int(utility(query.items, seed).argmax())


def session(path, seed, total, repair=False):
    return ts.PreferenceSession(make_pool(seed), session_file=path, seed=seed, num_queries=total, repair=repair)


if __name__ == "__main__":
    path, seed, total, pause = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
    state = {"step": -1}
    write_all = journal._write_all

    def slow_write(fd, data):  # half a record, a pause, the rest: room for a kill mid-write
        write_all(fd, data[: len(data) // 2])
        print(f"WRITING {state['step']}", flush=True)
        time.sleep(pause)
        write_all(fd, data[len(data) // 2:])

    journal._write_all = slow_write
    try:
        s = session(path, seed, total)
    except ts.SessionFileCorrupt as err:
        print(f"CORRUPT line {err.line_number}", flush=True)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            s = session(path, seed, total, repair=True)
        assert any(issubclass(w.category, ts.SessionRepairWarning) for w in caught)
        print("REPAIRED", flush=True)
    print(f"READY {s.step}", flush=True)
    while not s.done:
        q = s.ask()
        a = answer(q, seed)
        state["step"] = s.step
        s.tell(q, a)
        print(f"TOLD {s.step}", flush=True)
    print("DONE", flush=True)
'''


def load_child(tmp_path):
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    spec = importlib.util.spec_from_file_location("session_kill_child", script)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return script, mod


class Child:
    """A child process with its stdout lines in a queue."""

    def __init__(self, script, path, pause):
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen(
            [sys.executable, str(script), str(path), str(SEED), str(TOTAL), str(pause)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        for line in self.proc.stdout:
            self.lines.put(line.strip())
        self.lines.put(None)

    def next_line(self, timeout=60.0):
        line = self.lines.get(timeout=timeout)
        if line is not None:
            self.seen.append(line)
        return line

    def wait_for(self, prefix, timeout=60.0):
        deadline = time.monotonic() + timeout
        while True:
            line = self.next_line(max(0.01, deadline - time.monotonic()))
            if line is None:
                raise AssertionError(f"child ended before {prefix!r}: {self.seen}\n{self.proc.stderr.read()}")
            if line.startswith(prefix):
                return line

    def kill(self):
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait()
        self.proc.stderr.close()


def test_sigkill_at_random_points_loses_nothing(tmp_path):
    script, child_mod = load_child(tmp_path)
    path = tmp_path / "session.jsonl"
    rng = random.Random(SEED)
    t0 = time.monotonic()
    runs, mid_write_steps, kills = [], [], 0
    while True:
        child = Child(script, path, pause=0.1)  # the window a mid-write kill must land in
        runs.append(child)
        ready = int(child.wait_for("READY").split()[1])
        if kills >= NUM_KILLS or ready >= TOTAL:
            child.wait_for("DONE")
            assert child.proc.wait(timeout=60) == 0
            break
        if kills in MID_WRITE_KILLS:
            line = child.wait_for("WRITING")
            mid_write_steps.append(int(line.split()[1]))
        else:
            time.sleep(rng.uniform(0.0, 0.8))
        child.kill()
        kills += 1
    elapsed = time.monotonic() - t0

    # every kill that landed mid-write was detected, reported and repaired by the next process;
    # that answer was asked again (the restart was READY at that step) and re-answered
    corrupt_after = [i for i, c in enumerate(runs) if any(s.startswith("CORRUPT") for s in c.seen)]
    assert len(corrupt_after) >= len(MID_WRITE_KILLS)
    for step in mid_write_steps:
        nxt = runs[[i for i, c in enumerate(runs) if f"WRITING {step}" in c.seen][0] + 1]
        assert "REPAIRED" in nxt.seen and f"READY {step}" in nxt.seen
    assert (tmp_path / "session.jsonl.dropped").exists()

    from torchpref.sessions.session import PreferenceSession, read_session_file

    header, records, _ = read_session_file(path)  # complete and valid: no repair needed
    answers = [r for r in records if r["type"] == "answer"]
    assert len(answers) == TOTAL and all(r["type"] == "answer" for r in records)
    seqs = [r["seq"] for r in answers]
    assert seqs == sorted(set(seqs))  # each sequence number once, in order
    assert sorted(r["query"]["step"] for r in answers) == list(range(TOTAL))  # each question once
    for step in mid_write_steps:
        assert sum(r["query"]["step"] == step for r in answers) == 1

    resumed = PreferenceSession.load(path)
    reference = PreferenceSession(child_mod.make_pool(SEED), seed=SEED, num_queries=TOTAL)
    while not reference.done:
        q = reference.ask()
        reference.tell(q, child_mod.answer(q, SEED))
    assert [h.items.tolist() for h in resumed.history] == [h.items.tolist() for h in reference.history]
    assert [h.answer for h in resumed.history] == [h.answer for h in reference.history]
    g = torch.Generator().manual_seed(0)
    X_test = torch.rand(100, 2, generator=g, dtype=torch.float64) * torch.tensor([400.0, 200.0], dtype=torch.float64)
    m1, s1 = resumed.predict(X_test)
    m2, s2 = reference.predict(X_test)
    torch.testing.assert_close(m1, m2, rtol=0, atol=1e-8)
    torch.testing.assert_close(s1, s2, rtol=0, atol=1e-8)
    print(f"{kills} kills, {len(corrupt_after)} mid-write, {elapsed:.1f} s")


# ------------------------------------------------------------------ a kill in the middle of an undo
UNDO_CHILD = r'''
import sys
import time

import torch

import torchpref.sessions.journal as journal
from torchpref.sessions.session import PreferenceSession

path, pause = sys.argv[1], float(sys.argv[2])
write_all = journal._write_all


def slow_write(fd, data):  # half the undo record, a pause (the kill lands here), the rest
    write_all(fd, data[: len(data) // 2])
    print("WRITING", flush=True)
    time.sleep(pause)
    write_all(fd, data[len(data) // 2:])


s = PreferenceSession.load(path)
journal._write_all = slow_write
s.undo()
print("UNDONE", flush=True)
'''


def _answered_session(path, n):
    from torchpref.sessions.session import PreferenceSession

    g = torch.Generator().manual_seed(3)
    s = PreferenceSession(
        torch.rand(12, 2, generator=g, dtype=torch.float64), session_file=path, seed=3, num_queries=10
    )
    for _ in range(n):
        q = s.ask()
        s.tell(q, 4 if q.kind == "rating" else 0)
    s.close()


def test_sigkill_in_the_middle_of_an_undo_keeps_the_answer(tmp_path):
    import warnings

    from torchpref.sessions.errors import SessionFileCorrupt, SessionRepairWarning
    from torchpref.sessions.session import PreferenceSession

    path = tmp_path / "s.jsonl"
    _answered_session(path, 4)
    before = path.read_bytes()
    script = tmp_path / "undo_child.py"
    script.write_text(UNDO_CHILD)
    proc = subprocess.Popen([sys.executable, str(script), str(path), "30"], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "WRITING"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    proc.stdout.close()
    assert path.read_bytes().startswith(before) and len(path.read_bytes()) > len(before)  # half an undo
    with pytest.raises(SessionFileCorrupt, match="line 6"):
        PreferenceSession.load(path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = PreferenceSession.load(path, repair=True)
    assert any(issubclass(w.category, SessionRepairWarning) for w in caught)
    assert path.read_bytes() == before and s.step == 4  # the undo never happened: all 4 answers in force
    undone = s.undo()  # and can be given again
    assert undone.seq == 4 and s.step == 3
    s.close()
    assert PreferenceSession.load(path).step == 3


# ------------------------------------------------------------------ a kill in the middle of save_model
SAVE_CHILD = r'''
import io
import sys
import time

import torch

import torchpref
import torchpref.models.checkpoint as checkpoint

path, pause = sys.argv[1], float(sys.argv[2])
real_save = torch.save


def slow_save(obj, fh):  # half the file, a pause (room for a kill), the rest
    buf = io.BytesIO()
    real_save(obj, buf)
    data = buf.getvalue()
    fh.write(data[: len(data) // 2])
    fh.flush()
    print(f"SAVING {len(obj['data']['ratings'])}", flush=True)
    time.sleep(pause)
    fh.write(data[len(data) // 2:])


checkpoint.torch.save = slow_save
g = torch.Generator().manual_seed(0)
X = torch.rand(12, 2, generator=g, dtype=torch.float64)
for k in range(1, 13):
    model = torchpref.PreferenceGP(X, ratings=torch.linspace(0.1, 0.9, 12, dtype=torch.float64)[:k],
                                   rating_index=torch.arange(k))
    torchpref.save_model(model, path)
    print(f"SAVED {k}", flush=True)
'''


def test_sigkill_during_save_model_leaves_the_last_complete_checkpoint(tmp_path):
    import torchpref

    path = tmp_path / "model.pt"
    script = tmp_path / "save_child.py"
    script.write_text(SAVE_CHILD)
    rng = random.Random(5)
    for trial in range(2):  # a kill mid-write, then one a moment after it
        path.unlink(missing_ok=True)
        proc = subprocess.Popen([sys.executable, str(script), str(path), "0.05"], stdout=subprocess.PIPE, text=True)
        target = rng.randint(2, 10)  # kill while the target-th save is half written, or at a random moment
        saved = 0
        for line in proc.stdout:
            saved = int(line.split()[1]) if line.startswith("SAVED") else saved
            if line.startswith(f"SAVING {target}"):
                if trial % 2:
                    time.sleep(rng.uniform(0.0, 0.1))  # sometimes past the write, into fsync and rename
                break
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
        loaded = torchpref.load_model(path)  # always a complete checkpoint: the old one or the new one
        assert len(loaded.ratings) in ((saved,) if trial % 2 == 0 else (saved, saved + 1)), (trial, saved)
        assert torch.isfinite(loaded.posterior(loaded.train_X).mean).all()
        if trial % 2 == 0:  # the half-written save is a temporary file beside it, not the checkpoint
            assert list(tmp_path.glob("model.pt.*.tmp"))


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")
def test_kills_mid_write_mid_rollback_and_mid_header_lose_nothing(tmp_path):
    """The benchmark's kill harness (benchmarks/durability/session_kills.py, 200 kills there) with 8 kills: two
    at random moments, two mid-write, two mid-rollback of a failed write, two mid-header."""
    from torchpref.testing import session_kills as kills

    out = kills.run_all(8, 2, seed=3, workdir=tmp_path, progress=False)
    assert out["by_mode"] == {"random": 2, "write": 2, "rollback": 2, "header": 2}
    assert out["killed_at"].get("ROLLBACK") == 2 and out["killed_at"].get("HEADER") == 2
    assert out["open_failures"] == [] and out["all_sequences_ok"] and out["files_checked"] == 4
    assert out["lost"] == out["doubled"] == out["undos_lost"] == 0
    assert out["acknowledged_answers"] > 0 and out["max_posterior_vs_replay"] < 1e-8
