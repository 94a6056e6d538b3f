"""``torchpref serve`` killed with SIGKILL while answers are in flight, restarted each time: no
acknowledged answer is lost (:func:`torchpref.testing.serve.kill_run`). Four kills, and twenty
(``benchmarks/durability/serve_kill.py`` runs that and keeps the results); both marked slow
(``make test-slow``, which CI runs)."""

from __future__ import annotations

import pytest

from torchpref.testing.serve import kill_run

pytest.importorskip("starlette", reason="the serve extra (starlette) is not installed")
pytest.importorskip("uvicorn", reason="the serve extra (uvicorn) is not installed")


def _check(result: dict, kills: int) -> None:
    assert result["lost"] == [], result["lost"]
    assert result["answers_in_file"] == result["acknowledged"] > kills  # nothing lost, nothing twice
    assert sum(result["outcomes"].values()) == kills and result["server_starts"] == kills + 1


@pytest.mark.slow
def test_four_kills(tmp_path):
    _check(kill_run(tmp_path, kills=4, seed=1), 4)


@pytest.mark.slow
def test_twenty_kills(tmp_path):
    _check(kill_run(tmp_path, kills=20, seed=0), 20)
