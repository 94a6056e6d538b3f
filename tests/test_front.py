"""The package's front: the lazily exported names, their type-checker imports and ``__all__`` agree."""

from __future__ import annotations

import ast
from pathlib import Path

import torchpref

INIT = Path(torchpref.__file__)


def _type_checking_imports() -> dict[str, str]:
    """name -> module (relative to torchpref) of each import under ``if TYPE_CHECKING:``."""
    out = {}
    for node in ast.parse(INIT.read_text()).body:
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            for imp in node.body:
                assert isinstance(imp, ast.ImportFrom), ast.dump(imp)
                for alias in imp.names:
                    out[alias.asname or alias.name] = imp.module.removeprefix("torchpref.")
    return out


def test_type_checking_imports_are_the_lazy_exports():
    assert _type_checking_imports() == torchpref._EXPORTS


def test_all_lists_every_export_once():
    assert sorted(torchpref.__all__) == sorted({*torchpref._EXPORTS, "__version__"})
    assert len(torchpref.__all__) == len(set(torchpref.__all__))


def test_every_export_resolves():
    missing = [name for name in torchpref._EXPORTS if getattr(torchpref, name, None) is None]
    assert not missing, missing
