r"""A notebook widget that asks a :class:`~torchpref.PreferenceSession`'s queries with pictures.

:class:`PreferenceWidget` shows the session's next query (:meth:`~torchpref.PreferenceSession.ask`)
with one picture per option and records a click as the answer
(:meth:`~torchpref.PreferenceSession.tell`): a ranking's options each get a "best" button and
there is a "no preference" button; a rating gets one button per Likert level (or a slider for
ratings in ``[0, 1]``). An "undo" button withdraws the last answer. With a ``session_file`` the
session saves every click as it is made, so the notebook can be closed and resumed.

A picture comes from a *render hook*, ``render(item, index)``: ``item`` is the option's ``d``
objective values, ``index`` its row in the session's pool (``None`` for a box). It may return a
matplotlib ``Figure``, PNG/JPEG/GIF ``bytes``, a path to an image file, an HTML string, an
``ipywidgets`` widget, or any object with ``_repr_png_`` / ``_repr_svg_`` / ``_repr_html_``.
Without a hook each option is a table of its objective values. :func:`lake_renderer` draws a
lake path on the map (:mod:`torchpref.lake`).

Needs ``ipywidgets`` (the ``notebooks`` extra); importing this module does not.

Example:
    >>> session = PreferenceSession(scenario.train_X, names=["distance", "information"])
    >>> PreferenceWidget(session, render=lake_renderer(scenario))   # last line of a cell
"""

from __future__ import annotations

import html
import io
import os
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from torch import Tensor

from torchpref.data.queries import Query, RankingQuery
from torchpref.lake.scenario import LakeScenario
from torchpref.sessions.session import PreferenceSession

if TYPE_CHECKING:  # ipywidgets is the notebook extra: imported where used
    from ipywidgets import Widget

__all__ = ["PreferenceWidget", "as_picture", "lake_renderer", "table_picture"]

RenderHook = Callable[[Tensor, "int | None"], Any]
"""``render(item, index) -> picture``: see the module docstring."""

LETTERS = "ABCDEFGHIJKLMNOPQRSTUVWXYZ"
_MAGIC = ((b"\x89PNG", "png"), (b"\xff\xd8", "jpeg"), (b"GIF8", "gif"))


def _widgets():
    from torchpref.extras import require

    return require("ipywidgets", "the notebook widget")


def _image(data: bytes, fmt: str, width: str):
    w = _widgets()
    return w.Image(value=data, format=fmt, layout=w.Layout(width=width, height="auto"))


def table_picture(item: Tensor, index: int | None = None, names: list[str] | None = None) -> str:
    """The plain fallback picture: an HTML table of the item's objective values.

    Args:
        item: ``d`` objective values.
        index: the item's row in the pool (shown as ``item #index``), or ``None``.
        names: the ``d`` objectives' names (default ``x1 .. xd``).
    """
    values = [float(v) for v in item.reshape(-1)]
    names = names if names is not None else [f"x{k + 1}" for k in range(len(values))]
    rows = "".join(
        f"<tr><td>{html.escape(str(n))}</td><td style='text-align:right'>{v:.4g}</td></tr>"
        for n, v in zip(names, values)
    )
    head = f"<b>item #{index}</b>" if index is not None else ""
    return f"{head}<table>{rows}</table>"


def as_picture(picture: object, width: str = "100%") -> Widget:
    """An ``ipywidgets`` widget showing what a render hook returned.

    Args:
        picture: a widget (returned as is), a matplotlib ``Figure`` (drawn to PNG and closed),
            image ``bytes`` (PNG, JPEG or GIF), a :class:`~pathlib.Path` to an image file, an HTML
            ``str``, or an object with ``_repr_png_``, ``_repr_svg_`` or ``_repr_html_``.
        width: the CSS width of an image.

    Raises:
        TypeError: anything else (naming its type).
    """
    w = _widgets()
    if isinstance(picture, w.Widget):
        return picture
    if hasattr(picture, "savefig"):  # a matplotlib Figure
        buf = io.BytesIO()
        picture.savefig(buf, format="png", dpi=getattr(picture, "dpi", 100))
        if "matplotlib.pyplot" in sys.modules:  # not shown a second time by the inline backend
            sys.modules["matplotlib.pyplot"].close(picture)
        return _image(buf.getvalue(), "png", width)
    if isinstance(picture, (bytes, bytearray)):
        fmt = next((f for magic, f in _MAGIC if picture.startswith(magic)), "png")
        return _image(bytes(picture), fmt, width)
    if isinstance(picture, os.PathLike):
        path = Path(picture)
        fmt = {".jpg": "jpeg", ".jpeg": "jpeg", ".gif": "gif", ".svg": "svg+xml"}.get(path.suffix.lower(), "png")
        return _image(path.read_bytes(), fmt, width)
    if isinstance(picture, str):
        return w.HTML(picture)
    reprs: tuple[tuple[str, str | None], ...] = (("_repr_png_", "png"), ("_repr_svg_", None), ("_repr_html_", None))
    for method, kind in reprs:
        if hasattr(picture, method):
            data = getattr(picture, method)()
            if kind is not None:
                return _image(data, kind, width)
            return w.HTML(data)
    raise TypeError(
        f"a render hook must return a figure, image bytes, a Path, an HTML string or a widget, "
        f"got {type(picture).__name__}."
    )


def lake_renderer(scenario: LakeScenario) -> RenderHook:
    """A render hook for a session over a lake scenario's training paths: path ``index`` drawn on
    the information field over the lake (:mod:`torchpref.lake`'s map).

    Args:
        scenario: a :class:`~torchpref.lake.LakeScenario`; the session's pool must be its
            ``train_X`` (an option's ``index`` is its training path).

    Returns:
        ``render(item, index) -> bytes`` (a PNG).
    """
    from torchpref.frontends.elicit import plot_paths

    def render(item: Tensor, index: int | None) -> bytes:
        if index is None:
            raise ValueError("lake_renderer draws pool paths: the session's candidates must be scenario.train_X.")
        title = f"path {index}: distance {float(item[0]):.0f}, information {float(item[1]):.0f}"
        with tempfile.TemporaryDirectory() as tmp:
            png = plot_paths(scenario, [int(index)], [""], title, Path(tmp) / "path.png")
            return png.read_bytes()

    return render


class PreferenceWidget:
    """Ask a session's queries in a notebook, each option as a picture, answered by a click.

    Display it as the last expression of a cell (or ``display(widget)``); the ipywidgets box is
    :attr:`box`. Each click calls ``session.tell`` (so a session file saves it at once) and shows
    the next query.

    Args:
        session: the :class:`~torchpref.PreferenceSession` that asks and records.
        render: the render hook ``render(item, index) -> picture`` (see the module docstring);
            ``None``: a table of the objective values (:func:`table_picture`).
        noun: what an item is called in prompts ("path", "design", ...).
        picture_width: the CSS width of each option's picture.

    Attributes:
        box: the ``ipywidgets.VBox`` shown.
        buttons: the answer buttons of the current query; each has an ``answer`` attribute, the
            value passed to ``session.tell`` (``.click()`` answers from code).
        status: an ``ipywidgets.HTML`` line saying what was recorded (or what went wrong).
    """

    def __init__(
        self,
        session: PreferenceSession,
        render: RenderHook | None = None,
        *,
        noun: str = "item",
        picture_width: str = "360px",
    ) -> None:
        if not isinstance(session, PreferenceSession):
            raise TypeError(f"session must be a PreferenceSession, got {type(session).__name__}.")
        if render is not None and not callable(render):
            raise TypeError(f"render must be callable(item, index) or None, got {type(render).__name__}.")
        w = _widgets()
        self.session, self.render, self.noun, self.picture_width = session, render, noun, picture_width
        self.prompt = w.HTML()
        self.options = w.Box(layout=w.Layout(display="flex", flex_flow="row wrap", align_items="flex-start"))
        self.extra = w.HBox()
        self.status = w.HTML()
        self.undo_button = w.Button(description="undo last answer", icon="undo")
        self.undo_button.on_click(self._undo)
        self.box = w.VBox([self.prompt, self.options, self.extra, w.HBox([self.undo_button]), self.status])
        self.box.add_class("torchpref-widget")
        self.buttons: list = []
        self.query: Query | None = None
        self.refresh()

    def _ipython_display_(self) -> None:
        from IPython.display import display

        display(self.box)

    # ------------------------------------------------------------------ drawing
    def picture(self, item: Tensor, index: int | None) -> Widget:
        """The widget showing one option (the render hook's picture, or the table fallback).

        A render hook that raises, or returns something that is no picture, gets the table with
        the error above it: the session goes on (an answer already told stays recorded)."""
        failure = None
        if self.render is not None:
            try:
                pic = as_picture(self.render(item, index), self.picture_width)
                pic.add_class("torchpref-picture")
                return pic
            except Exception as exc:
                failure = _widgets().HTML(
                    f"<span style='color:#b00'>render hook failed: "
                    f"{html.escape(type(exc).__name__ + ': ' + str(exc))}</span>"
                )
        table = as_picture(table_picture(item, index, self.session.names))
        return table if failure is None else _widgets().VBox([failure, table])

    def _button(self, label: str, answer: int | float | None, style: str = ""):
        w = _widgets()
        b = w.Button(description=label, button_style=style, layout=w.Layout(width="auto"))
        b.answer = answer
        b.add_class("torchpref-answer")
        b.on_click(self._clicked)
        self.buttons.append(b)
        return b

    def refresh(self) -> None:
        """Show the session's current query (after an answer, an undo, or a change made elsewhere)."""
        w = _widgets()
        s = self.session
        self.query = q = s.ask()
        self.buttons = []
        number = f"Query {s.step + 1}" + (f" of {s.num_queries}" if not s.done else " (extra)")
        if isinstance(q, RankingQuery):
            idx = q.indices if q.indices is not None else (None,) * q.m
            self.prompt.value = f"<h3>{number}: which {self.noun} is best?</h3>"
            cards = [
                w.VBox([self.picture(x, i), self._button(f"{LETTERS[k]} is best", k, "primary")])
                for k, (x, i) in enumerate(zip(q.items, idx))
            ]
            self.extra.children = [self._button("no preference", None)]
        else:
            levels = s.num_levels
            scale = f"1 (bad) to {levels} (great)" if levels else "0 (bad) to 1 (great)"
            self.prompt.value = f"<h3>{number}: rate this {self.noun} from {scale}</h3>"
            if levels:
                row = [self._button(str(k), k, "primary") for k in range(1, levels + 1)]
            else:
                slider = w.FloatSlider(value=0.5, min=0.0, max=1.0, step=0.01, description="rating")
                submit = self._button("rate", None, "primary")
                slider.observe(lambda change: setattr(submit, "answer", change["new"]), names="value")
                submit.answer = slider.value
                row = [slider, submit]
            cards = [w.VBox([self.picture(q.item, q.index), w.HBox(row)])]
            self.extra.children = []
        self.options.children = cards
        self.undo_button.disabled = s.step == 0

    # ------------------------------------------------------------------ events
    def _saved(self) -> str:
        n = self.session.step
        where = f" (saved to {html.escape(str(self.session.path))})" if self.session.path is not None else ""
        return f"{n} answer{'s' if n != 1 else ''} in force{where}"

    def _clicked(self, button) -> None:
        self.answer(button.answer)

    def answer(self, value: int | float | None) -> None:
        """Record ``value`` as the answer to the query shown (what a button's click does) and show
        the next query. An invalid answer is reported in :attr:`status`; nothing is recorded."""
        if self.query is None:
            self.status.value = "<span style='color:#b00'>not recorded: no question is shown.</span>"
            return
        for b in self.buttons:
            b.disabled = True
        try:
            self.session.tell(self.query, value)
        except ValueError as exc:
            self.status.value = f"<span style='color:#b00'>not recorded: {html.escape(str(exc))}</span>"
            for b in self.buttons:
                b.disabled = False
            return
        done = " All planned queries are answered; more may be asked." if self.session.done else ""
        self.status.value = f"Recorded. {self._saved()}.{done}"
        self.refresh()

    def _undo(self, _button=None) -> None:
        try:
            self.session.undo()
        except ValueError as exc:
            self.status.value = f"<span style='color:#b00'>{html.escape(str(exc))}</span>"
            return
        self.status.value = f"Last answer withdrawn. {self._saved()}."
        self.refresh()
