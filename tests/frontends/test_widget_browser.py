"""The lake widget in a real headless browser: Voilà serves a notebook with a
:class:`~torchpref.frontends.widgets.PreferenceWidget` over lake paths, Playwright drives Chromium.

Checks that each option's picture is rendered by the browser and shows a path on the map (its
pixels hold the path's colour), and that a click on "A is best" is recorded in the session file.
Skipped where Chromium (Debian's ``chromium``, or the browser at ``TORCHPREF_CHROMIUM``), Voilà or
Playwright is missing.

``TORCHPREF_SCREENSHOT_DIR=benchmarks/results`` also writes the page's screenshot there as
``widget_lake.png`` (by default it goes to the test's temporary folder only).
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

CHROMIUM = os.environ.get("TORCHPREF_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
pytestmark = pytest.mark.slow  # a browser: make test-slow (CI runs it)

if not os.path.exists(CHROMIUM):
    pytest.skip(
        f"no Chromium at {CHROMIUM} (Debian: apt-get install chromium; or set TORCHPREF_CHROMIUM)",
        allow_module_level=True,
    )
pytest.importorskip("voila", reason="Voilà is not installed (the test extra)")
sync_api = pytest.importorskip("playwright.sync_api", reason="Playwright is not installed (the test extra)")
pytest.importorskip("ipywidgets")
mpimg = pytest.importorskip("matplotlib.image")

PATH_COLOUR = (0x1F, 0x3F, 0xBF)  # the first path's colour on the lake map (torchpref.frontends.elicit.plot_paths)
STARTUP_S = 240  # Voilà runs the notebook (scenario, model, five maps) before the page is ready
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]

NOTEBOOK_CODE = """\
from torchpref.lake import make_scenario
from torchpref import UCBC
from torchpref.sessions.session import PreferenceSession
from torchpref.frontends.widgets import PreferenceWidget, lake_renderer

scenario = make_scenario(seed=0, paths_per_planner=10)
session = PreferenceSession(scenario.train_X, session_file={session_file!r}, num_queries=4,
                            names=["distance", "information"], selector=UCBC(m=5))
PreferenceWidget(session, lake_renderer(scenario), noun="path")
"""


def _notebook(path: Path, session_file: Path) -> None:
    nb = {
        "cells": [
            {
                "cell_type": "code",
                "execution_count": None,
                "id": "lake-widget",
                "metadata": {},
                "outputs": [],
                "source": NOTEBOOK_CODE.format(session_file=str(session_file)),
            }
        ],
        "metadata": {"kernelspec": {"name": "python3", "display_name": "Python 3", "language": "python"}},
        "nbformat": 4,
        "nbformat_minor": 5,
    }
    path.write_text(json.dumps(nb))


def _env(root: Path) -> dict:
    """Jupyter folders under ``root``, with a ``python3`` kernel that runs this interpreter."""
    spec = root / "data" / "kernels" / "python3"
    spec.mkdir(parents=True)
    (spec / "kernel.json").write_text(
        json.dumps(
            {
                "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
                "display_name": "Python 3 (test)",
                "language": "python",
            }
        )
    )
    env = dict(
        os.environ,
        JUPYTER_PATH=str(root / "data"),
        JUPYTER_DATA_DIR=str(root / "data"),
        JUPYTER_CONFIG_DIR=str(root / "config"),
        JUPYTER_RUNTIME_DIR=str(root / "runtime"),
        MPLBACKEND="Agg",
    )
    return env


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def voila_page(tmp_path):
    """``(url, session_file, log)`` of a Voilà server showing the lake widget; stopped afterwards."""
    session_file = tmp_path / "lake.jsonl"
    _notebook(tmp_path / "lake_widget.ipynb", session_file)
    port = _free_port()
    log = open(tmp_path / "voila.log", "w+")
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "voila",
            "lake_widget.ipynb",
            "--no-browser",
            f"--port={port}",
            "--Voila.ip=127.0.0.1",
            "--show_tracebacks=True",
        ],
        cwd=tmp_path,
        env=_env(tmp_path / "jupyter"),
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    url = f"http://127.0.0.1:{port}/"
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=5):
                    break  # the server listens
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    log.seek(0)
                    pytest.fail(f"Voilà did not start:\n{log.read()[-3000:]}")
                time.sleep(0.5)
        yield url, session_file, log
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()


def _path_pixels(png: Path) -> tuple[int, int]:
    """``(pixels of the path's colour, distinct colours)`` in a PNG screenshot."""
    img = mpimg.imread(png)[..., :3]
    rgb = (img * 255).round().astype(int)
    target = sum(abs(rgb[..., c] - PATH_COLOUR[c]) for c in range(3)) < 40
    distinct = len({tuple(p) for p in rgb.reshape(-1, 3)[::7].tolist()})
    return int(target.sum()), distinct


def _answers(session_file: Path) -> list[dict]:
    if not session_file.exists():
        return []
    lines = [json.loads(line) for line in session_file.read_text().splitlines() if line.strip()]
    return [r for r in lines if r.get("type") == "answer"]


def test_lake_widget_in_browser(voila_page, tmp_path):
    url, session_file, log = voila_page
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1100})
            page.goto(url, timeout=STARTUP_S * 1000)
            try:
                page.wait_for_selector("img.torchpref-picture", timeout=STARTUP_S * 1000)
            except sync_api.TimeoutError:
                log.seek(0)
                pytest.fail(f"no picture on the page:\n{page.content()[-2000:]}\nVoilà log:\n{log.read()[-3000:]}")
            pictures = page.locator("img.torchpref-picture")
            assert pictures.count() == 5  # UCBC's first query: a ranking of five paths
            # every picture decoded by the browser, at a real size
            sizes = page.eval_on_selector_all(
                "img.torchpref-picture", "imgs => imgs.map(i => [i.complete, i.naturalWidth, i.naturalHeight])"
            )
            assert all(ok and wd > 200 and ht > 150 for ok, wd, ht in sizes), sizes
            # and each shows a path on the map: pixels of the path's colour among many colours
            for k in range(5):
                shot = tmp_path / f"option{k}.png"
                pictures.nth(k).screenshot(path=str(shot))
                on_path, distinct = _path_pixels(shot)
                assert on_path > 100 and distinct > 30, (k, on_path, distinct)
            screenshot = tmp_path / "widget_lake.png"
            page.screenshot(path=str(screenshot), full_page=True)
            assert _answers(session_file) == []

            page.get_by_role("button", name="A is best").click()
            page.wait_for_selector("text=1 answer in force", timeout=120_000)
        finally:
            browser.close()
    answers = _answers(session_file)
    assert len(answers) == 1
    assert answers[0]["kind"] == "choice" and answers[0]["answer"] == 0
    assert len(answers[0]["query"]["pool_indices"]) == 5
    out = os.environ.get("TORCHPREF_SCREENSHOT_DIR")
    if out:
        Path(out).mkdir(parents=True, exist_ok=True)
        shutil.copy(screenshot, Path(out) / "widget_lake.png")
