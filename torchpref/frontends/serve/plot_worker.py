r"""The summary plot of ``torchpref serve``, drawn from plain numbers, and the worker process that
draws it (:class:`~torchpref.frontends.serve.plots.Plots` starts it).

This file imports neither torch nor the rest of torchpref: run by its path
(``python serve_plot_worker.py``) it is a small process of its own (matplotlib and NumPy), at a
lower priority than the server, that reads jobs from its standard input and writes PNGs to its
standard output. A plot drawn there never holds the server's interpreter lock, so answers are
not slowed by it. The server also imports :func:`draw_utility` to draw in a thread where no
process can be started.

The protocol: each message is a 4-byte big-endian length and that many bytes of a pickle; a job
is a ``dict`` (:func:`draw_utility`'s data), a reply is ``("ok", png_bytes)`` or ``("error", text)``.
"""

from __future__ import annotations

import io
import os
import pickle
import struct
import sys
from typing import Any, BinaryIO

__all__ = ["draw_utility", "read_message", "write_message"]


def draw_utility(data: dict[str, Any]) -> bytes:
    """A PNG of the learned utility (the summary page's plot) from ``data``: ``step`` (answers),
    ``xs`` and ``ys`` (every item's two objectives; ``ys`` ``None`` for one objective), ``mean``
    and ``std`` (the posterior at every item), ``seen`` (rows answered about), ``best`` (the row
    recommended), ``xlabel``, ``ylabel``."""
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 4.6), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    if data["step"] == 0:
        ax.text(0.5, 0.5, "no answers yet", ha="center", va="center", transform=ax.transAxes)
        ax.set_axis_off()
    else:
        xs, mean, std = (np.asarray(data[k], dtype=float) for k in ("xs", "mean", "std"))
        seen, best = list(data["seen"]), int(data["best"])
        if data["ys"] is None:
            o = xs.argsort()
            m, sd = mean[o], std[o]
            ax.fill_between(xs[o], m - 2 * sd, m + 2 * sd, color="#9ecae1", alpha=0.5, label="± 2 sd")
            ax.plot(xs[o], m, color="#08519c", marker=".", label="posterior mean")
            ax.set_ylabel("utility")
        else:
            ys = np.asarray(data["ys"], dtype=float)
            pts = ax.scatter(xs, ys, c=mean, cmap="viridis", s=36, edgecolors="none")
            fig.colorbar(pts, ax=ax, label="utility (posterior mean)")
            if seen:
                rows = sorted(seen)
                ax.scatter(xs[rows], ys[rows], s=90, facecolors="none", edgecolors="#d62728", label="answered about")
            ax.scatter(xs[best], ys[best], marker="*", s=320, c="#ff7f0e", edgecolors="k", label="recommended")
            ax.set_ylabel(data["ylabel"])
        ax.set_xlabel(data["xlabel"])
        ax.legend(loc="best", fontsize=8)
        shown, of = len(data["xs"]), data.get("of", len(data["xs"]))
        part = f" ({shown:,} of {of:,} items drawn)" if shown < of else ""
        ax.set_title(f"Learned utility from {data['step']} answers{part}")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def write_message(stream: BinaryIO, obj: object) -> None:
    """Write ``obj`` as one message (length, pickle) and flush."""
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(struct.pack(">I", len(data)) + data)
    stream.flush()


def read_message(stream: BinaryIO) -> Any:
    """Read one message; ``EOFError`` at the end of the stream."""
    head = stream.read(4)
    if len(head) < 4:
        raise EOFError
    (n,) = struct.unpack(">I", head)
    data = stream.read(n)
    if len(data) < n:
        raise EOFError
    return pickle.loads(data)


def main() -> None:
    """Draw jobs from standard input until it closes."""
    try:
        os.nice(int(os.environ.get("TORCHPREF_PLOT_NICE", "10")))
    except (OSError, ValueError, AttributeError):
        pass
    jobs, replies = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # nothing else may write into the replies
    draw_utility({"step": 0})  # matplotlib loaded before the first job
    write_message(replies, ("ready", b""))
    while True:
        try:
            job = read_message(jobs)
        except EOFError:
            return
        reply: tuple[str, Any]
        try:
            reply = ("ok", draw_utility(job))
        except Exception as exc:  # a bad job: said, and the next one is drawn
            reply = ("error", f"{type(exc).__name__}: {exc}")
        write_message(replies, reply)


if __name__ == "__main__":
    if sys.path and os.path.abspath(sys.path[0]) == os.path.dirname(os.path.abspath(__file__)):
        sys.path.pop(0)  # this folder's modules must not shadow others (run by path)
    main()
