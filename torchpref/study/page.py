r"""The experimenter's page of a study (``/study/``): the participants with their progress, answers
and seconds, the current population's utility and spread, the refit history, and downloads of
the exports and the report. Reached only with the study's key: ``/study/?key=KEY`` once (the key
becomes a cookie of that path), never with a participant's link; anything else under ``/study/``
is a 403.
"""

from __future__ import annotations

import hmac
import html
import io
from typing import TYPE_CHECKING

from torchpref.study.export import participant_rows, table_bytes
from torchpref.study.folder import StudyFolder
from torchpref.study.items import study_space
from torchpref.study.report import plain, report_html
from torchpref.study.store import StudyStore

if TYPE_CHECKING:  # starlette is the serve extra: imported where the routes are made
    from starlette.requests import Request

    from torchpref.frontends.serve.items import ServeItems

__all__ = ["KEY_COOKIE", "study_routes"]

KEY_COOKIE = "torchpref_study"
#: the selectors a study may name (``--selector``; torchpref.selection.defaults.named_selector) and what they ask
SELECTOR_DESCRIPTIONS: dict[str, str] = {
    "default": "each question (a rating or a best-of-m choice) valued by the expected information about the "
    "utility and the clipped profile's expected variance reduction, per second of the participant's effort",
    "ucbc": "the paper's UCBC: best-of-m rankings early, ratings late",
    "information": "the question of the most expected information about the utility per second of effort",
    "random": "a random rating or best-of-m choice, even odds (a baseline)",
}
DOWNLOADS = {
    "answers.csv": "text/csv",
    "participants.csv": "text/csv",
    "population_utility.csv": "text/csv",
    "report.html": "text/html",
}


def _allowed(request: Request, key: str) -> bool:
    given = request.cookies.get(KEY_COOKIE, "")
    return bool(given) and hmac.compare_digest(given.encode(), key.encode())


def study_routes(store: StudyStore, key: str) -> list:
    """The page's Starlette routes over ``store`` (a study's), guarded by ``key``."""
    from starlette.concurrency import run_in_threadpool
    from starlette.responses import HTMLResponse, PlainTextResponse, RedirectResponse, Response
    from starlette.routing import Route

    folder = store.folder
    pngs: dict[int, bytes] = {}

    def guarded(fn):
        async def handler(request):
            given = request.query_params.get("key")
            if given is not None and hmac.compare_digest(given.encode(), key.encode()):
                response = RedirectResponse(request.url.path, 303)
                response.set_cookie(KEY_COOKIE, key, httponly=True, samesite="strict", path="/study/")
                return response
            if not _allowed(request, key):
                return PlainTextResponse("the experimenter's page needs the study's key (?key=...).", 403)
            return await run_in_threadpool(fn, request)

        return handler

    def page(request):
        return HTMLResponse(_page(folder, store))

    def population_png(request):
        pointer = folder.current()
        if pointer is None:
            return PlainTextResponse("no population yet", 404)
        v = pointer.version
        if v not in pngs:
            pngs[v] = _population_png(folder, v, store.items)
        return Response(pngs[v], media_type="image/png", headers={"Cache-Control": "no-store"})

    def download(request):
        what = request.path_params["what"]
        if what not in DOWNLOADS:
            return PlainTextResponse("no such download", 404)
        # built in memory for this request: two downloads at once never share (or empty) a file
        space = study_space(folder, store.items)  # the server's items: not read again
        data = report_html(folder, space).encode() if what == "report.html" else table_bytes(folder, what, space)
        headers = {"Content-Disposition": f'attachment; filename="{what}"', "Cache-Control": "no-store"}
        return Response(data, media_type=DOWNLOADS[what], headers=headers)

    return [
        Route("/study", lambda r: RedirectResponse("/study/" + (f"?{r.url.query}" if r.url.query else ""), 307)),
        Route("/study/", guarded(page)),
        Route("/study/population.png", guarded(population_png)),
        Route("/study/download/{what}", guarded(download)),
    ]


def _population_png(folder: StudyFolder, version: int, items: ServeItems | None = None) -> bytes:
    import torch
    from matplotlib.figure import Figure

    space = study_space(folder, items)
    pop = folder.population(version, names=space.names)
    assert pop is not None
    X, names = space.unit, [plain(n) for n in space.names]
    with torch.no_grad():
        post = pop.person_model(X).posterior(X.unsqueeze(-2))
    mean, sd = post.mean.reshape(-1), post.variance.reshape(-1).clamp_min(0).sqrt()
    fig = Figure(figsize=(9, 3.6))
    ax = fig.subplots(1, 2)
    raw = space.X
    y = raw[:, 1] if raw.shape[1] > 1 else torch.zeros(raw.shape[0])
    for a, v, title in ((ax[0], mean, "mean utility"), (ax[1], sd, "spread (sd)")):
        sc = a.scatter(raw[:, 0], y, c=v, cmap="viridis", s=22)
        fig.colorbar(sc, ax=a, label=title)
        a.set(xlabel=names[0], ylabel=names[1] if len(names) > 1 else "", title=f"population v{version}: {title}")
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    return buf.getvalue()


def _population(folder: StudyFolder, store: StudyStore) -> str:
    esc = html.escape
    pointer = folder.current()
    if pointer is not None:
        fallback = (
            f"<p><strong>current.json was not usable ({esc(pointer.fallback)}): the newest population that loads "
            "is used.</strong></p>"
            if pointer.fallback
            else ""
        )
        seconds = "" if pointer.seconds is None else f" in {pointer.seconds:.1f} s"
        when = f" ({esc(pointer.fitted_at)})" if pointer.fitted_at else ""
        return (
            f"{fallback}<p>Population v{pointer.version}, fitted on {len(pointer.participants)} finished "
            f"participants{seconds}{when}.</p>"
            '<img id="population" src="population.png" width="810" height="324" '
            "alt=\"the population's utility and spread\">"
        )
    if store.first_population_pending():
        if store.refits.busy():
            return "<p id=\"first-population\">The first population is being fitted now (two participants have finished).</p>"
        return "<p id=\"first-population\">The first population could not be fitted yet: see the refits below.</p>"
    return "<p>No population yet: it is fitted as soon as two participants have finished.</p>"


def _page(folder: StudyFolder, store: StudyStore) -> str:
    esc = html.escape
    people = participant_rows(folder)
    events = [
        e
        for e in folder.events()
        if e.get("event")
        in ("refit", "refit failed", "refit stopped", "refit worker lost", "finished", "population pointer")
    ]
    rows = "".join(
        f"<tr><td>{esc(str(p['participant']))}</td><td>{esc(str(p['participant_id']))}</td>"
        f"<td>{esc(p['status'])}</td><td>{p['answers']} / {p['questions']}</td><td>{p['median_seconds']}</td>"
        f"<td>{esc(str(p['last_answer']))}</td><td>{p['population_version']}</td></tr>"
        for p in people
    )
    history = "".join(
        f"<tr><td>{esc(str(e.get('time', '')))}</td><td>{esc(str(e['event']))}</td><td>{esc(str(e.get('version', '')))}</td>"
        f"<td>{esc(str(e.get('participants', e.get('participant', ''))))}</td><td>{esc(str(e.get('seconds', '')))}</td>"
        f"<td>{esc(str(e.get('why', '')))}</td></tr>"
        for e in reversed(events[-200:])
    )
    count = {k: sum(p["status"] == k for p in people) for k in ("finished", "in progress", "abandoned")}
    links = "".join(f'<li><a href="download/{w}">{w}</a></li>' for w in DOWNLOADS)
    selector = store.selector_name
    done = store.completion() or {}
    end = "".join(
        f"<li>{what}: <code>{esc(str(v))}</code></li>"
        for what, v in (("completion code", done.get("code")), ("sent on to", done.get("redirect")))
        if v
    )
    refit = "a refit is running" if store.refits.busy() else "no refit running"
    return f"""<!doctype html><html lang="en"><head><meta charset="utf-8"><meta http-equiv="refresh" content="15">
<title>torchpref study: {esc(folder.path.name)}</title><link rel="icon" href="/static/favicon.ico">
<link rel="stylesheet" href="/static/serve.css"></head><body><main>
<h1>Study {esc(folder.path.name)}</h1>
<p id="counts">{len(people)} participants: {count["finished"]} finished, {count["in progress"]} in progress,
{count["abandoned"]} abandoned (unfinished and silent for 30 minutes); {sum(p["answers"] for p in people)} answers in force;
{refit} (this page refreshes every 15 s).</p>
<p id="selector">Questions are chosen by the <strong>{esc(selector)}</strong> selector:
{esc(SELECTOR_DESCRIPTIONS.get(selector, ""))}</p>
{f'<p>At the end, each participant is shown:</p><ul id="completion">{end}</ul>' if end else ""}
<h2>Population</h2>{_population(folder, store)}
<h2>Participants</h2><table id="participants"><thead><tr><th>participant</th><th>participant id (link)</th>
<th>status</th><th>answers</th><th>median seconds</th><th>last answer</th><th>population</th></tr></thead>
<tbody>{rows}</tbody></table>
<h2>Refits</h2><table id="refits"><thead><tr><th>time</th><th>event</th><th>version</th><th>participants</th>
<th>seconds</th><th>note</th></tr></thead><tbody>{history}</tbody></table>
<h2>Downloads</h2><ul id="downloads">{links}</ul>
</main></body></html>"""
