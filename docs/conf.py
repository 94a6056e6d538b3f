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
copyright = "2026, The torchpref contributors"  # noqa: A001
release = version = torchpref.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "sphinx.ext.intersphinx",
    "myst_nb",
]
source_suffix = {".md": "myst-nb", ".ipynb": "myst-nb"}
exclude_patterns = ["_build", "notebooks/.ipynb_checkpoints", "**/.ipynb_checkpoints"]
templates_path = ["_templates"]

html_theme = "furo"
html_title = f"torchpref {release}"

# --- API reference: every public module, each object documented once, where it is defined
autosummary_generate = True
autosummary_imported_members = False
autodoc_default_options = {"members": True, "show-inheritance": True, "ignore-module-all": True}
autodoc_member_order = "bysource"
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
