"""The package's layout stays as docs/architecture.md describes it: subpackages by stage, each
importing only the stages below it (any import, at module level or inside a function), no import
cycle among the modules (module-level imports), no module over 600 lines (the exceptions: :data:`LONG_MODULES`) and no function over 60 lines of code (ruff-formatted),
and the lake world (``torchpref/lake/``) imports nothing of learning (the model, the loop, the
selectors, the metrics) from the rest of the package."""

import ast
from pathlib import Path

import torchpref

PACKAGE = Path(torchpref.__file__).parent
MAX_MODULE_LINES = 600  # a guard against files that should be split, not a goal (formatted by ruff)
#: One class, one file, as BoTorch keeps ``PairwiseGP`` in ``pairwise_gp.py``: the model's data,
#: predictives and BoTorch interface are one class, not mixins split by a size rule (issue 35).
# one class in one file: PreferenceGP, and PreferenceSession (its file, its model cache and its query list)
# and the command line: every command's parser and dispatch in one place, as argparse programs keep them
LONG_MODULES = {"models/preference_gp.py": 1200, "sessions/session.py": 900, "cli.py": 700}
MAX_FUNCTION_LINES = 60  # code lines: the docstring does not count

# What a module of torchpref/lake/ may import from the rest of torchpref: the data conventions
# (Likert levels) and numerical helpers; never a model, a selector, the loop or the metrics.
LAKE_MAY_IMPORT = {"data", "inference"}
LAKE_MAY_IMPORT_MODULES = {"torchpref.data.preference_data", "torchpref.inference.numerics", "torchpref.extras"}

# The stages, lowest first: a module may import its own stage and those below it, never one above.
# The top-level modules (the package's front, the command line, the demo) may import everything;
# ``version`` and ``extras`` (the optional dependencies' messages) are the floor.
LAYERS = [
    "version",
    "extras",
    "data",
    "inference",
    "likelihoods",
    "models",
    "population",
    "acquisition",
    "simulation",
    "selection",
    "sessions",
    "lake",
    "experiments",
    "frontends",
    "study",
    "integrations",
    "testing",
]
TOP = {"__init__", "cli", "demo", "serve"}


def _modules() -> list[Path]:
    return sorted(PACKAGE.rglob("*.py"))


def _name(f: Path) -> str:
    return f.relative_to(PACKAGE).as_posix()


def test_no_module_over_the_limit():
    long = {
        _name(f): n
        for f in _modules()
        if (n := len(f.read_text().splitlines())) > LONG_MODULES.get(_name(f), MAX_MODULE_LINES)
    }
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


def test_no_function_over_the_limit():
    long = []
    for f in _modules():
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                first = node.body[0]
                if (
                    isinstance(first, ast.Expr)
                    and isinstance(first.value, ast.Constant)
                    and isinstance(first.value.value, str)
                ):
                    n -= first.end_lineno - first.lineno + 1  # the docstring
                if n > MAX_FUNCTION_LINES:
                    long.append(f"{_name(f)}:{node.lineno} {node.name} ({n} lines)")
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines:\n" + "\n".join(long)


def _module_imports(f: Path) -> set[str]:
    """The torchpref modules ``f`` imports at module level (not inside functions), type-only imports
    (``if TYPE_CHECKING:``) included, as dotted names."""
    package = "torchpref." + ".".join(f.relative_to(PACKAGE).with_suffix("").parts[:-1])
    package = package.rstrip(".")
    out = set()
    body = ast.parse(f.read_text()).body
    # type-only imports count too: a cycle that only type checkers follow is still a cycle
    body += [n for node in body if _is_type_checking(node) for n in node.body]
    for node in body:
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


def _is_type_checking(node: ast.stmt) -> bool:
    """``if TYPE_CHECKING:`` (or ``typing.TYPE_CHECKING``)."""
    if not isinstance(node, ast.If):
        return False
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


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
            return path[path.index(m) :] + [m]
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
    graph = {
        f"torchpref.{_name(f)[:-3].replace('/', '.')}".removesuffix(".__init__"): _module_imports(f) for f in _modules()
    }
    assert {"torchpref.models.preference_gp", "torchpref.lake.field"} <= graph["torchpref.sessions.settings"] | graph[
        "torchpref.lake.plan"
    ] | graph["torchpref.lake.planners"], "is the walk blind?"
    cycle = _cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_the_cycle_search_finds_one():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None


def _all_imports(f: Path, source: str | None = None) -> list[tuple[str, int]]:
    """Every torchpref module ``f`` (or ``source``, read as if it were ``f``) imports, anywhere in
    the file, as ``(dotted name, line)``."""
    package = "torchpref." + ".".join(f.relative_to(PACKAGE).with_suffix("").parts[:-1])
    package = package.rstrip(".")
    out = []
    for node in ast.walk(ast.parse(f.read_text() if source is None else source)):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module or ""
            if module == "torchpref":
                out += [(f"torchpref.{a.name}", node.lineno) for a in node.names]
            elif module.startswith("torchpref."):
                out.append((module, node.lineno))
        elif isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names if a.name.startswith("torchpref.")]
    return out


def test_imports_anywhere_form_no_cycle():
    """Imports inside functions count too: a cycle that only a function-level import closes still
    ties the modules together (the top level, which imports every stage on first use, aside)."""

    def module(dotted: str) -> str | None:
        while dotted.count(".") >= 1:
            if _path(dotted) is not None:
                return dotted
            dotted = dotted.rsplit(".", 1)[0]
        return None

    graph: dict[str, set[str]] = {}
    for f in _modules():
        if f.parent == PACKAGE:
            continue
        name = f"torchpref.{_name(f)[:-3].replace('/', '.')}".removesuffix(".__init__")
        targets = {module(d) for d, _ in _all_imports(f)}
        graph[name] = {t for t in targets if t is not None and t != name and t.count(".") >= 1}
    assert "torchpref.frontends.serve.summary" in graph, "is the walk blind?"
    cycle = _cycle(graph)
    assert cycle is None, "import cycle (imports inside functions included): " + " -> ".join(cycle)


def _stage(dotted: str) -> str:
    return dotted.split(".")[1]


def test_every_module_is_in_a_stage():
    stray = [_name(f) for f in _modules() if f.parent == PACKAGE and f.stem not in TOP | {"version", "extras"}]
    stray += [_name(f) for f in _modules() if f.parent != PACKAGE and f.relative_to(PACKAGE).parts[0] not in LAYERS]
    assert not stray, f"modules outside the stages of docs/architecture.md: {stray}"


def test_no_module_imports_a_stage_above_its_own():
    bad = []
    for f in _modules():
        here = f.relative_to(PACKAGE).parts[0].removesuffix(".py")
        if here in TOP:
            continue
        for dotted, line in _all_imports(f):
            there = _stage(dotted)
            if there in TOP or (there in LAYERS and LAYERS.index(there) > LAYERS.index(here)):
                bad.append(f"{_name(f)}:{line} imports {dotted} ({there} is above {here})")
    assert not bad, "\n".join(bad)


def test_the_lake_world_imports_only_data_and_numerics():
    bad = [
        f"{f.name}:{line} imports {dotted}"
        for f in sorted((PACKAGE / "lake").glob("*.py"))
        for dotted, line in _all_imports(f)
        if not dotted.startswith("torchpref.lake") and dotted not in LAKE_MAY_IMPORT_MODULES
    ]
    assert not bad, "\n".join(bad)


def test_the_import_walk_sees_every_form():
    src = (
        "from ..models.batch import BatchedPreferenceGP\nfrom .. import data\nimport torchpref.simulation.metrics\n"
        "from torchpref import sessions\nfrom .field import x\n"
        "def f():\n    from torchpref.acquisition.functions import item_ucb\n"
    )
    found = _all_imports(PACKAGE / "lake" / "probe.py", src)
    assert sorted(found) == [
        ("torchpref.acquisition.functions", 7),
        ("torchpref.data", 2),
        ("torchpref.lake.field", 5),
        ("torchpref.models.batch", 1),
        ("torchpref.sessions", 4),
        ("torchpref.simulation.metrics", 3),
    ]
