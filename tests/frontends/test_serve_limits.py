"""``torchpref serve`` as a process whose descriptor limit is lowered under it (``prlimit``): a new
participant gets 503 with ``Retry-After`` and a message, a participant already in goes on, the
log holds a line or two and no traceback, and the server recovers when the limit returns."""

from __future__ import annotations

import os
import threading
import time

import pytest

from torchpref.testing.serve import Server, get_json, post, write_items

pytest.importorskip("starlette", reason="the serve extra (starlette) is not installed")
pytest.importorskip("uvicorn", reason="the serve extra (uvicorn) is not installed")
resource = pytest.importorskip("resource")

pytestmark = pytest.mark.skipif(
    not hasattr(resource, "prlimit") or not os.path.isdir("/proc/self/fd"), reason="needs Linux's prlimit and /proc"
)


def _answer(url: str, k: int) -> int:
    st = get_json(url + "state")
    q = st["question"]
    a = 1 + k % 5 if q["kind"] == "rating" else k % len(q["options"])
    return post(url + "answer", {"qid": st["qid"], "answer": a, "response_time": 1.0})[0]


@pytest.mark.slow  # a server process started (some 20 s on a loaded machine); test_serve_pool checks the same in-process
def test_out_of_descriptors_is_503_then_recovers(tmp_path):
    items = write_items(tmp_path, n=20, d=2, pictures=False)
    srv = Server(["--features", str(items), "--sessions", "sessions", "--queries", "6"], tmp_path)
    srv.start()
    try:
        pid = srv.proc.pid
        soft, hard = resource.prlimit(pid, resource.RLIMIT_NOFILE)
        status, data, _ = post(srv.url + "api/new", {})
        assert status == 200
        mine = srv.url + data["url"]
        assert _answer(mine, 0) == 200

        # a few descriptors left: below the reserve kept for participants already in
        used = len(os.listdir(f"/proc/{pid}/fd"))
        resource.prlimit(pid, resource.RLIMIT_NOFILE, (used + 3, hard))
        for _ in range(20):
            status, data, headers = post(srv.url + "api/new", {})
            headers = {k.lower(): v for k, v in headers.items()}
            assert status == 503 and int(headers["retry-after"]) > 0
            assert "try again" in data["error"]
        assert _answer(mine, 1) == 200  # a participant already in goes on
        assert len(list((tmp_path / "sessions").glob("*.session.jsonl"))) == 1  # nothing half-made

        # none left at all: connections wait in the backlog, the event loop's accept fails each second
        resource.prlimit(pid, resource.RLIMIT_NOFILE, (len(os.listdir(f"/proc/{pid}/fd")), hard))
        waiting: list = []
        t = threading.Thread(target=lambda: waiting.append(post(srv.url + "api/new", {}, timeout=120)))
        t.start()
        time.sleep(3)
        resource.prlimit(pid, resource.RLIMIT_NOFILE, (soft, hard))  # the limit returns
        t.join(timeout=150)
        assert waiting and waiting[0][0] in (200, 503)  # answered either way, never a 500
        status, data, _ = post(srv.url + "api/new", {})
        assert status == 200 and _answer(srv.url + data["url"], 0) == 200
        assert _answer(mine, 2) == 200
    finally:
        srv.stop()
    log = srv.log()
    assert "Traceback" not in log, log[-3000:]
    noted = [line for line in log.splitlines() if "descriptors" in line or "Too many open files" in line]
    assert 2 <= len(noted) <= 4, noted  # out of, (accept failing,) available again
    assert "available again" in noted[-1]
