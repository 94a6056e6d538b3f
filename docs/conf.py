"""Sphinx configuration of torchpref's documentation site (``make docs``).

Sphinx with autodoc, autosummary and napoleon reads the docstrings (Google style) of every public
module; MyST (myst-nb) reads the concept pages (Markdown, as on GitHub) and executes the
notebooks at build time; furo is the theme. Why Sphinx and not mkdocs: docs/install.md.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the checkout's package, also where it is not installed editable

import torchpref  # noqa: E402

project = "torchpref"
author = "The torchpref contributors"
copyright = "2026, The torchpref contributors"
release = version = torchpref.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "sphinx.ext.intersphinx",
    "myst_nb",
]
source_suffix = {
    ".rst": "restructuredtext",
    ".md": "myst-nb",
    ".ipynb": "myst-nb",
}  # .rst first: autosummary writes .rst
exclude_patterns = ["_build", "notebooks/.ipynb_checkpoints", "**/.ipynb_checkpoints"]
templates_path = ["_templates"]

html_theme = "furo"
html_title = f"torchpref {release}"

# --- API reference: a page per public module (written below), each object documented once, in
# the module that defines it (autodoc skips imported names)
autodoc_default_options = {"members": True, "show-inheritance": True, "ignore-module-all": True}
autodoc_member_order = "bysource"
# the integrations' libraries are optional extras, not installed to build the docs: stand-ins
autodoc_mock_imports = ["ax", "bofire", "pydantic"]
autodoc_typehints = "description"
autodoc_typehints_format = "short"
autodoc_inherit_docstrings = False  # BoTorch's and GPyTorch's docstrings are theirs to render
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False

intersphinx_mapping = {}  # the site is built offline; references to torch / BoTorch stay plain text

# --- Markdown and notebooks
myst_enable_extensions = ["dollarmath", "colon_fence"]
myst_heading_anchors = 3
nb_execution_mode = os.environ.get("TORCHPREF_DOCS_EXECUTE", "force")  # "off" for a quick build
nb_execution_timeout = 1800
nb_execution_raise_on_error = True
nb_merge_streams = True


STAGES = [
    ("Data", ["torchpref.data"]),
    ("Inference", ["torchpref.inference"]),
    ("Likelihoods", ["torchpref.likelihoods"]),
    ("Models", ["torchpref.models"]),
    ("Acquisition", ["torchpref.acquisition"]),
    ("Simulation", ["torchpref.simulation"]),
    ("Selection", ["torchpref.selection"]),
    ("Sessions", ["torchpref.sessions"]),
    ("Lake world", ["torchpref.lake"]),
    ("Experiments", ["torchpref.experiments"]),
    ("Front ends", ["torchpref.frontends"]),
    ("Integrations", ["torchpref.integrations"]),
    ("Testing helpers", ["torchpref.testing"]),
    ("Command line, demo, optional dependencies", ["torchpref.cli", "torchpref.demo", "torchpref.extras"]),
]


def _public_modules(name: str) -> list[str]:
    """``name`` and, for a package, its public submodules (no part starting with ``_``), sorted."""
    import importlib
    import pkgutil

    module = importlib.import_module(name)
    names = [name]
    if hasattr(module, "__path__"):
        names += sorted(
            m.name
            for m in pkgutil.walk_packages(module.__path__, f"{name}.")
            if not any(part.startswith("_") for part in m.name.split("."))
        )
    return names


def _write_if_changed(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` unless it holds it already (an unchanged page is not rebuilt)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if not path.exists() or path.read_text() != text:
        path.write_text(text)


def _write_api_pages() -> None:
    """``_generated/api/MODULE.rst`` for every public module and ``_generated/modules.md``, the
    toctrees of those pages by stage. A stage folder that does not exist (yet) is left out."""
    import importlib.util

    out = Path(__file__).parent / "_generated"
    lines = ["# Modules by stage", "", "Every public module of the package, in the order of its stages.", ""]
    for title, roots in STAGES:
        modules = [m for root in roots if importlib.util.find_spec(root) is not None for m in _public_modules(root)]
        if not modules:
            continue
        lines += [f"## {title}", "", "```{toctree}", ":maxdepth: 1", ""]
        lines += [f"/_generated/api/{m}" for m in modules] + ["```", ""]
        for m in modules:
            _write_if_changed(out / "api" / f"{m}.rst", f"{m}\n{'=' * len(m)}\n\n.. automodule:: {m}\n")
    _write_if_changed(out / "modules.md", "\n".join(lines))


def _write_public_names() -> None:
    """``_generated/public_names.md``: a table of every ``torchpref.X`` and the module defining it."""
    import importlib

    rows = ["| name | defined in |", "|---|---|"]
    for name in sorted(torchpref._EXPORTS, key=str.lower):
        obj = getattr(torchpref, name)
        module = getattr(obj, "__module__", None) if callable(obj) else None
        module = module or f"torchpref.{torchpref._EXPORTS[name]}"
        importlib.import_module(module)
        target = f"{module}.{name}"
        rows.append(f"| {{py:obj}}`torchpref.{name} <{target}>` | `{module}` |")
    out = Path(__file__).parent / "_generated"
    out.mkdir(exist_ok=True)
    text = "\n".join(rows) + "\n"
    path = out / "public_names.md"
    if not path.exists() or path.read_text() != text:  # unchanged: no rebuild of the pages that include it
        path.write_text(text)


_write_public_names()
_write_api_pages()

# Pygments' retry in relaxed mode after a literal block that is not strictly its language (the
# session file's example has "..." for elided values): cosmetic, the block is still shown.
suppress_warnings = ["misc.highlighting_failure"]
nb_execution_in_temp = True  # the notebooks run in a temporary folder: nothing is written into the checkout
