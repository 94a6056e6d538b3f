r"""Where a population's shards live and run: in this process, on any
``concurrent.futures.Executor``, or on a Dask cluster, behind one small interface (:class:`Host`)
that the joint Newton loop (:mod:`torchpref.population.joint`) runs over.

* :class:`InProcess`: the shards' states are objects here; each function is called directly.
* :class:`OnExecutor`: each call is submitted to the executor with the shard's state as an
  argument and its new state comes back: free on a thread pool (shared memory), but a process
  pool copies every state both ways on every round (counted in :class:`Traffic`).
* :class:`OnDask`: each shard's state stays on its Dask worker (a future); a call sends only its
  small arguments and the master gathers only the :class:`~torchpref.population.shards.Summary`
  (``O(M^2)`` numbers per shard per Newton step). ``fit_population(executor=client.get_executor())``
  and ``executor=client`` both run here.

:class:`Traffic` counts the bytes of the tensors that cross between the master and the shards
(for :class:`InProcess`, those that would cross if the shards were elsewhere): the figure the
cost model of docs/population.md is built on.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass, fields, is_dataclass
from typing import Any, Protocol

from gpytorch.module import Module
from torch import Tensor

from torchpref.population.shards import summary_of


def nbytes(obj: object) -> int:
    """The bytes of the tensors (and 8 per number) in ``obj``: dataclasses, sequences, mappings
    and modules (their ``state_dict``) walked; anything else counts 0."""
    if isinstance(obj, Tensor):
        return obj.numel() * obj.element_size()
    if isinstance(obj, Module):
        return sum(nbytes(t) for t in obj.state_dict().values())
    if is_dataclass(obj) and not isinstance(obj, type):
        return sum(nbytes(getattr(obj, f.name)) for f in fields(obj))
    if isinstance(obj, (list, tuple)):
        return sum(nbytes(x) for x in obj)
    if isinstance(obj, dict):
        return sum(nbytes(x) for x in obj.values())
    return 8 if isinstance(obj, (int, float)) else 0


@dataclass
class Traffic:
    """Bytes sent to the shards and received from them, and the number of rounds."""

    sent: int = 0
    received: int = 0
    rounds: int = 0

    @property
    def total(self) -> int:
        """Bytes both ways."""
        return self.sent + self.received


class Host(Protocol):
    """Where the shards live: ``place`` them, ``map`` a function over their states (the new states
    stay where the shards are), ``gather`` a function's (small) results here."""

    traffic: Traffic
    remote: bool

    def place(self, data: Sequence[object]) -> list[object]:
        """Put each shard's data where the shards live; returns a handle per shard."""

    def map(self, fn: Callable[..., object], handles: Sequence[object], *shared: object) -> list[object]:
        """Call ``fn(state, *shared)`` on every shard; the new states stay where the shards are."""

    def gather(self, fn: Callable[..., object], handles: Sequence[object], *shared: object) -> list[Any]:
        """Call ``fn(state, *shared)`` on every shard and bring each (small) result here."""

    def total(self, fn: Callable[..., object], handles: Sequence[object], *shared: object) -> Any:
        """The sum over the shards of ``fn(state, *shared)``, brought here."""


def sum_or_none(parts: Sequence[Any]) -> Any:
    """The sum of ``parts``, or ``None`` if any is ``None``."""
    if any(p is None for p in parts):
        return None
    return sum(parts[1:], parts[0])


class InProcess:
    """The shards in this process: each function called directly on each state in turn."""

    #: Whether a round trip to the shards costs (a network's or a scheduler's latency): then the
    #: master asks for a point's summary and its part of ``S`` in one round.
    remote = False

    def __init__(self) -> None:
        self.traffic = Traffic()

    def place(self, data: Sequence[object]) -> list[object]:
        """The shards' data as they are (this process holds them)."""
        self.traffic.sent += nbytes(list(data))
        return list(data)

    def map(self, fn: Callable[..., object], handles: Sequence[object], *shared: object) -> list[object]:
        """``fn`` on each state in turn, here."""
        self.traffic.sent += len(handles) * nbytes(shared)
        self.traffic.rounds += 1
        return [fn(h, *shared) for h in handles]

    def gather(self, fn: Callable[..., object], handles: Sequence[object], *shared: object) -> list[Any]:
        """``fn`` on each state in turn, here; its results."""
        out = self.map(fn, handles, *shared)
        self.traffic.received += nbytes(out)
        return out

    def total(self, fn: Callable[..., object], handles: Sequence[object], *shared: object) -> Any:
        """The sum of ``fn``'s results (``None`` if one is), added up as they come: one at a time here."""
        self.traffic.sent += len(handles) * nbytes(shared)
        self.traffic.rounds += 1
        out: Any = None
        for h in handles:
            part: Any = fn(h, *shared)
            if part is None:
                return None
            self.traffic.received += nbytes(part)
            out = part if out is None else out + part
        return out


class OnExecutor(InProcess):
    """The shards' calls on a ``concurrent.futures.Executor``, their states passed along (copied
    both ways by a process pool, shared by a thread pool)."""

    def __init__(self, executor: Executor):
        super().__init__()
        self.executor = executor
        self.copies = not isinstance(executor, ThreadPoolExecutor)

    def map(self, fn: Callable[..., object], handles: Sequence[object], *shared: object) -> list[object]:
        """``fn`` on every state through the executor."""
        self.traffic.sent += len(handles) * nbytes(shared) + (nbytes(list(handles)) if self.copies else 0)
        self.traffic.rounds += 1
        futures = [self.executor.submit(fn, h, *shared) for h in handles]
        out = [f.result() for f in futures]
        self.traffic.received += nbytes(out) if self.copies else 0
        return out

    def gather(self, fn: Callable[..., object], handles: Sequence[object], *shared: object) -> list[Any]:
        """``fn`` on every state through the executor; its results brought back."""
        out = self.map(fn, handles, *shared)
        self.traffic.received += 0 if self.copies else nbytes(out)
        return out

    def total(self, fn: Callable[..., object], handles: Sequence[object], *shared: object) -> Any:
        return sum_or_none(self.gather(fn, handles, *shared))


class OnDask:
    """The shards on a Dask cluster, each pinned to a worker (round robin), its state kept there
    as a future; only calls' small arguments and gathered results cross."""

    remote = True

    def __init__(self, client: Any):
        self.client = client
        self.traffic = Traffic()
        self.workers = list(client.scheduler_info(n_workers=-1)["workers"])
        if not self.workers:
            raise ValueError("the Dask client has no workers to place the population's shards on.")
        self._where: list[str] = []

    def place(self, data: Sequence[object]) -> list[object]:
        """Scatter the shards' data to the Dask workers; a future per shard."""
        self.traffic.sent += nbytes(list(data))
        self._where = [self.workers[i % len(self.workers)] for i in range(len(data))]
        return [self.client.scatter(d, workers=[w], hash=False) for d, w in zip(data, self._where)]

    def map(self, fn: Callable[..., object], handles: Sequence[object], *shared: object) -> list[object]:
        """``fn`` on every shard on its worker; the new states stay there (futures)."""
        self.traffic.sent += len(handles) * nbytes(shared)
        self.traffic.rounds += 1
        return [
            self.client.submit(fn, h, *shared, pure=False, workers=[w], allow_other_workers=False)
            for h, w in zip(handles, self._where)
        ]

    def gather(self, fn: Callable[..., object], handles: Sequence[object], *shared: object) -> list[Any]:
        """``fn`` on every shard on its worker; the results brought back."""
        out = self.client.gather(self.map(fn, handles, *shared))
        self.traffic.received += nbytes(out)
        return out

    def total(self, fn: Callable[..., object], handles: Sequence[object], *shared: object) -> Any:
        """The sum of ``fn`` over the shards, reduced on the workers and brought back."""
        return sum_or_none(self.gather(fn, handles, *shared))


def summaries(host: Host, handles: Sequence[Any]) -> list[Any]:
    """The shards' summaries, brought here (a round of its own only where the states are remote)."""
    if isinstance(host, OnDask):
        return host.gather(summary_of, handles)
    out = [h.summary for h in handles]
    host.traffic.received += 0 if getattr(host, "copies", False) else nbytes(out)  # copied states: counted
    return out


def _dask_client(executor: object) -> Any:
    """The Dask client behind ``executor`` (a ``distributed.Client`` or its ``get_executor()``), or
    ``None``. Dask's executor brings every result back to the caller, which would send each shard's
    state here on every round, so its client is used directly."""
    kind = type(executor)
    if not kind.__module__.startswith("distributed"):
        return None
    if kind.__name__ == "Client":
        return executor
    return getattr(executor, "_client", None)  # distributed.cfexecutor.ClientExecutor keeps it there


def host_for(executor: object) -> Host:
    """The :class:`Host` for ``fit_population``'s ``executor`` (``None``: this process)."""
    if executor is None:
        return InProcess()
    client = _dask_client(executor)
    if client is not None:
        return OnDask(client)
    if not isinstance(executor, Executor):
        raise ValueError(
            f"executor must be a concurrent.futures.Executor or a Dask client, got {type(executor).__name__}."
        )
    return OnExecutor(executor)


def workers_of(executor: object) -> int | None:
    """How many workers ``executor`` says it has, where it says."""
    client = _dask_client(executor)
    if client is not None:
        return len(client.scheduler_info(n_workers=-1)["workers"])
    count = getattr(executor, "_max_workers", None)  # concurrent.futures' pools
    return count if isinstance(count, int) else None
