"""The README's code runs as written."""

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def _python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


def test_readme_has_a_quick_start():
    assert _python_blocks(), "README.md has no python code block"


def test_readme_code_runs(capsys):
    namespace: dict = {}  # the blocks build on each other, as a reader runs them
    for block in _python_blocks():
        exec(compile(block, str(README), "exec"), namespace)
    model = namespace["model"]
    assert model.train_X.shape[0] == 13  # the quick start's 12 items plus the UCB point
    assert model.ratings.shape[0] == 4
    printed = capsys.readouterr().out
    assert "tensor(" in printed and "grad_fn" not in printed  # the printed tensors are plain values
    assert 0 <= namespace["row"] < 12 and namespace["best"].shape == (2,)
