r"""``torchpref serve``: the browser page a person answers in (docs/serve.md).

The pieces, each imported only by the ones after it:

* ``errors``: :class:`AnswerRefused` (an answer the page refuses, with its HTTP status);
* ``items``: the items served and their pictures (a features CSV, the lake);
* ``net``: the network policy (loopback, hosts, tokens, connection limits);
* ``pool``: the open sessions, bounded (files, memory), evicted least recently used;
* ``plot_worker`` / ``summary`` / ``plots``: the summary's utility plot, drawn in a worker process;
* ``store``: :class:`SessionStore`, every participant's session: the one way an answer enters;
* ``options``: ``serve()``'s settings in groups (:class:`Listen`, ``NewSessions``, ``PoolLimits``);
* ``app``: the Starlette application, :func:`serve`, :func:`serve_store` and :func:`create_app`.
"""

from __future__ import annotations

from torchpref.frontends.serve.app import Listen, ServeError, create_app, run, serve
from torchpref.frontends.serve.pool import PoolLimits
from torchpref.frontends.serve.store import NewSessions

__all__ = ["Listen", "NewSessions", "PoolLimits", "ServeError", "create_app", "run", "serve"]
