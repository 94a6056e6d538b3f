r"""``torchpref study report DIR``: one self-contained HTML page about a study (figures inline).

Its figures: the current population's utility over the items (in the items' own units) and its
spread; each participant's learned utility at every item (their session's recorded model:
:meth:`~torchpref.sessions.contents.SessionContents.model`, from the population version they
started with); the agreement between participants (Kendall's tau between their utilities over
the items), participants named by their ids; seconds per answer; questions answered per
participant. Abandoned sessions are counted and marked apart. Needs matplotlib (the ``plot`` extra).
"""

from __future__ import annotations

import base64
import html
import io
from pathlib import Path

import torch

from torchpref.extras import require
from torchpref.models.preference_gp import PreferenceGP
from torchpref.study.export import answer_rows, participant_id, participant_rows, population_version, study_sessions
from torchpref.study.folder import StudyFolder, write_private
from torchpref.study.items import StudySpace, study_space

__all__ = ["participant_utilities", "report", "report_html"]


def participant_utilities(folder: StudyFolder, space: StudySpace | None = None) -> dict[str, torch.Tensor]:
    """Each participant's posterior mean utility at the study's items (by session id), from their
    answers in force and the model their session records (the population they started with, or a
    session's default model); participants without an answer are left out."""
    space = space if space is not None else study_space(folder)
    out: dict[str, torch.Tensor] = {}
    cache: dict = {}
    for s in study_sessions(folder):
        if not s.in_force:
            continue
        v = population_version(s)
        if v not in cache:
            cache[v] = folder.population(v, names=space.names)
        out[s.sid] = _mean(s.model(cache[v]), space.unit)
    return out


def plain(text: str) -> str:
    """``text`` as matplotlib draws it literally: a ``$`` (which would start mathematics, and a
    malformed formula in an item's name or a participant's id would fail the figure) escaped."""
    return text.replace("$", r"\$")


def _mean(model: PreferenceGP, X: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        return model.posterior(X.unsqueeze(-2)).mean.reshape(-1)


def _kendall(U: torch.Tensor) -> torch.Tensor:
    """Kendall's tau-a between the rows of ``U`` (``P x N``), over all item pairs."""
    s = torch.sign(U.unsqueeze(-1) - U.unsqueeze(-2))  # P x N x N
    n = U.shape[1]
    return torch.einsum("aij,bij->ab", s, s) / (n * (n - 1))


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    return base64.b64encode(buf.getvalue()).decode()


def _figures(folder: StudyFolder, space: StudySpace, answers, people, utilities, who) -> list[tuple[str, str]]:
    Figure = require("matplotlib.figure", "the study report", "plot").Figure  # no pyplot: safe in a server's thread
    figs: list[tuple[str, str]] = []
    pointer = folder.current()
    X, raw, names = space.unit, space.X, [plain(n) for n in space.names]
    if pointer is not None and X.shape[1] >= 2:
        pop = folder.population(pointer.version, names=names)
        assert pop is not None
        with torch.no_grad():
            post = pop.person_model(X).posterior(X.unsqueeze(-2))
        mean, sd = post.mean.reshape(-1), post.variance.reshape(-1).clamp_min(0).sqrt()
        fig = Figure(figsize=(10, 4))
        ax = fig.subplots(1, 2)
        for a, v, title in ((ax[0], mean, "population mean utility"), (ax[1], sd, "spread (sd) of the mean")):
            sc = a.scatter(raw[:, 0], raw[:, 1], c=v, cmap="viridis", s=28)
            fig.colorbar(sc, ax=a, label=title)
            a.set(xlabel=names[0], ylabel=names[1], title=f"{title} (population v{pointer.version})")
        figs.append(("The population's utility and its spread over the items", _png(fig)))
    if utilities:
        sids = list(utilities)
        tick = [plain(who[s]) for s in sids]
        U = torch.stack([utilities[s] for s in sids])
        order = U.mean(0).argsort(descending=True)
        fig = Figure(figsize=(10, 0.3 * len(sids) + 1.5))
        ax = fig.subplots()
        im = ax.imshow(U[:, order].numpy(), aspect="auto", cmap="viridis", interpolation="nearest")
        ax.set(xlabel="items (by the participants' average utility)", ylabel="participant", yticks=range(len(sids)))
        ax.set_yticklabels(tick, fontsize=7)
        if len(order) <= 40:
            ax.set_xticks(range(len(order)))
            ax.set_xticklabels([plain(space.labels[int(i)]) for i in order], rotation=90, fontsize=6)
        fig.colorbar(im, ax=ax, label="learned utility")
        figs.append(("Each participant's learned utility at every item", _png(fig)))
        if len(sids) >= 2:
            fig = Figure(figsize=(6.5, 5.5))
            ax = fig.subplots()
            im = ax.imshow(_kendall(U).numpy(), vmin=-1, vmax=1, cmap="RdBu_r")
            fig.colorbar(im, ax=ax, label="Kendall's tau over item pairs")
            ax.set(title="agreement between participants", xticks=range(len(sids)), yticks=range(len(sids)))
            ax.set_xticklabels(tick, rotation=90, fontsize=6)
            ax.set_yticklabels(tick, fontsize=6)
            figs.append(("Agreement between participants", _png(fig)))
    secs = [float(r["seconds"]) for r in answers if r.get("seconds") not in ("", None)]
    fig = Figure(figsize=(10, 3.5))
    ax = fig.subplots(1, 2)
    ax[0].hist(secs or [0], bins=30, color="C0")
    ax[0].set(xlabel="seconds per answer", ylabel="answers", title=f"{len(secs)} answers timed by the page")
    counts = [int(r["answers"]) for r in people]
    colours = ["C7" if r["status"] == "abandoned" else "C1" for r in people]
    ax[1].bar(range(len(counts)), counts, color=colours)
    ax[1].set_xticks(range(len(counts)))
    ax[1].set_xticklabels([plain(who[r["participant"]]) for r in people], rotation=90, fontsize=6)
    ax[1].set(ylabel="answers in force", title="questions answered per participant (grey: abandoned)")
    figs.append(("Seconds per answer and questions per participant", _png(fig)))
    return figs


def report_html(folder: StudyFolder, space: StudySpace | None = None) -> str:
    """The report's page (module docstring), built in memory (``space``: the study's items, read
    from the folder if not given)."""
    esc = html.escape
    space = space if space is not None else study_space(folder)
    answers = answer_rows(folder, space)
    utilities = participant_utilities(folder, space)
    parts = participant_rows(folder)
    who = {
        s.sid: (participant_id(s) or s.sid[:8]) + (" (abandoned)" if r["status"] == "abandoned" else "")
        for s, r in zip(study_sessions(folder), parts)
    }
    refits = [e for e in folder.events() if str(e.get("event", "")).startswith("refit")]
    figs = _figures(folder, space, answers, parts, utilities, who)
    rows = "".join(
        f"<tr><td>{esc(str(p['participant']))}</td><td>{esc(str(p['participant_id']))}</td><td>{esc(p['status'])}</td>"
        f"<td>{p['answers']} / {p['questions']}</td><td>{p['median_seconds']}</td><td>{p['population_version']}</td></tr>"
        for p in parts
    )
    count = {k: sum(p["status"] == k for p in parts) for k in ("finished", "in progress", "abandoned")}
    body = [
        f"<h1>Study {esc(folder.path.name)}</h1>",
        f"<p>{len(parts)} participants: {count['finished']} finished, {count['in progress']} in progress, "
        f"{count['abandoned']} abandoned; {len(answers)} answer records; "
        f"{sum(e.get('event') == 'refit' for e in refits)} population refits.</p>",
        *[f'<h2>{esc(t)}</h2><img alt="{esc(t)}" src="data:image/png;base64,{b}">' for t, b in figs],
        "<h2>Participants</h2><table><tr><th>participant</th><th>participant id (link)</th><th>status</th>"
        f"<th>answers</th><th>median seconds</th><th>population version</th></tr>{rows}</table>",
    ]
    style = "body{font-family:system-ui,sans-serif;max-width:1100px;margin:1rem auto}img{max-width:100%}td,th{padding:0 .6rem}"
    return f'<!doctype html><html lang="en"><head><meta charset="utf-8"><title>torchpref study</title><style>{style}</style></head><body>{"".join(body)}</body></html>'


def report(folder: StudyFolder, out: Path | None = None) -> Path:
    """Write ``report.html`` (default in ``DIR/exports``; atomically, mode 0600) and return its path."""
    out = out or folder.exports / "report.html"
    out.parent.mkdir(parents=True, exist_ok=True)
    write_private(out, report_html(folder).encode())
    return out
