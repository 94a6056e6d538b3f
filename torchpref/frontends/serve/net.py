r"""The network side of ``torchpref serve``: the listening socket (a busy port named with the way
out), uvicorn with deadlines for slow clients and a bound on connections, and ``ready`` called once
the server accepts connections."""

from __future__ import annotations

import asyncio
import errno
import socket
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, TypeVar

if TYPE_CHECKING:  # starlette and uvicorn are the serve extra: imported where used
    import uvicorn
    from starlette.types import ASGIApp

HEADER_TIMEOUT_S = 15.0
"""A connection must send a request's headers within this many seconds (else it is closed)."""
MAX_CONNECTIONS = 200
"""Connections served at once; more get ``503``."""


class ServeError(ValueError):
    """Settings ``serve`` cannot run with (another interface without a token, a bad port)."""


T = TypeVar("T")


def _with_cpu(fn: Callable[..., T], *args: object) -> tuple[T, float]:
    """``fn(*args)`` and the CPU seconds this thread spent in it (a request's own work, whatever
    the other threads do meanwhile)."""
    start = time.thread_time()
    return fn(*args), time.thread_time() - start


def _shown_host(host: str) -> str:
    """``host`` as a URL and a ``Host`` header name it (an IPv6 address in brackets)."""
    return f"[{host}]" if ":" in host else host


def listening_socket(host: str, port: int) -> socket.socket:
    """A socket bound to ``(host, port)`` (``port`` 0: a free one).

    Raises:
        ServeError: the port is in use or the address cannot be bound, naming it and ``--port 0``.
    """

    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as err:
        sock.close()
        where = f"{_shown_host(host)}:{port}"
        if err.errno == errno.EADDRINUSE:
            raise ServeError(
                f"port {port} on {host} is in use (another server?): choose another with --port N, "
                "or --port 0 for a free one (the link is printed)."
            ) from None
        raise ServeError(f"cannot listen on {where}: {err.strerror or err}.") from None
    return sock


def _timed_protocol():
    """uvicorn's h11 protocol with a deadline for each request's headers: a client that connects
    and sends nothing, or its headers a byte at a time, is disconnected after
    :data:`HEADER_TIMEOUT_S` (uvicorn times out only idle keep-alive connections)."""
    from uvicorn.protocols.http.h11_impl import H11Protocol

    class TimedH11Protocol(H11Protocol):
        _header_timer: asyncio.TimerHandle | None = None

        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            self._arm()

        def _arm(self) -> None:
            if self._header_timer is None:
                self._header_timer = self.loop.call_later(HEADER_TIMEOUT_S, self._too_slow)

        def _disarm(self) -> None:
            if self._header_timer is not None:
                self._header_timer.cancel()
                self._header_timer = None

        def data_received(self, data: bytes) -> None:
            if self.cycle is None or self.cycle.response_complete:  # waiting for a request's headers
                self._arm()
            super().data_received(data)
            if self.cycle is not None and not self.cycle.response_complete:
                self._disarm()  # the headers are in; the body has its own deadline (BODY_TIMEOUT_S)

        def connection_lost(self, exc) -> None:
            self._disarm()
            super().connection_lost(exc)

        def _too_slow(self) -> None:
            self._header_timer = None
            if not self.transport.is_closing() and (self.cycle is None or self.cycle.response_complete):
                self.transport.close()

    return TimedH11Protocol


def uvicorn_server(app: ASGIApp, ready: Callable[[], None] | None = None) -> uvicorn.Server:
    """The uvicorn server of ``app``: one event loop, h11 with header deadlines
    (:func:`_timed_protocol`), at most :data:`MAX_CONNECTIONS` at once; ``ready()`` is called (in
    a thread of its own) once it accepts connections."""
    import uvicorn

    class Server(uvicorn.Server):
        async def startup(self, sockets=None) -> None:
            await super().startup(sockets=sockets)
            if self.started and ready is not None:
                threading.Thread(target=ready, name="torchpref-serve-ready", daemon=True).start()

    config = uvicorn.Config(
        app,
        log_level="warning",
        access_log=False,
        lifespan="off",
        http=_timed_protocol(),
        limit_concurrency=MAX_CONNECTIONS,
        timeout_keep_alive=5,
    )
    return Server(config)


def _run_uvicorn(app, sock, host: str, token: str | None, ready, path: str = "") -> None:
    bound = sock.getsockname()[1]
    url = f"http://{_shown_host(host)}:{bound}/{path}" + (f"?token={token}" if token else "")

    def listening() -> None:
        print(f"torchpref serve: open {url}  (Ctrl-C stops; every answer is already saved)", flush=True)
        if ready is not None:
            ready(url)

    uvicorn_server(app, listening).run(sockets=[sock])
