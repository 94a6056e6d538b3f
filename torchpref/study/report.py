r"""``torchpref study report DIR``: one self-contained HTML page about a study (figures inline).

Its figures: the current population's utility over the items and its spread; each participant's
learned utility at every item (from the population version they started with); the agreement
between participants (Kendall's tau between their utilities over the items); seconds per answer;
questions answered per participant. Needs matplotlib (the ``plot`` extra).
"""

from __future__ import annotations

import base64
import html
import io
from pathlib import Path

import torch

from torchpref.extras import require
from torchpref.models.preference_gp import PreferenceGP
from torchpref.sessions.settings import default_session_model
from torchpref.study.export import participant_rows, study_items
from torchpref.study.folder import StudyFolder
from torchpref.study.refit import person_data

__all__ = ["participant_utilities", "report"]


def participant_utilities(folder: StudyFolder, X: torch.Tensor, names: list[str]) -> dict[str, torch.Tensor]:
    """Each participant's posterior mean utility at the items ``X`` (unit cube), from their answers
    in force and the population they started with (or a session's default model)."""
    out: dict[str, torch.Tensor] = {}
    cache: dict = {}
    for f in sorted(folder.sessions.glob("*.session.jsonl")):
        try:
            data, header, answered = person_data(f)
        except (OSError, ValueError):
            continue
        if not answered:
            continue
        v = (header.get("metadata") or {}).get("study_population")
        if v not in cache:
            cache[v] = folder.population(v, names=names)
        pop = cache[v]
        if pop is not None:
            model = pop.person_model(data)
        else:
            model = default_session_model(data.train_X[:1])
            model.replace_data(data)
        out[f.name.split(".")[0]] = _mean(model, X)
    return out


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


def _figures(folder: StudyFolder, X, names, people, utilities) -> list[tuple[str, str]]:
    Figure = require("matplotlib.figure", "the study report", "plot").Figure  # no pyplot: safe in a server's thread
    figs: list[tuple[str, str]] = []
    pointer = folder.current()
    if pointer is not None and X.shape[1] >= 2:
        pop = folder.population(pointer["version"], names=names)
        assert pop is not None
        with torch.no_grad():
            post = pop.person_model(X).posterior(X.unsqueeze(-2))
        mean, sd = post.mean.reshape(-1), post.variance.reshape(-1).clamp_min(0).sqrt()
        fig = Figure(figsize=(10, 4))
        ax = fig.subplots(1, 2)
        for a, v, title in ((ax[0], mean, "population mean utility"), (ax[1], sd, "spread (sd) of the mean")):
            sc = a.scatter(X[:, 0], X[:, 1], c=v, cmap="viridis", s=28)
            fig.colorbar(sc, ax=a, label=title)
            a.set(xlabel=names[0], ylabel=names[1], title=f"{title} (population v{pointer['version']})")
        figs.append(("The population's utility and its spread over the items", _png(fig)))
    if utilities:
        sids = list(utilities)
        U = torch.stack([utilities[s] for s in sids])
        order = U.mean(0).argsort(descending=True)
        fig = Figure(figsize=(10, 0.3 * len(sids) + 1.5))
        ax = fig.subplots()
        im = ax.imshow(U[:, order].numpy(), aspect="auto", cmap="viridis", interpolation="nearest")
        ax.set(xlabel="items (by the participants' average utility)", ylabel="participant", yticks=range(len(sids)))
        ax.set_yticklabels([s[:8] for s in sids], fontsize=7)
        fig.colorbar(im, ax=ax, label="learned utility")
        figs.append(("Each participant's learned utility at every item", _png(fig)))
        if len(sids) >= 2:
            fig = Figure(figsize=(5.5, 4.5))
            ax = fig.subplots()
            im = ax.imshow(_kendall(U).numpy(), vmin=-1, vmax=1, cmap="RdBu_r")
            fig.colorbar(im, ax=ax, label="Kendall's tau over item pairs")
            ax.set(title="agreement between participants", xlabel="participant", ylabel="participant")
            figs.append(("Agreement between participants", _png(fig)))
    secs = [float(r["seconds"]) for r in people if r.get("seconds") not in ("", None)]
    fig = Figure(figsize=(10, 3.5))
    ax = fig.subplots(1, 2)
    ax[0].hist(secs or [0], bins=30, color="C0")
    ax[0].set(xlabel="seconds per answer", ylabel="answers", title=f"{len(secs)} answers timed by the page")
    counts = [int(r["answers"]) for r in participant_rows(folder)]
    ax[1].bar(range(len(counts)), counts, color="C1")
    ax[1].set(xlabel="participant (by id)", ylabel="answers in force", title="questions answered per participant")
    figs.append(("Seconds per answer and questions per participant", _png(fig)))
    return figs


def report(folder: StudyFolder, out: Path | None = None) -> Path:
    """Write ``report.html`` (default in ``DIR/exports``) and return its path."""
    from torchpref.study.export import answer_rows

    out = out or folder.exports / "report.html"
    out.parent.mkdir(parents=True, exist_ok=True)
    X, names = study_items(folder)
    answers = answer_rows(folder)
    utilities = participant_utilities(folder, X, names)
    parts = participant_rows(folder)
    refits = [e for e in folder.events() if e.get("event", "").startswith("refit")]
    figs = _figures(folder, X, names, answers, utilities)
    rows = "".join(
        f"<tr><td>{html.escape(str(p['participant']))}</td><td>{p['answers']} / {p['questions']}</td>"
        f"<td>{p['median_seconds']}</td><td>{p['population_version']}</td></tr>"
        for p in parts
    )
    body = [
        f"<h1>Study {html.escape(folder.path.name)}</h1>",
        f"<p>{len(parts)} participants, {sum(p['finished'] for p in parts)} finished; {len(answers)} answer records; "
        f"{sum(e['event'] == 'refit' for e in refits)} population refits.</p>",
        *[f'<h2>{html.escape(t)}</h2><img alt="{html.escape(t)}" src="data:image/png;base64,{b}">' for t, b in figs],
        "<h2>Participants</h2><table><tr><th>participant</th><th>answers</th><th>median seconds</th>"
        f"<th>population version</th></tr>{rows}</table>",
    ]
    style = "body{font-family:system-ui,sans-serif;max-width:1100px;margin:1rem auto}img{max-width:100%}td,th{padding:0 .6rem}"
    page = f'<!doctype html><html lang="en"><head><meta charset="utf-8"><title>torchpref study</title><style>{style}</style></head><body>{"".join(body)}</body></html>'
    out.write_text(page)
    return out
