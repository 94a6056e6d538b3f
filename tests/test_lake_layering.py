"""The lake world knows nothing of learning: no module of torchpref/lake imports the model, the
loop, the selectors or the metrics."""

import ast
from pathlib import Path

import torchpref.lake

LEARNING = {"models", "laplace", "batch", "active", "session", "strategies", "acquisition", "metrics", "queries",
            "likelihoods", "experiments"}


def test_lake_modules_import_nothing_of_learning():
    folder = Path(torchpref.lake.__file__).parent
    seen = []
    for f in sorted(folder.glob("*.py")):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.ImportFrom):
                names = [f"{'.' * node.level}{node.module or ''}"]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            for name in names:
                parts = name.lstrip(".").split(".")
                if name.startswith("torchpref") or (name.startswith("..")):
                    seen.append((f.name, name))
                    assert not set(parts) & LEARNING, f"{f.name} imports {name}"
    assert seen, "expected at least one import of torchpref outside the lake (data)"
