"""The session file (torchpref.sessions.journal): strict validation of every record, lock before read,
a complete last record kept, and a session that an interrupt cannot split from its file."""

import json

import pytest
import torch

from torchpref.sessions.errors import SessionFileCorrupt, SessionFileError
from torchpref.sessions.session import PreferenceSession, read_session_file

SCALE = torch.tensor([100.0, 5.0], dtype=torch.float64)


def pool(n: int = 20) -> torch.Tensor:
    g = torch.Generator().manual_seed(3)
    return torch.rand(n, 2, generator=g, dtype=torch.float64) * SCALE


def written(tmp_path, answers=(("rating", 4), ("choice", 1), ("rating", 2))):
    """A valid session file with the given answers; ``(X, path, lines as dicts)``."""
    X = pool()
    path = tmp_path / "s.jsonl"
    with PreferenceSession(X, session_file=path, seed=5) as s:
        for k, (kind, a) in enumerate(answers):
            if kind == "rating":
                s.tell_rating(X[k], a)
            else:
                s.tell_choice(X[[k, k + 1, k + 2]], a)
    return X, path, [json.loads(line) for line in path.read_text().splitlines()]


def rewrite(path, lines) -> None:
    path.write_text("".join(json.dumps(r) + "\n" for r in lines))


def opening_fails(X, path, match: str) -> str:
    """Opening ``path`` (load, the constructor and read_session_file) fails by name with ``match``
    and the file and line in the message; returns the message."""
    before = path.read_bytes()
    for open_it in (
        lambda: PreferenceSession.load(path),
        lambda: PreferenceSession(X, session_file=path, seed=5),
        lambda: read_session_file(path),
    ):
        with pytest.raises(SessionFileError, match=match) as err:
            open_it()
        assert f"session file {path}" in str(err.value)
    assert path.read_bytes() == before  # nothing changed by failing to open
    return str(err.value)


@pytest.mark.parametrize("bad", [1.5, True, "1", -1, 3, None])
def test_choice_answer_must_be_an_item_index(tmp_path, bad):
    X, path, lines = written(tmp_path)
    lines[2]["answer"] = bad  # line 3: the choice among three items
    rewrite(path, lines)
    opening_fails(X, path, "line 3: 'answer' must be an integer in 0..2")


def test_rating_record_with_two_items(tmp_path):
    X, path, lines = written(tmp_path)
    lines[1]["items"] = X[:2].tolist()
    rewrite(path, lines)
    opening_fails(X, path, r"line 2: a rating's items must have exactly 1 row\(s\), got 2")


@pytest.mark.parametrize(
    "level, value, match",
    [
        (9, 0.5, r"'answer' must be an integer in 1..5, got 9"),
        (4, 0.5, r"value 0.5 does not match its answer 4 \(expected 0.7"),
        (4.0, 0.7, r"'answer' must be an integer in 1..5, got 4.0"),
        (4, None, r"value None does not match"),
    ],
)
def test_rating_level_and_value_must_agree(tmp_path, level, value, match):
    X, path, lines = written(tmp_path)
    lines[1]["answer"], lines[1]["value"] = level, value
    rewrite(path, lines)
    opening_fails(X, path, "line 2: .*" + match)


@pytest.mark.parametrize("key", ["time", "items", "answer", "seq", "kind"])
def test_answer_missing_a_field(tmp_path, key):
    X, path, lines = written(tmp_path)
    del lines[4 - 1][key]
    rewrite(path, lines)
    opening_fails(X, path, "line 4: ")


@pytest.mark.parametrize("key", ["num_queries", "candidates", "bounds", "dim", "seed", "num_levels", "version"])
def test_header_missing_a_field(tmp_path, key):
    X, path, lines = written(tmp_path)
    del lines[0][key]
    rewrite(path, lines)
    assert repr(key) in opening_fails(X, path, "line 1: ")


def test_header_seed_as_text_is_named(tmp_path):
    X, path, lines = written(tmp_path)
    lines[0]["seed"] = "0"
    rewrite(path, lines)
    msg = opening_fails(X, path, "line 1: 'seed' must be an integer, got '0'")
    assert "seed 0, but this session has seed 0" not in msg


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda h: h["candidates"].update(items=[[1.0, 2.0], [3.0]]), "candidates' items"),
        (lambda h: h.update(bounds=[[1.0, 2.0], [0.0, 3.0]]), "lower < upper"),
        (lambda h: h.update(names=["a"]), "names must be null or 2 strings"),
        (lambda h: h.update(num_levels=1), "'num_levels' must be an integer >= 2"),
    ],
)
def test_header_values_are_checked(tmp_path, change, match):
    X, path, lines = written(tmp_path)
    change(lines[0])
    rewrite(path, lines)
    opening_fails(X, path, "line 1: .*" + match)


def test_pool_indices_must_be_the_items_rows(tmp_path):
    X = pool()
    path = tmp_path / "s.jsonl"
    with PreferenceSession(X, session_file=path, seed=5) as s:
        q = s.ask()
        s.tell(q, 0 if q.kind == "ranking" else 3)
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    lines[1]["query"]["pool_indices"] = [(i + 1) % 20 for i in lines[1]["query"]["pool_indices"]]
    rewrite(path, lines)
    opening_fails(X, path, "line 2: the items are not the pool's rows")


def test_deeply_nested_json_is_a_named_error(tmp_path):
    X, path, _ = written(tmp_path)
    good = path.read_bytes()
    path.write_bytes(good + b"[" * 100_000 + b"]" * 100_000 + b"\n")
    with pytest.raises(SessionFileCorrupt, match="line 5: not a valid record"):
        PreferenceSession.load(path)
    path.write_bytes(good + b"[" * 100_000 + b"]" * 100_000 + b"\n" + good.splitlines(keepends=True)[1])
    with pytest.raises(SessionFileCorrupt, match="line 5") as err:
        read_session_file(path)
    assert not err.value.repairable


def test_nan_and_infinity_are_not_numbers(tmp_path):
    X, path, _ = written(tmp_path)
    path.write_text(path.read_text().replace('"value":0.7', '"value":NaN', 1))
    opening_fails(X, path, "line 2: not a valid record")


def test_complete_last_record_without_newline_is_kept(tmp_path):
    X, path, lines = written(tmp_path)
    data = path.read_bytes()
    path.write_bytes(data.rstrip(b"\n"))  # every byte of the last answer, only its newline lost
    assert len(read_session_file(path)[1]) == 3
    with PreferenceSession(X, session_file=path, seed=5) as s:
        assert s.step == 3 and path.read_bytes() == data  # kept; its line ended on opening
        s.tell_rating(X[5], 1)
    assert len(read_session_file(path)[1]) == 4


def test_file_is_locked_before_it_is_read(tmp_path, monkeypatch):
    """A second writer that appends between our open and our lock: we must read its record, so
    that our next record follows its sequence number (reading first would duplicate it)."""
    import torchpref.sessions.journal as journal

    X, path, lines = written(tmp_path)
    real_lock = journal._lock
    theirs = dict(lines[-1], seq=lines[-1]["seq"] + 1, time="2026-01-01T00:00:00.000+00:00")

    def lock_after_another_writer(fd, p):
        with open(path, "a") as f:  # the other writer finishes its answer just before our lock
            f.write(json.dumps(theirs) + "\n")
        monkeypatch.setattr(journal, "_lock", real_lock)
        real_lock(fd, p)

    monkeypatch.setattr(journal, "_lock", lock_after_another_writer)
    with PreferenceSession(X, session_file=path, seed=5) as s:
        assert s.step == 4
        s.tell_rating(X[6], 5)
    _, records, _ = read_session_file(path)  # opens: no duplicate sequence number
    assert [r["seq"] for r in records] == [1, 2, 3, 4, 5]


def test_session_directory_is_a_named_error(tmp_path):
    with pytest.raises(SessionFileError, match="is a directory"):
        PreferenceSession(pool(), session_file=tmp_path)


def test_api_answers_are_strict(tmp_path):
    X = pool()
    s = PreferenceSession(X, session_file=tmp_path / "s.jsonl", seed=5)
    for bad in (1.5, True, "1", 3):
        with pytest.raises(ValueError, match="item index in 0..2"):
            s.tell_choice(X[:3], bad)
    for bad in ("4", True, 4.5, 0, 6, float("nan")):
        with pytest.raises(ValueError, match="whole level in 1..5"):
            s.tell_rating(X[0], bad)
    with pytest.raises(ValueError, match="seed must be an integer"):
        PreferenceSession(X, seed="0")
    assert s.step == 0 and len(read_session_file(tmp_path / "s.jsonl")[1]) == 0


class Interrupt:
    """Raise KeyboardInterrupt at the ``when``-th call of a wrapped function."""

    def __init__(self, fn, when: int = 1):
        self.fn, self.when, self.calls = fn, when, 0

    def __call__(self, *args, **kwargs):
        self.calls += 1
        if self.calls == self.when:
            raise KeyboardInterrupt
        return self.fn(*args, **kwargs)


def consistent(s: PreferenceSession, path, X) -> None:
    """Model, file and history agree: the history is the file's answers in force, and the
    posterior is that of a fresh session replaying the file."""
    from torchpref.sessions.records import records_in_force

    _, records, _ = read_session_file(path)
    assert [h.seq for h in s.history] == [r["seq"] for r in records_in_force(records)]
    ref = PreferenceSession(X, seed=5)
    for r in records_in_force(records):
        if r["kind"] == "rating":
            ref.tell_rating(torch.tensor(r["items"][0], dtype=torch.float64), r["answer"])
        else:
            ref.tell_choice(torch.tensor(r["items"], dtype=torch.float64), r["answer"])
    torch.testing.assert_close(s.predict(X), ref.predict(X), rtol=0, atol=1e-10)


@pytest.mark.parametrize("where", ["model", "write", "after_write"])
def test_keyboard_interrupt_in_tell_keeps_model_file_and_history_together(tmp_path, monkeypatch, where):
    import torchpref.models.preference_gp as models
    import torchpref.sessions.journal as journal

    X, path, _ = written(tmp_path)
    s = PreferenceSession(X, session_file=path, seed=5)
    q = s.ask()
    if where == "model":  # inside the model's update, after it took the new data (the worst case)

        def half_update(self, data, warm_f=None, *, lazy=False):
            self._data, self._cache = data, None
            raise KeyboardInterrupt

        monkeypatch.setattr(models.PreferenceGP, "replace_data", half_update)
    elif where == "write":  # half the record written

        def half(fd, data):
            journal.os.write(fd, data[: len(data) // 2])
            raise KeyboardInterrupt

        monkeypatch.setattr(journal, "_write_all", half)
    else:  # the record is on disk, the fsync is interrupted
        monkeypatch.setattr(journal.os, "fsync", Interrupt(journal.os.fsync, 1))
    with pytest.raises(KeyboardInterrupt):
        s.tell(q, 3 if q.kind == "rating" else 1)
    monkeypatch.undo()
    assert s.step == 3 and len(read_session_file(path)[1]) == 3
    consistent(s, path, X)
    assert s.ask().items.equal(q.items)  # the same question again
    s.tell(q, 3 if q.kind == "rating" else 1)
    consistent(s, path, X)
    s.close()
