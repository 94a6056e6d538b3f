r"""``torchpref serve``: the browser page a person answers in, with their response times.

    torchpref serve --features items.csv [--image-column COL [--image-dir DIR]] [--sessions DIR]
    torchpref serve lake [--sessions DIR]
    torchpref.serve(items_or_session, render=..., ...)          # from Python

A small Starlette application (run by uvicorn; Jinja2 templates, plain JavaScript, no build
step; the ``serve`` extra). Each visitor of ``/`` starts a session of their own, a link
``/s/SID/`` whose file is ``SESSIONS/SID.session.jsonl``; the page asks one question at a time
(a rating with buttons and keys ``1..K``, or the best of ``m`` side by side, keys ``A..`` or
``1..m``, ``0`` or ``=`` for "no preference"), undoes (``U``), shows the progress and the item
the model recommends now, and ends on a summary (the learned utility over two objectives, the
best items, downloads of the session file, the answers as CSV and the model checkpoint).

An answer is acknowledged only once it is in the session file (fsynced:
:class:`~torchpref.PreferenceSession`); the page measures the seconds from showing a question to
its answer and the journal keeps them (``response_time``). Stale, repeated and foreign answers
are refused by :class:`~torchpref.frontends.serve.store.SessionStore`.

Safe by default: it binds 127.0.0.1 and answers only requests whose ``Host`` is this machine's
loopback name (no DNS rebinding); another interface needs ``allow_remote=True`` and a token
(the link's ``?token=`` sets a cookie); requests that change a session must be same-origin JSON;
pictures are served by item number only. See ``docs/serve.md``.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import hmac
import inspect
import ipaddress
import json
import secrets
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from torch import Tensor

from torchpref.frontends.serve.items import ServeItems, items_from_csv, lake_items
from torchpref.frontends.serve.net import (  # noqa: F401  (HEADER_TIMEOUT_S, MAX_CONNECTIONS: re-exported)
    HEADER_TIMEOUT_S,
    MAX_CONNECTIONS,
    ServeError,
    _run_uvicorn,
    _shown_host,
    _with_cpu,
    listening_socket,
    uvicorn_server,
)
from torchpref.frontends.serve.options import Listen, ServeItemsSpec, grouped
from torchpref.frontends.serve.pool import PoolLimits
from torchpref.frontends.serve.store import AnswerRefused, NewSessions, SessionStore
from torchpref.sessions.session import PreferenceSession

__all__ = ["Listen", "NewSessions", "PoolLimits", "ServeError", "ServeItemsSpec", "create_app", "run", "serve"]

HERE = Path(__file__).parent
MAX_BODY = 4096
BODY_TIMEOUT_S = 15.0
"""A request's body must arrive within this many seconds (else ``408``)."""
TOKEN_COOKIE = "torchpref_token"
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")
HEADERS = {
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",  # the session id is in the link
    "X-Frame-Options": "DENY",
    "Content-Security-Policy": "default-src 'self'; img-src 'self'; object-src 'none'; frame-ancestors 'none'",
    "Cache-Control": "no-store",
}


def _require() -> None:
    """Import the ``serve`` extra's modules, or raise :class:`~torchpref.extras.MissingExtraError`
    (an ``ImportError``) naming ``torchpref[serve]``."""
    from torchpref.extras import require

    for module in ("starlette", "uvicorn", "jinja2"):
        require(module, "torchpref serve", extra="serve")


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def create_app(
    store: SessionStore,
    *,
    token: str | None = None,
    allowed_hosts: list[str] | None = None,
    extra_routes: list | None = None,
) -> _Guard:
    """The ASGI application over ``store`` (Starlette, wrapped in the Host / token / headers guard).

    Args:
        store: the sessions (:class:`~torchpref.frontends.serve.store.SessionStore`).
        token: if given, every request must carry it (``?token=`` once, then a cookie).
        allowed_hosts: the host names a request's ``Host`` may name (default: the loopback names);
            ``["*"]`` for any (only with a token).
        extra_routes: more Starlette routes (the study's experimenter page), before the static files.
    """
    _require()
    from starlette.applications import Starlette
    from starlette.responses import RedirectResponse
    from starlette.routing import Mount, Route
    from starlette.staticfiles import StaticFiles

    h = _Handlers(store)
    routes = [
        Route("/", h.wrap(h.index)),
        Route("/api/new", h.wrap(h.new), methods=["POST"]),
        Route("/picture/{index}", h.wrap(h.picture)),
        Route("/s/{sid}", lambda r: RedirectResponse(f"{r.path_params['sid']}/", 307)),
        Route("/s/{sid}/", h.wrap(h.question_page)),
        Route("/s/{sid}/state", h.wrap(h.state)),
        Route("/s/{sid}/answer", h.wrap(h.answer), methods=["POST"]),
        Route("/s/{sid}/undo", h.wrap(h.undo), methods=["POST"]),
        Route("/s/{sid}/summary", h.wrap(h.summary)),
        Route("/s/{sid}/utility.png", h.wrap(h.utility_png)),
        Route("/s/{sid}/download/{what}", h.wrap(h.download)),
        Route("/favicon.ico", _favicon),
        *(extra_routes or []),
        Mount("/static", StaticFiles(directory=HERE / "static"), name="static"),
    ]
    app = Starlette(routes=routes, exception_handlers={404: h.not_found})
    app.state.store = store
    hosts = list(LOOPBACK_NAMES) if allowed_hosts is None else list(allowed_hosts)
    return _Guard(app, token, hosts)


def _favicon(request):
    """The page's icon (browsers ask for ``/favicon.ico`` on every page)."""
    from starlette.responses import Response

    data = (HERE / "static" / "favicon.ico").read_bytes()
    return Response(data, media_type="image/x-icon", headers={"Cache-Control": "public, max-age=86400"})


class _Handlers:
    """The routes' handlers over one store. Blocking work (the model, the file) runs in
    Starlette's thread pool; a refused request becomes a JSON error (or an HTML page for a
    browser's GET) with its status."""

    def __init__(self, store: SessionStore):
        import jinja2

        self.store = store
        self.env = jinja2.Environment(loader=jinja2.FileSystemLoader(HERE / "templates"), autoescape=True)

    def page(self, name: str, status: int = 200, headers: dict | None = None, **ctx):
        from starlette.responses import HTMLResponse

        return HTMLResponse(self.env.get_template(name).render(**ctx), status_code=status, headers=headers)

    def wrap(self, fn):
        from starlette.concurrency import run_in_threadpool
        from starlette.responses import JSONResponse

        async def wrapped(request):
            try:
                try:
                    if inspect.iscoroutinefunction(fn):
                        return await fn(request)
                    return await run_in_threadpool(fn, request)
                except (MemoryError, OSError, RuntimeError) as exc:  # out of memory or files: 503, else re-raised
                    raise self.store.pool.as_busy(exc) from None
            except AnswerRefused as err:
                retry = getattr(err, "retry_after", None)  # ServerBusy (503): out of descriptors or memory
                if retry is None and err.status in (503, 507):  # a full disk, a file changed under a session
                    retry = 5
                headers = {"Retry-After": str(retry)} if retry is not None else None
                if request.method == "GET" and "text/html" in request.headers.get("accept", ""):
                    return self.page("error.html", err.status, message=str(err), headers=headers)
                return JSONResponse({"error": str(err), "state": err.state}, status_code=err.status, headers=headers)

        return wrapped

    async def json_body(self, request) -> object:
        """The request's JSON, if it is same-origin JSON of at most ``MAX_BODY`` bytes."""
        if request.headers.get("content-type", "").split(";")[0].strip() != "application/json":
            raise AnswerRefused("send the answer as application/json.", 415)
        origin = request.headers.get("origin")
        if origin is not None and origin != f"{request.url.scheme}://{request.headers.get('host')}":
            raise AnswerRefused(f"a request from another site ({origin[:80]}) is refused.", 403)
        try:  # a client sending its body slowly is cut off
            data = await asyncio.wait_for(_read_body(request), BODY_TIMEOUT_S)
        except asyncio.TimeoutError:
            raise AnswerRefused(f"the request's body did not arrive within {BODY_TIMEOUT_S:.0f} s.", 408) from None
        try:
            return json.loads(data.decode(), parse_constant=_no_constant)
        except RecursionError:
            raise AnswerRefused("the request is not JSON this server reads (nested too deeply).", 400) from None
        except (UnicodeDecodeError, ValueError) as exc:
            raise AnswerRefused(f"the request is not JSON ({str(exc)[:80]}).", 400) from None

    async def not_found(self, request, exc):
        """A wrong address: a page with the way back for a browser, JSON otherwise (404)."""
        from starlette.responses import JSONResponse

        message = "there is no page at this address."
        if request.method == "GET" and "text/html" in request.headers.get("accept", ""):
            return self.page("error.html", 404, message=message)
        return JSONResponse({"error": message}, status_code=404)

    def index(self, request):
        store = self.store
        return self.page("index.html", fixed=store.sids if store.fixed else None, noun=store.items.noun)

    async def new(self, request):
        from starlette.concurrency import run_in_threadpool
        from starlette.responses import JSONResponse

        body = await self.json_body(request)
        participant = body.get("participant") if isinstance(body, dict) else None
        if participant is not None and not isinstance(participant, str):
            raise AnswerRefused(f"a participant id must be text, got {participant!r:.80}.", 400)
        sid = await run_in_threadpool(self.store.create, participant or None)
        return JSONResponse({"sid": sid, "url": f"s/{sid}/"})

    def question_page(self, request):
        sid = request.path_params["sid"]
        self.store.entry(sid)
        return self.page("question.html", sid=sid, noun=self.store.items.noun)

    def state(self, request):
        from starlette.responses import JSONResponse

        entry = self.store.entry(request.path_params["sid"])
        with entry.lock:
            state = self.store.state(entry)
        self.store.plots.prefetch_state(state)  # the pictures it shows, started before they are asked for
        return JSONResponse(state)

    async def answer(self, request):
        from starlette.concurrency import run_in_threadpool
        from starlette.responses import JSONResponse

        body = await self.json_body(request)
        start = time.perf_counter()
        result, cpu_s = await run_in_threadpool(_with_cpu, self.store.answer, request.path_params["sid"], body)
        ms = 1000 * (time.perf_counter() - start)
        self.store.plots.prefetch_state(result)  # queued only: no picture or plot delays this reply
        if result["done"]:
            self.store.plots.prerender(self.store, result["sid"])
            self.store.on_finished(result["sid"])
        # the answer's wall time, then the CPU its thread spent on it (the answer and the next question)
        return JSONResponse(result, headers={"Server-Timing": f"answer;dur={ms:.2f}, cpu;dur={1000 * cpu_s:.2f}"})

    async def undo(self, request):
        from starlette.concurrency import run_in_threadpool
        from starlette.responses import JSONResponse

        body = await self.json_body(request)
        return JSONResponse(await run_in_threadpool(self.store.undo, request.path_params["sid"], body))

    def summary(self, request):
        from torchpref.frontends.serve.summary import summary_context

        entry = self.store.entry(request.path_params["sid"])
        with entry.lock:
            ctx = summary_context(self.store, entry, request.query_params)
        self.store.plots.prerender(self.store, entry.sid, ctx["x"], ctx["y"])
        return self.page("summary.html", **ctx)

    def utility_png(self, request):
        from starlette.responses import Response

        from torchpref.frontends.serve.summary import axes_from_query

        x, y = axes_from_query(self.store.items, request.query_params)
        png = self.store.plots.utility_png(self.store, request.path_params["sid"], x, y)  # drawn by a worker
        return Response(png, media_type="image/png")

    def download(self, request):
        from starlette.responses import Response

        store = self.store
        sid, what = request.path_params["sid"], request.path_params["what"]
        makers: dict[str, tuple[Callable[[str], Any], str]] = {
            "session.jsonl": (store.session_file, "application/x-ndjson"),
            "answers.csv": (store.answers_csv, "text/csv; charset=utf-8"),
            "model.pt": (store.checkpoint, "application/octet-stream"),
        }
        if what not in makers:
            raise AnswerRefused("no such download.", 404)
        make, media = makers[what]
        disposition = f'attachment; filename="{sid}.{what}"'
        return Response(make(sid), media_type=media, headers={"Content-Disposition": disposition})

    def picture(self, request):
        from starlette.responses import Response

        try:
            pic = self.store.plots.picture(int(request.path_params["index"]))  # drawn by a worker, kept
        except (ValueError, IndexError):
            raise AnswerRefused("no such picture.", 404) from None
        except OSError:
            raise AnswerRefused("that picture cannot be read.", 404) from None
        if pic is None:
            raise AnswerRefused("no such picture.", 404)
        data, media = pic
        return Response(data, media_type=media, headers={"Cache-Control": "private, max-age=3600"})


def _host_name(host: str) -> str:
    """The name in a ``Host`` header, without the port (``[::1]:80`` -> ``[::1]``)."""
    if host.startswith("["):
        return host[: host.find("]") + 1]
    return host.rsplit(":", 1)[0]


async def _read_body(request) -> bytes:
    data = b""
    async for chunk in request.stream():
        data += chunk
        if len(data) > MAX_BODY:
            raise AnswerRefused(f"the request is over {MAX_BODY} bytes.", 413)
    return data


def _same_token(given: str, token: str) -> bool:
    """Whether ``given`` is ``token``, compared in constant time as UTF-8 bytes (a string with
    characters outside ASCII is a wrong token, not an error)."""
    return hmac.compare_digest(given.encode("utf-8", "surrogatepass"), token.encode("utf-8", "surrogatepass"))


def _no_constant(name: str):
    raise ValueError(f"{name} is not a number")


class _Guard:
    """ASGI middleware: the ``Host`` check, the token (query parameter once, then a cookie) and
    the security headers on every response."""

    def __init__(self, app, token: str | None, hosts: list[str]):
        self.app, self.token, self.hosts = app, token, hosts
        self.state = app.state

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        from starlette.datastructures import URL, Headers, QueryParams
        from starlette.requests import cookie_parser
        from starlette.responses import PlainTextResponse, RedirectResponse

        headers = Headers(scope=scope)
        host = _host_name(headers.get("host", ""))
        if "*" not in self.hosts and host not in self.hosts:
            return await PlainTextResponse("unknown host", 421)(scope, receive, send)
        if self.token is not None:
            url = URL(scope=scope)
            given = QueryParams(scope.get("query_string", b"")).get("token")
            if given is not None and _same_token(given, self.token):
                target = url.remove_query_params("token")
                response = RedirectResponse(target.path + (f"?{target.query}" if target.query else ""), 303)
                response.set_cookie(TOKEN_COOKIE, self.token, httponly=True, samesite="strict")
                return await response(scope, receive, send)
            cookie = cookie_parser(headers.get("cookie", "")).get(TOKEN_COOKIE, "")
            if not _same_token(cookie, self.token):
                return await PlainTextResponse("a token is needed: open the link with ?token=...", 403)(
                    scope, receive, send
                )

        async def send_with_headers(message):
            if message["type"] == "http.response.start":
                message.setdefault("headers", [])
                have = {k.lower() for k, _ in message["headers"]}
                for k, v in HEADERS.items():
                    if k.lower().encode() not in have:
                        message["headers"].append((k.lower().encode(), v.encode()))
            await send(message)

        return await self.app(scope, receive, send_with_headers)


def _check_network(host: str, port: int, allow_remote: bool, token: str | None) -> str | None:
    """The token to require (``None``: none), or :class:`ServeError` for unsafe settings."""
    if not isinstance(port, int) or isinstance(port, bool) or not 0 <= port <= 65535:
        raise ServeError(f"port must be 0..65535, got {port!r:.40}.")
    if _is_loopback(host):
        return token
    if not allow_remote:
        raise ServeError(
            f"serving on {host} lets other machines reach the page: pass allow_remote=True "
            "(--allow-remote) to do so; a token is then required."
        )
    if token is None:
        token = secrets.token_urlsafe(18)
    elif len(token) < 16:
        raise ServeError("a token must be at least 16 characters long.")
    return token


def serve(
    source: PreferenceSession | Tensor | ServeItems,
    *,
    render: Callable | None = None,
    names: list[str] | None = None,
    labels: list[str] | None = None,
    noun: str = "item",
    sessions: str | Path = "torchpref-sessions",
    new: NewSessions | None = None,
    listen: Listen | None = None,
    limits: PoolLimits | None = None,
    threads: int | None = 1,
    ready: Callable[[str], None] | None = None,
    **settings: object,
) -> None:
    """Serve the answering page until interrupted (Ctrl-C).

    Args:
        source: a :class:`~torchpref.PreferenceSession` over a pool (served as the one session:
            its settings and file are used; no new sessions), an ``N x d`` tensor of items (each
            visitor a new session in ``sessions``), or a
            :class:`~torchpref.frontends.serve.items.ServeItems`.
        render: ``render(item, index) -> picture`` (PNG/JPEG/GIF bytes, a matplotlib Figure, a
            Path or None) for each item's picture.
        names, labels, noun: the objectives' and items' names, and what an item is called.
        sessions: the folder of the session files.
        new: each new session's settings (:class:`~torchpref.frontends.serve.store.NewSessions`:
            ``num_queries``, ``seed``, ``num_levels``, ``ties``, ``population``).
        listen: where to listen (:class:`Listen`: ``host``, ``port``, ``allow_remote``, ``token``).
        limits: sessions are a bounded cache over their files
            (:class:`~torchpref.frontends.serve.pool.PoolLimits`: at most ``max_open`` open at once,
            default from the descriptor limit; each closed after ``idle_close`` seconds without a
            request, ``finished_close`` once all its questions are answered, and reopened from its
            file on the next one).
        threads: torch's intra-op threads while serving (:func:`torch.set_num_threads`, restored
            after; ``None``: left as they are). One is fastest for a session's small matrices, and
            sessions of different people run in parallel threads (5-10x faster answers than
            torch's default on a loaded 2-core machine, docs/serve.md).
        ready: called with the page's URL once the server accepts connections (from a thread of
            its own, so it may itself request the page).
        **settings: any field of the three groups as a keyword (``num_queries=6``, ``port=0``,
            ``max_open=100``), overriding the group's; any other keyword is a ``TypeError``.

    Raises:
        ServeError: unsafe or impossible network settings. ImportError: the ``serve`` extra is missing.
    """
    _require()

    new, listen, limits = grouped(dict(settings), new, listen, limits)
    serve_store(
        lambda: _store(source, ServeItemsSpec(render, names, labels, noun), sessions, new, limits),
        listen,
        threads,
        ready,
    )


def serve_store(
    make_store: Callable[[], SessionStore],
    listen: Listen,
    threads: int | None = 1,
    ready: Callable[[str], None] | None = None,
    extra_routes: Callable[[SessionStore], list] | None = None,
    started: Callable[[SessionStore, str], None] | None = None,
) -> None:
    """Serve the store ``make_store()`` builds (after the network settings are checked and the
    port is taken) until interrupted: the pictures drawn first, then the address printed.
    ``extra_routes(store)``: more routes (the study's page); ``started(store, url)``: called once
    the server listens (the study prints its experimenter link). Used by :func:`serve` and
    ``torchpref study serve``."""
    from torchpref.frontends.serve.pool import quiet_resource_errors
    from torchpref.inference.fast_path import check_setting

    check_setting()  # a mistyped TORCHPREF_FAST_PATH is named now, not at every page
    token = _check_network(listen.host, listen.port, listen.allow_remote, listen.token)
    sock = listening_socket(listen.host, listen.port)  # a busy port is named before any work
    try:
        store = make_store()
    except BaseException:
        sock.close()
        raise
    host = listen.host
    hosts = ["*"] if not _is_loopback(host) else [*LOOPBACK_NAMES, _shown_host(host)]
    routes = extra_routes(store) if extra_routes is not None else None
    app = create_app(store, token=token, allowed_hosts=hosts, extra_routes=routes)
    if started is not None:
        inner = ready

        def ready(url: str) -> None:
            started(store, url)
            if inner is not None:
                inner(url)

    import torch

    before = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        store.items.prerender(progress=True)  # every picture drawn before the address is printed
        store.warm_up()  # the process's first fit before the first participant's (about a second)
    except BaseException:
        sock.close()
        store.close()
        torch.set_num_threads(before)
        raise
    # every object alive now (torch, the items, the pictures) left out of later collections: the
    # collection after sessions close then takes under a millisecond instead of ~150 ms with the
    # interpreter's lock held, which every answer in flight waited for (the soak's slowest answers)
    gc.collect()
    gc.freeze()
    prerender = store.items.prerender_in_background()  # beyond the cache's size (none for most pools)
    try:
        path = f"s/{store.sids[0]}/" if store.fixed else ""
        with quiet_resource_errors():  # out of descriptors: one log line, not a traceback a second
            _run_uvicorn(app, sock, host, token, ready, path)
    finally:
        prerender.set()
        sock.close()
        store.close()
        gc.unfreeze()  # the caller's objects are collectable again (serve() called from Python)
        torch.set_num_threads(before)


def _store(
    source: PreferenceSession | Tensor | ServeItems,
    shown: ServeItemsSpec,
    sessions: str | Path,
    new: NewSessions,
    limits: PoolLimits,
) -> SessionStore:
    """The store serving ``source`` (one session, or new ones in the folder ``sessions``)."""
    from torchpref.data.queries import FinitePool

    if isinstance(source, PreferenceSession):
        if new.population is not None:
            raise ServeError(
                "a served session has its own model: give population to serve() with items, not a session."
            )
        pool = source.candidates  # the session's own candidates: queries name their rows
        if not isinstance(pool, FinitePool):
            raise ServeError("a served session's candidates must be a pool of items (N x d), not a box.")
        items = ServeItems(
            pool.X, list(shown.names or source.names or []), shown.labels, render=shown.render, noun=shown.noun
        )
        return SessionStore(items, session=source, ties=new.ties, limits=limits)
    if isinstance(source, ServeItems):
        items = source
    elif isinstance(source, Tensor):
        items = ServeItems(source, list(shown.names or []), shown.labels, render=shown.render, noun=shown.noun)
    else:
        raise TypeError(
            f"serve() takes a PreferenceSession, an N x d tensor or ServeItems, got {type(source).__name__}."
        )
    return SessionStore(items, sessions, new=new, limits=limits)


def run(args: argparse.Namespace) -> int:
    """``torchpref serve`` (``args`` from :mod:`torchpref.cli`); returns the exit code."""
    _require()
    _check_network(args.host, args.port, args.allow_remote, args.token)
    listening_socket(args.host, args.port).close()  # a busy port is named before the items are read
    if args.features is not None:
        items = items_from_csv(args.features, args.id_column, args.image_column, args.image_dir)
    else:
        print(f"Building the lake scenario (seed {args.seed}; cached after the first time) ...", file=sys.stderr)
        items = lake_items(args.seed)
    population = None
    if getattr(args, "population", None) is not None:
        from torchpref.population.io import load_population

        population = load_population(args.population, dim=items.X.shape[-1], names=items.names)
        if population.names is None and not getattr(args, "population_without_names", False):
            raise ServeError(
                f"the population {args.population} records no feature names, so it cannot be checked against "
                f"the items' ({', '.join(items.names)}): fit it with names= (torchpref.fit_population), or "
                "pass --population-without-names if its features are these, in this order."
            )
    queries = None
    if getattr(args, "question_list", None) is not None:
        from torchpref.sessions.query_list import read_question_list

        queries = tuple(read_question_list(args.question_list, items.X))
    selector = None
    if getattr(args, "selector", None) is not None:
        from torchpref.selection.defaults import named_selector

        selector = named_selector(args.selector, items.X.unique(dim=0).shape[0], args.levels)
    serve(
        items,
        sessions=args.sessions,
        new=NewSessions(args.queries, args.seed, args.levels, not args.no_ties, population, queries, selector),
        listen=Listen(args.host, args.port, args.allow_remote, args.token),
        limits=PoolLimits(max_open=args.max_open, idle_close=args.idle_close, finished_close=args.finished_close),
    )
    return 0
