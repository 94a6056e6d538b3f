"""``torchpref serve`` in a real browser: Playwright drives Debian's Chromium against the server
run as a process (``python -m torchpref.cli serve``) on a free loopback port.

* a person answers 20 questions (ratings, rankings, a "no preference", an undo) by mouse and by
  keyboard, reloads mid-question, reaches the summary; the session file then replays to the
  model the server has (its checkpoint, downloaded from the page);
* two browsers answer two sessions at once;
* the server is killed with SIGKILL while answers are in flight and restarted: every answer the
  page had acknowledged is in the file and the page carries on by itself.

Skipped (with the reason) where Chromium (Debian's ``chromium``, or ``TORCHPREF_CHROMIUM``),
Playwright or the ``serve`` extra is missing. ``TORCHPREF_SCREENSHOT_DIR=DIR`` also keeps the
rating, ranking and summary screenshots there.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from torchpref.testing.serve import CHROMIUM, CHROMIUM_ARGS, Server, acknowledged_in_file, choose, records, write_items

pytestmark = pytest.mark.slow  # a browser and server processes: make test-slow (CI runs it)

if not os.path.exists(CHROMIUM):
    pytest.skip(
        f"no Chromium at {CHROMIUM} (Debian: apt-get install chromium; or set TORCHPREF_CHROMIUM)",
        allow_module_level=True,
    )
sync_api = pytest.importorskip("playwright.sync_api", reason="Playwright is not installed (the test extra)")
pytest.importorskip("starlette", reason="the serve extra (starlette) is not installed")
pytest.importorskip("uvicorn", reason="the serve extra (uvicorn) is not installed")
pytest.importorskip("matplotlib")

ACK_MS = 120_000  # one answer on a loaded machine, restart included
LETTERS = "ABCDEFGHIJ"


@pytest.fixture
def server(tmp_path):
    items = write_items(tmp_path, n=30, d=3)
    srv = Server(
        # UCBC asks both kinds (the default rates each item once first: docs/selection.md)
        ["--features", str(items), "--image-column", "picture", "--sessions", "sessions", "--queries", "20"]
        + ["--selector", "ucbc"],
        tmp_path,
    )
    srv.start()
    yield srv
    srv.stop()


# The page's Content-Security-Policy forbids evaluating strings as script, which is how
# Playwright's wait_for_function runs its predicate: the test's contexts bypass it (bypass_csp).
@pytest.fixture
def browser():
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


def _start_session(page, url: str, ready: bool = True) -> str:
    page.goto(url)
    page.wait_for_function("document.activeElement && document.activeElement.id === 'start'", timeout=ACK_MS)
    page.keyboard.press("Enter")  # the Start button has the focus
    page.wait_for_url("**/s/*/", timeout=ACK_MS)
    page.wait_for_selector("body[data-qid]", timeout=ACK_MS)
    if ready:
        _wait_ready(page)
    return page.url.rstrip("/").rsplit("/", 1)[1]


def _state(page) -> dict:
    return page.evaluate("window.torchpref.state()")


def _wait_ready(page) -> None:
    """The question on screen is shown in full (its pictures decoded): it can be answered."""
    page.wait_for_function(
        "document.body.dataset.ready === 'true' || !!document.getElementById('to-summary')", timeout=ACK_MS
    )


def _wait_answered(page, n: int) -> None:
    page.wait_for_function(f"document.body.dataset.answered === '{n}'", timeout=ACK_MS)
    _wait_ready(page)


def _answer(page, k: int, by_keyboard: bool, tie: bool = False):
    """Answer the question on screen (:func:`choose`, or "no preference" if ``tie`` and it is a
    ranking) by key or by click; returns the answer."""
    q = _state(page)["question"]
    a = None if tie and q["kind"] == "ranking" else choose(q, k)
    if by_keyboard:
        key = str(a) if q["kind"] == "rating" else ("0" if a is None else (LETTERS[a] if k % 2 else str(a + 1)))
        page.keyboard.press(key)
    elif q["kind"] == "rating":
        page.locator("#question .levels button").nth(a - 1).click()
    elif a is None:
        page.get_by_role("button", name="No preference (0)").click()
    else:
        page.get_by_role("button", name=f"{LETTERS[a]} is best").click()
    return a


def test_twenty_questions_by_mouse_and_keyboard(server, browser, tmp_path):
    import torch

    import torchpref
    from torchpref.sessions.session import PreferenceSession

    page = browser.new_page(viewport={"width": 1280, "height": 900}, bypass_csp=True)
    sid = _start_session(page, server.url)
    shots = {}
    given, undone_at, tie_seen, kinds = [], None, False, set()
    k = 0
    while len(given) < 20:
        st = _state(page)
        q = st["question"]
        kinds.add(q["kind"])
        if q["kind"] == "rating" and "rating" not in shots:
            pictures = page.eval_on_selector_all("img.picture", "imgs => imgs.map(i => i.complete && i.naturalWidth)")
            assert pictures and all(w and w > 50 for w in pictures), pictures
            shots["rating"] = tmp_path / "serve_rating.png"
            page.screenshot(path=str(shots["rating"]), full_page=True)
        if q["kind"] == "ranking" and "ranking" not in shots:
            assert page.locator("img.picture").count() == len(q["options"]) >= 2
            shots["ranking"] = tmp_path / "serve_ranking.png"
            page.screenshot(path=str(shots["ranking"]), full_page=True)
        if len(given) == 6 and undone_at is None:  # reload mid-question: the same question
            page.reload()
            page.wait_for_selector("body[data-qid]", timeout=ACK_MS)
            _wait_ready(page)
            assert _state(page)["qid"] == st["qid"]
        a = _answer(page, k, by_keyboard=k % 2 == 1, tie=k >= 3 and not tie_seen)
        tie_seen |= a is None
        given.append((st["qid"], a))
        _wait_answered(page, len(given))
        if len(given) == 9 and undone_at is None:  # undo by key, then answer it again
            page.keyboard.press("u")
            _wait_answered(page, 8)
            undone_at = given.pop()
        k += 1
    assert {"rating", "ranking"} <= kinds
    assert tie_seen, given
    page.wait_for_selector("#to-summary", timeout=ACK_MS)
    page.keyboard.press("Enter")  # the summary link has the focus
    page.wait_for_url("**/summary", timeout=ACK_MS)
    page.wait_for_function("document.getElementById('utility').naturalWidth > 100", timeout=ACK_MS)
    assert page.locator("table#top tbody tr").count() == 5
    shots["summary"] = tmp_path / "serve_summary.png"
    page.screenshot(path=str(shots["summary"]), full_page=True)
    ckpt = tmp_path / "model.pt"
    ckpt.write_bytes(page.request.get(page.url.replace("summary", "download/model.pt")).body())
    csv_text = page.request.get(page.url.replace("summary", "download/answers.csv")).text()
    assert csv_text.count("\n") == 1 + 21  # header, 20 answers in force and the one undone

    path = server.folder / "sessions" / f"{sid}.session.jsonl"
    recs = records(path)
    answers = [r for r in recs if r["type"] == "answer"]
    assert [r["type"] for r in recs].count("undo") == 1 and len(answers) == 21
    assert all(isinstance(r["response_time"], float) and 0 < r["response_time"] < 600 for r in answers)
    assert not acknowledged_in_file(given, recs)
    copy = tmp_path / "copy.session.jsonl"  # the server holds the file's lock
    shutil.copy(path, copy)
    with PreferenceSession.load(copy) as replayed:  # a fresh replay of the file
        X = replayed._pool
        mean, _ = replayed.predict(X)
        model = torchpref.load_model(ckpt)
        with torch.no_grad():
            served = model.posterior(replayed.transform(X).unsqueeze(-2)).mean.reshape(-1)
    assert torch.allclose(served, mean, atol=1e-9), (served - mean).abs().max()
    out = os.environ.get("TORCHPREF_SCREENSHOT_DIR")
    if out:
        Path(out).mkdir(parents=True, exist_ok=True)
        for p in shots.values():
            shutil.copy(p, Path(out) / p.name)


def test_two_browsers_two_sessions_at_once(server, browser):
    pages = [browser.new_context(bypass_csp=True).new_page() for _ in range(2)]
    sids = [_start_session(p, server.url) for p in pages]
    assert sids[0] != sids[1]
    given = [[], []]
    for k in range(5):
        for j, page in enumerate(pages):  # both answers in flight together
            given[j].append((_state(page)["qid"], _answer(page, k + j, by_keyboard=j == 1)))
        for page in pages:
            _wait_answered(page, k + 1)
    for j, sid in enumerate(sids):
        recs = records(server.folder / "sessions" / f"{sid}.session.jsonl")
        assert len(recs) == 5 and not acknowledged_in_file(given[j], recs)


def test_server_killed_mid_answer_and_restarted(server, browser):
    page = browser.new_page(bypass_csp=True)
    sid = _start_session(page, server.url)
    for k in range(3):
        _answer(page, k, by_keyboard=True)
        _wait_answered(page, k + 1)
    for k in range(3, 6):  # the server dies right after the click, before or after the fsync
        _answer(page, k, by_keyboard=k % 2 == 0)
        server.kill()
        server.start()
        _wait_answered(page, k + 1)  # the page retried by itself
    _answer(page, 6, by_keyboard=False)
    _wait_answered(page, 7)
    acked = page.evaluate("window.torchpref.log.acked")
    assert len(acked) == 7
    recs = records(server.folder / "sessions" / f"{sid}.session.jsonl")
    assert len(recs) == 7 and not acknowledged_in_file([(a["qid"], a["answer"]) for a in acked], recs)


def test_the_clock_starts_when_the_pictures_are_shown(server, browser):
    """Pictures held back (a slow network): the question shows "loading", its answer controls are
    disabled and its keys do nothing; once the pictures are decoded the clock starts, and the
    journal's shown_at is after the pictures were let through, its response_time that of the
    person alone (answered_at - shown_at)."""
    import datetime as dt

    page = browser.new_page(viewport={"width": 1280, "height": 900}, bypass_csp=True)
    holding, held = {"on": True}, []
    page.route("**/picture/**", lambda route: held.append(route) if holding["on"] else route.continue_())
    sid = _start_session(page, server.url, ready=False)
    page.wait_for_selector("#question.loading", timeout=ACK_MS)
    assert page.locator("#loading").is_visible()
    assert all(page.eval_on_selector_all("#question button.answer", "bs => bs.map(b => b.disabled)"))
    q = _state(page)["question"]
    for key in ("1", "2", "a", "Enter"):  # answers before the pictures show: nothing is sent
        page.keyboard.press(key)
    page.wait_for_timeout(1500)  # the pictures are still held back
    assert held and page.evaluate("window.torchpref.log.acked.length") == 0
    path = server.folder / "sessions" / f"{sid}.session.jsonl"
    assert records(path) == [] and page.locator("#question.loading").count() == 1
    released = page.evaluate("Date.now()")
    holding["on"] = False
    for route in held:
        route.continue_()
    _wait_ready(page)
    assert not page.locator("#loading").is_visible()
    a = _answer(page, 0, by_keyboard=True)
    _wait_answered(page, 1)
    (rec,) = records(path)
    assert rec["answer"] == a and rec["items"] and q["options"]

    def ms(text: str) -> float:
        return dt.datetime.fromisoformat(text).timestamp() * 1000

    shown, answered = ms(rec["shown_at"]), ms(rec["answered_at"])
    assert shown >= released  # the clock started after the pictures were let through
    assert abs(rec["response_time"] - (answered - shown) / 1000) < 0.002  # the wait is not in it
    assert page.evaluate("window.torchpref.log.acked[0].shown_at") == shown


def test_lake_page(tmp_path, browser):
    """``torchpref serve lake``: each path drawn on its map, answered by keyboard; a best-of-5
    question in a 1280 px window gives each map at least 340 px, Shift + a letter (or a click)
    enlarges one, Escape closes it, and the recommendation is one line until opened."""
    srv = Server(["lake", "--sessions", "sessions", "--queries", "10", "--selector", "ucbc"], tmp_path)
    srv.start()
    shots = {}
    try:
        page = browser.new_page(viewport={"width": 1280, "height": 900}, bypass_csp=True)
        _start_session(page, srv.url)
        q = _state(page)["question"]
        assert q["options"][0]["label"].startswith("path ")
        page.wait_for_function(
            "[...document.querySelectorAll('#question img.picture')].every(i => i.complete && i.naturalWidth > 600)",
            timeout=ACK_MS,
        )
        assert page.locator("#question img.picture").count() == len(q["options"])
        k = 0
        while k == 0 or _state(page)["question"]["kind"] != "ranking":  # one answer: a recommendation
            _answer(page, k, by_keyboard=True)
            k += 1
            _wait_answered(page, k)
        q = _state(page)["question"]
        widths = page.eval_on_selector_all("#question img.picture", "imgs => imgs.map(i => i.clientWidth)")
        assert len(widths) == len(q["options"]) == 5 and min(widths) >= 340, widths
        # at 1280 x 900 every option's button, "no preference" and undo are in view without scrolling
        bottoms = page.eval_on_selector_all(
            "#question button.answer, #ties-slot button, #undo", "bs => bs.map(b => b.getBoundingClientRect().bottom)"
        )
        assert len(bottoms) == 7 and max(bottoms) <= 900, bottoms
        assert page.evaluate("window.scrollY") == 0
        assert page.locator("#recommended img.picture").count() == 1  # the recommended path's map ...
        assert not page.locator("#recommended img.picture").is_visible()  # ... only when opened
        shots["serve_lake_best_of_5"] = tmp_path / "serve_lake_best_of_5.png"
        page.screenshot(path=str(shots["serve_lake_best_of_5"]), full_page=True)
        page.keyboard.press("Shift+B")
        page.wait_for_function("document.getElementById('zoom').open", timeout=ACK_MS)
        page.wait_for_function("document.getElementById('zoom-img').naturalWidth > 600", timeout=ACK_MS)
        zoomed = page.evaluate("document.getElementById('zoom-img').clientWidth")
        assert zoomed > 2 * min(widths) and q["options"][1]["label"] in page.inner_text("#zoom-title")
        shots["serve_lake_enlarged"] = tmp_path / "serve_lake_enlarged.png"
        page.screenshot(path=str(shots["serve_lake_enlarged"]))
        page.keyboard.press("2")  # no answer while the enlarged picture is open
        page.keyboard.press("Escape")
        page.wait_for_function("!document.getElementById('zoom').open", timeout=ACK_MS)
        assert _state(page)["answered"] == k
        page.locator("#question button.enlarge").nth(0).click()  # a click enlarges too
        page.wait_for_function("document.getElementById('zoom').open", timeout=ACK_MS)
        page.keyboard.press("Escape")
        _answer(page, 1, by_keyboard=True)
        _wait_answered(page, k + 1)
        page.keyboard.press("u")  # the undo's confirmation is in view too
        page.wait_for_function("document.getElementById('message').textContent.includes('withdrawn')", timeout=ACK_MS)
        text_bottom = page.evaluate(
            "(() => { const r = document.createRange(); r.selectNodeContents(document.getElementById('message'));"
            " return r.getBoundingClientRect().bottom; })()"
        )
        assert 0 < text_bottom <= 900 and page.evaluate("window.scrollY") == 0, text_bottom
    finally:
        srv.stop()
    out = os.environ.get("TORCHPREF_SCREENSHOT_DIR")
    if out:
        Path(out).mkdir(parents=True, exist_ok=True)
        for p in shots.values():
            shutil.copy(p, Path(out) / p.name)
