"""The package's layout stays as docs/architecture.md describes it: no module of ``torchpref``
over 450 lines, no function over 60, no import cycle among the modules (module-level imports),
and the lake world (``torchpref/lake/``) imports nothing of learning (the model, the loop, the
selectors, the metrics) from the rest of the package."""

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


def _module_imports(f: Path) -> set[str]:
    """The torchpref modules ``f`` imports at module level (not inside functions), as dotted names."""
    package = "torchpref." + ".".join(f.relative_to(PACKAGE).with_suffix("").parts[:-1])
    package = package.rstrip(".")
    out = set()
    for node in ast.parse(f.read_text()).body:
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module or ""
            names = [module] + [f"{module}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        else:
            continue
        out |= {n for n in names if n.startswith("torchpref.") and _path(n) is not None}
    return out


def _path(dotted: str) -> Path | None:
    """The file of module ``dotted`` (a package's ``__init__.py``), or ``None`` if it is not one."""
    base = PACKAGE.joinpath(*dotted.split(".")[1:])
    for p in (base.with_suffix(".py"), base / "__init__.py"):
        if p.is_file():
            return p
    return None


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """An import cycle of ``graph`` (module -> modules it imports) as a path, or ``None``."""
    done, path = set(), []

    def visit(m: str) -> list[str] | None:
        if m in path:
            return path[path.index(m):] + [m]
        if m in done:
            return None
        path.append(m)
        for n in sorted(graph.get(m, ())):
            if (found := visit(n)) is not None:
                return found
        path.pop()
        done.add(m)
        return None

    for m in sorted(graph):
        if (found := visit(m)) is not None:
            return found
    return None


def test_module_level_imports_form_no_cycle():
    graph = {f"torchpref.{_name(f)[:-3].replace('/', '.')}".removesuffix(".__init__"): _module_imports(f)
             for f in _modules()}
    assert {"torchpref.models", "torchpref.lake.field"} <= graph["torchpref.session_settings"] | graph[
        "torchpref.lake.plan"] | graph["torchpref.lake.planners"], "is the walk blind?"
    cycle = _cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_the_cycle_search_finds_one():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None
