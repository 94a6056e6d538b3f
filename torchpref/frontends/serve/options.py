r"""``serve()``'s settings in groups, as BoTorch groups a model's: where it listens
(:class:`Listen`), each new session (:class:`~torchpref.frontends.serve.store.NewSessions`), the
open sessions (:class:`~torchpref.frontends.serve.pool.PoolLimits`), and how items given as a
tensor are shown (:class:`ServeItemsSpec`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from typing import Any

from torchpref.frontends.serve.pool import PoolLimits
from torchpref.frontends.serve.store import NewSessions

__all__ = ["Listen", "ServeItemsSpec", "grouped"]


@dataclass(frozen=True)
class Listen:
    """Where :func:`serve` listens: ``host`` and ``port`` (``port=0``: a free one); another host
    than the loopback needs ``allow_remote=True`` and a ``token`` (one is made and printed if not
    given)."""

    host: str = "127.0.0.1"
    port: int = 8000
    allow_remote: bool = False
    token: str | None = None


def grouped(
    settings: dict[str, object], new: NewSessions | None, listen: Listen | None, limits: PoolLimits | None
) -> tuple[NewSessions, Listen, PoolLimits]:
    """:func:`serve`'s keyword settings sorted into their groups, each overriding the group given.

    Raises:
        TypeError: a keyword of no group, naming it.
    """
    groups: list[Any] = [NewSessions, Listen, PoolLimits]
    given: list[Any] = [new, listen, limits]
    out = []
    for cls, group in zip(groups, given, strict=True):
        names = {f.name for f in fields(cls)}
        mine = {k: settings.pop(k) for k in list(settings) if k in names}
        out.append(replace(group if group is not None else cls(), **mine))
    if settings:
        raise TypeError(
            f"serve() got unexpected keyword argument(s) {', '.join(sorted(settings))}; its settings are "
            "those of NewSessions, Listen and PoolLimits."
        )
    return out[0], out[1], out[2]


@dataclass(frozen=True)
class ServeItemsSpec:
    """How :func:`serve` shows items given as a tensor or a session: their pictures, names and labels."""

    render: Callable | None = None
    names: list[str] | None = None
    labels: list[str] | None = None
    noun: str = "item"
