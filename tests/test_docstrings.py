"""Every public name of torchpref has a docstring, the top-level API annotates its parameters,
and ``--help`` texts are plain text.

Public: a module under ``torchpref`` whose name has no leading underscore, the names in its
``__all__`` (or, without one, its functions and classes defined there without a leading
underscore), and the public methods and properties a public class defines itself.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import pkgutil
import re

import pytest

import torchpref

SKIP_MODULES = {"torchpref.version"}  # only __version__


def _public_modules() -> list:
    names = ["torchpref"] + [
        m.name
        for m in pkgutil.walk_packages(torchpref.__path__, "torchpref.")
        if not any(part.startswith("_") for part in m.name.split("."))
    ]
    return [m for n in sorted(names) if n not in SKIP_MODULES and (m := _import(n)) is not None]


def _import(name: str):
    """The module, or ``None`` for an integration whose optional extra is not installed (its
    ImportError names the extra, ``pip install 'torchpref[...]'``)."""
    try:
        return importlib.import_module(name)
    except ImportError as err:
        if name.startswith("torchpref.integrations.") and "torchpref[" in str(err):
            return None
        raise


def _public_objects(module) -> list[tuple[str, object]]:
    if hasattr(module, "__all__"):
        names = [n for n in module.__all__ if not n.startswith("_")]
    else:
        names = [
            n
            for n, v in vars(module).items()
            if not n.startswith("_")
            and (inspect.isfunction(v) or inspect.isclass(v))
            and v.__module__ == module.__name__
        ]
    return [(f"{module.__name__}.{n}", getattr(module, n)) for n in names]


def _own_members(cls) -> list[tuple[str, object]]:
    out = []
    for name, value in vars(cls).items():
        if name.startswith("_") or inspect.isclass(value):
            continue
        if isinstance(value, (staticmethod, classmethod)):
            value = value.__func__
        if inspect.isfunction(value) or isinstance(value, property):
            # an override of a documented base-class method inherits its contract
            inherited = any(getattr(getattr(base, name, None), "__doc__", None) for base in cls.__mro__[1:])
            if not inherited:
                out.append((f"{cls.__module__}.{cls.__qualname__}.{name}", value))
    return out


def _undocumented() -> list[str]:
    missing, seen = [], set()
    for module in _public_modules():
        if not (module.__doc__ or "").strip():
            missing.append(module.__name__)
        for qualname, obj in _public_objects(module):
            if not (inspect.isfunction(obj) or inspect.isclass(obj)) or id(obj) in seen:
                continue  # constants and type aliases: documented where they are defined
            seen.add(id(obj))
            if not (obj.__doc__ or "").strip():
                missing.append(qualname)
            if inspect.isclass(obj) and obj.__module__.startswith("torchpref"):
                missing += [q for q, member in _own_members(obj) if not (member.__doc__ or "").strip()]
    return missing


def test_public_modules_are_found():
    names = {m.__name__ for m in _public_modules()}
    assert {
        "torchpref",
        "torchpref.models.preference_gp",
        "torchpref.sessions.session",
        "torchpref.frontends.widgets",
        "torchpref.lake",
    } <= names


def test_every_public_name_has_a_docstring():
    missing = _undocumented()
    assert not missing, f"{len(missing)} public names without a docstring:\n" + "\n".join(missing)


def _unannotated(functions) -> list[str]:
    out = []
    for qualname, f in functions:
        f = getattr(f, "fget", None) or getattr(f, "__func__", f)
        if not inspect.isfunction(f):
            continue
        missing = [
            p.name
            for p in inspect.signature(f).parameters.values()
            if p.name not in ("self", "cls")
            and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
            and p.annotation is inspect.Parameter.empty
        ]
        if missing:
            out.append(f"{qualname}: {', '.join(missing)}")
    return out


TYPED_MODULES = ("torchpref", "torchpref.frontends.widgets")


def test_top_level_api_annotates_its_parameters():
    functions = []
    for module in map(importlib.import_module, TYPED_MODULES):
        for qualname, obj in _public_objects(module):
            if inspect.isfunction(obj):
                functions.append((qualname, obj))
            elif inspect.isclass(obj):
                functions += [
                    (f"{qualname}.{n}", v) for n, v in vars(obj).items() if n == "__init__" or not n.startswith("_")
                ]
    missing = _unannotated(functions)
    assert not missing, "parameters without a type annotation:\n" + "\n".join(missing)


def test_the_walker_sees_a_missing_annotation():
    def f(a, b: int, *args, **kwargs):
        pass

    assert _unannotated([("f", f)]) == ["f: a"]


def test_the_walker_sees_a_missing_docstring():
    class Undocumented:
        def method(self):
            pass

    assert [q for q, _ in _own_members(Undocumented)] == [f"{__name__}.{Undocumented.__qualname__}.method"]


def _parsers(parser: argparse.ArgumentParser):
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from _parsers(sub)


RST = re.compile(r"``|:class:|:func:|:meth:|:data:|:attr:")


def test_cli_help_texts_have_no_rst_markup():
    from torchpref.cli import build_parser

    parsers = list(_parsers(build_parser()))
    assert len(parsers) >= 5  # torchpref, reproduce, reproduce wave / lake, elicit
    for p in parsers:
        text = p.format_help()
        assert not RST.search(text), f"{p.prog}:\n{text}"


def test_demo_help_has_no_rst_markup(capsys):
    from torchpref.demo import main

    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert "--out" in text and not RST.search(text), text
