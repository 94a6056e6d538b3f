"""The package's layout stays as docs/architecture.md describes it: no module of ``torchpref``
over 450 lines, no function over 60, and the lake world (``torchpref/lake/``) imports nothing of
learning (the model, the loop, the selectors, the metrics) from the rest of the package."""

import ast
from pathlib import Path

import torchpref

PACKAGE = Path(torchpref.__file__).parent
MAX_MODULE_LINES = 450
MAX_FUNCTION_LINES = 60

# What a module of torchpref/lake/ may import from the rest of torchpref: the data conventions
# (Likert levels) and numerical helpers; never a model, a selector, the loop or the metrics.
LAKE_MAY_IMPORT = {"data", "numerics"}


def _modules() -> list[Path]:
    return sorted(PACKAGE.rglob("*.py"))


def _name(f: Path) -> str:
    return f.relative_to(PACKAGE).as_posix()


def test_no_module_over_the_limit():
    long = {_name(f): n for f in _modules() if (n := len(f.read_text().splitlines())) > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


def test_no_function_over_the_limit():
    long = []
    for f in _modules():
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    long.append(f"{_name(f)}:{node.lineno} {node.name} ({n} lines)")
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines:\n" + "\n".join(long)


def _torchpref_imports(tree: ast.AST) -> list[tuple[str, int]]:
    """Each import of a torchpref module outside the lake package: ``(top-level module, line)``."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level == 1:  # from .x import ...: inside the lake package
                continue
            if node.level >= 2:  # from ..x import ...: torchpref.x
                parts = (node.module or "").split(".")
                out += [(parts[0], node.lineno)] if parts[0] else [(a.name, node.lineno) for a in node.names]
            elif node.module and node.module.split(".")[0] == "torchpref":
                parts = node.module.split(".")
                out += [(parts[1], node.lineno)] if len(parts) > 1 else [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.Import):
            for a in node.names:
                parts = a.name.split(".")
                if parts[0] == "torchpref":
                    out.append((parts[1] if len(parts) > 1 else "torchpref", node.lineno))
    return out


def test_the_lake_world_imports_nothing_of_learning():
    folder = PACKAGE / "lake"
    seen, bad = [], []
    for f in sorted(folder.glob("*.py")):
        for module, line in _torchpref_imports(ast.parse(f.read_text())):
            seen.append(module)
            if module not in LAKE_MAY_IMPORT | {"lake"}:
                bad.append(f"{f.name}:{line} imports torchpref.{module}")
    assert not bad, "\n".join(bad)
    assert "data" in seen, "expected the lake operator's import of torchpref.data (is the walk blind?)"


def test_the_import_walk_sees_every_form():
    src = ("from ..models import PreferenceGP\nfrom .. import active\nimport torchpref.metrics\n"
           "from torchpref.strategies import UCBC\nfrom torchpref import session\nfrom .field import x\n"
           "def f():\n    from torchpref.acquisition import item_ucb\n")
    assert sorted(m for m, _ in _torchpref_imports(ast.parse(src))) == [
        "acquisition", "active", "metrics", "models", "session", "strategies"]
