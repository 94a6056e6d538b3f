r"""The summary page of ``torchpref serve``: the learned utility over two objectives, the best
items, and the downloads.

The plot shows every pool item at its values of the two chosen objectives, coloured by the
posterior mean of the utility (the model's prediction at that item, all its objectives), with
the items answered about ringed and the recommended item starred. With one objective it is the
posterior mean and a two-standard-deviation band against that objective.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Protocol

import torch

from torchpref.frontends.serve.items import ServeItems
from torchpref.frontends.serve.pool import PoolEntry

if TYPE_CHECKING:
    from torchpref.sessions.session import PreferenceSession

__all__ = ["axes_from_query", "summary_context", "utility_data", "utility_plot"]

TOP = 5


class HasItems(Protocol):
    """What the summary page asks of a store: its pool of items;
    :class:`~torchpref.frontends.serve.store.SessionStore` is one (a Protocol: the store imports
    the plots, which import this module)."""

    @property
    def items(self) -> ServeItems: ...


def axes_from_query(items: ServeItems, query: Mapping[str, str]) -> tuple[int, int]:
    """The two objectives to plot: ``?x=I&y=J`` (column numbers), by default the first two.

    Raises:
        AnswerRefused: (400) a number that is not an objective's column.
    """
    from torchpref.frontends.serve.errors import AnswerRefused

    d = items.X.shape[1]
    out = []
    for key, default in (("x", 0), ("y", min(1, d - 1))):
        text = query.get(key)
        if text is None:
            out.append(default)
            continue
        if not (text.isascii() and text.isdigit()) or not 0 <= int(text) < d:
            raise AnswerRefused(f"{key} must be an objective's column 0..{d - 1}, got {text[:20]!r}.", 400)
        out.append(int(text))
    return out[0], out[1]


def summary_context(store: HasItems, entry: PoolEntry, query: Mapping[str, str]) -> dict[str, Any]:
    """What ``summary.html`` shows for a session (call with ``entry.lock`` held)."""
    from torchpref.data.queries import first_unique_rows

    items, s = store.items, entry.session
    x, y = axes_from_query(items, query)
    ctx: dict[str, Any] = {
        "sid": entry.sid,
        "answered": s.step,
        "total": s.num_queries,
        "names": list(enumerate(items.names)),
        "x": x,
        "y": y,
        "noun": items.noun,
        "top": [],
        "levels": s.num_levels,
        "median_seconds": None,
    }
    if s.step == 0:
        return ctx
    seconds = sorted(a.response_time for a in s.history if a.response_time is not None)
    if seconds:
        ctx["median_seconds"] = f"{seconds[len(seconds) // 2]:.1f}"
    X = items.X
    distinct = first_unique_rows(X)
    mean, std = s.predict(X)
    rating = s.expected_rating(X)
    order = distinct[mean[distinct].argsort(descending=True)[:TOP]].tolist()
    k = s.num_levels
    for rank, i in enumerate(order, start=1):
        expected = float(k * rating[i] + 0.5).__round__(1) if k else float(rating[i]).__round__(2)
        ctx["top"].append(
            {
                "rank": rank,
                "label": items.label(i),
                "features": [f"{float(v):.4g}" for v in X[i]],
                "mean": f"{float(mean[i]):+.2f}",
                "std": f"{float(std[i]):.2f}",
                "expected": f"{min(max(expected, 1), k):.1f} / {k}" if k else f"{expected:.2f}",
            }
        )
    return ctx


def utility_data(items: ServeItems, session: PreferenceSession, x: int, y: int) -> dict[str, Any]:
    """The numbers the summary plot of objectives ``x`` and ``y`` is drawn from (plain lists: the
    plot is drawn in a worker process, :func:`~torchpref.frontends.serve.plot_worker.draw_utility`).
    Call with the session's lock held; it takes the posterior over the pool (a few milliseconds)."""
    X = items.X
    seen = sorted({i for r in session.history for i in (r.pool_indices or ())})
    mean = std = None
    if session.step > 0:
        with torch.no_grad():
            mean, std = session.predict(X)
    shown = plotted_rows(X.shape[0], seen, mean)
    data: dict[str, Any] = {
        "step": session.step,
        "xs": X[shown, x].tolist(),
        "ys": None if x == y else X[shown, y].tolist(),
        "xlabel": items.names[x],
        "ylabel": items.names[y],
        "of": X.shape[0],
    }
    if mean is None or std is None:
        return data
    at = {int(r): k for k, r in enumerate(shown.tolist())}
    data.update(
        mean=mean[shown].tolist(),
        std=std[shown].tolist(),
        seen=[at[i] for i in seen if i in at],
        best=at[int(mean.argmax())],
    )
    return data


PLOT_MAX_POINTS = 5000
"""The most items the summary plot draws: a larger pool is drawn by its answered items, its best
:data:`PLOT_TOP` by posterior mean and evenly spaced rows (a 100,000-item scatter takes seconds to draw)."""
PLOT_TOP = 500


def plotted_rows(n: int, seen: list[int], mean: torch.Tensor | None) -> torch.Tensor:
    """The rows of a pool of ``n`` items that the summary plot draws, in order: all of them, or
    for more than :data:`PLOT_MAX_POINTS` the answered ones, the best :data:`PLOT_TOP` by
    ``mean`` (when given) and evenly spaced rows, :data:`PLOT_MAX_POINTS` in all."""
    if n <= PLOT_MAX_POINTS:
        return torch.arange(n)
    keep = torch.zeros(n, dtype=torch.bool)
    keep[torch.tensor(seen, dtype=torch.long)] = True
    if mean is not None:
        keep[mean.topk(PLOT_TOP).indices] = True
    rest = PLOT_MAX_POINTS - int(keep.sum())
    if rest > 0:
        keep[torch.linspace(0, n - 1, rest).round().long()] = True
    return torch.nonzero(keep).reshape(-1)


def utility_plot(items: ServeItems, session: PreferenceSession, x: int, y: int) -> bytes:
    """A PNG of the learned utility over objectives ``x`` and ``y`` (see the module), drawn here."""
    from torchpref.frontends.serve.plot_worker import draw_utility

    return draw_utility(utility_data(items, session, x, y))
