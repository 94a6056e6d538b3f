r"""``torchpref elicit``: learn a person's preferences in the terminal.

    torchpref elicit lake [--session FILE] [--queries Q] [--seed S] [--out DIR]
    torchpref elicit --features items.csv [--id COLUMN] [--session FILE] [--queries Q] [--seed S]

Each query is shown as a table of the items' objective values (for the lake, also as a PNG of
the candidate paths on the map, written to ``--out``). A rating is answered with a whole number
``1..5``, a ranking with the letter of the best item; ``=`` says "no preference" (a tie between
the items shown, docs/likelihoods.md), ``u`` undoes the last answer, ``?`` shows help and ``q`` quits. Bad
input is explained and asked again. Every answer is saved (and fsynced) as it is given, to
``--session`` or by default to ``NAME.session.jsonl`` in the current folder (``--no-session``:
nothing is kept): run the same command again to continue. At the end the learned utility's best
items are shown (for the lake, the path the robot would pick).

Nothing a person types or puts in a file shows a traceback: errors are one line on stderr with
a non-zero exit status, and labels from a CSV are printed with control characters replaced.
The model works on the objectives normalised to the unit cube by the items' range
(:class:`~torchpref.sessions.session.PreferenceSession`'s ``bounds``).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

import torch
from torch import Tensor

from torchpref.data.features import FeaturesError, printable, read_features_csv
from torchpref.data.queries import Query, RankingQuery, first_unique_rows
from torchpref.selection.defaults import named_selector
from torchpref.sessions.contents import read_session_header
from torchpref.sessions.errors import SessionFileCorrupt, SessionFileError, SessionMismatchError
from torchpref.sessions.query_list import read_question_list
from torchpref.sessions.session import PreferenceSession

if TYPE_CHECKING:
    from torchpref.lake.scenario import LakeScenario

__all__ = ["FeaturesError", "FeaturesWorld", "LakeWorld", "plot_paths", "read_features_csv", "run"]

LETTERS = "ABCDEFGHIJKLMNOPQRSTUVWXYZ"
NUM_LEVELS = 5

HELP = """\
Answers:
  rating query   a whole number from 1 (unacceptable) to 5 (excellent)
  ranking query  the letter of the best item (A, B, ...); '=' if you have no preference
                 (the items shown are then taken to be about equally good)
  u              undo your last answer (it is asked again)
  ?              this help
  q              quit (with --session, every answer so far is saved; run the same command to continue)"""


# ----------------------------------------------------------------------------- worlds
class FeaturesWorld:
    """Items given as rows of objective values."""

    noun = "item"

    def __init__(self, X: Tensor, names: list[str], labels: list[str] | None):
        self.X, self.names, self.labels = X, names, labels

    def label(self, i: int | None) -> str:
        """How item ``i`` (a pool row) is named to the person (``-`` for none)."""
        if i is None:
            return "-"
        return self.labels[i] if self.labels is not None else f"#{i + 1}"

    def show(self, query: Query, number: int, out: TextIO) -> None:
        """Show query ``number`` beyond its table (plain features: nothing more)."""
        pass

    def finish(self, session: PreferenceSession, out: TextIO) -> None:
        """Say what was learned beyond the top items (plain features: nothing more)."""
        pass


class LakeWorld(FeaturesWorld):
    """The lake scenario's training paths, objectives ``[distance, information]``."""

    noun = "path"

    def __init__(self, seed: int, out_dir: Path):
        from torchpref.lake.scenario import cached_scenario, scenario_cache_path

        if not scenario_cache_path(seed).exists():
            print(
                f"Building the lake of seed {seed} (once; it is cached in {scenario_cache_path(seed).parent}) ...",
                file=sys.stderr,
            )
        self.scenario = cached_scenario(seed, progress=True)
        self.out_dir = out_dir
        super().__init__(self.scenario.train_X, ["distance", "information"], None)

    def label(self, i: int | None) -> str:
        """``path i`` (``-`` for ``None``)."""
        return "-" if i is None else f"path {i}"

    def show(self, query: Query, number: int, out: TextIO) -> None:
        """Write a map of the query's paths, labelled by their letters, and say where it is."""
        named = query.indices if isinstance(query, RankingQuery) else (query.index,)
        rows = [i for i in (named or ()) if i is not None]
        if len(rows) != query.items.shape[0]:
            raise ValueError(f"a lake query must name its paths' pool rows, got {named!r}.")
        letters = LETTERS[: len(rows)] if isinstance(query, RankingQuery) else ["?"]
        title = (
            f"Query {number}: which path is best?"
            if isinstance(query, RankingQuery)
            else f"Query {number}: rate this path from 1 to {NUM_LEVELS}"
        )
        png = plot_paths(self.scenario, rows, letters, title, self.out_dir / f"query-{number:02d}.png")
        print(f"Map of the {'paths' if len(rows) > 1 else 'path'}: {png}", file=out)

    def finish(self, session: PreferenceSession, out: TextIO) -> None:
        """Plan a path with the learned utility, draw it with the pool's best and recommend one."""
        from torchpref.experiments.lake_plan import PLAN_SETTINGS, plan_for_model
        from torchpref.lake.plotting import plot_paths as plot_map

        i, x = session.best_item()
        print(f"The robot would plan path {i}: distance {float(x[0]):.1f}, information {float(x[1]):.1f}.", file=out)
        rows = torch.arange(self.scenario.train_X.shape[0])
        plan = plan_for_model(self.scenario, session.model, session.bounds, rows)
        d, info = plan["planned_objectives"]
        shown = plan["shown_row"]
        sure = 100 * float(torch.special.ndtr(torch.tensor(float(PLAN_SETTINGS["beta"]))))
        if plan["source"] == "fallback":
            text = (
                f"Recommended: path {shown} (the best path you answered about): no planned path is at least "
                f"{sure:.0f} % sure to be better."
            )
        else:
            text = (
                f"Recommended: a planned path, distance {d:.1f}, information {info:.1f}: the learned utility is "
                f"at least {sure:.0f} % sure it beats path {shown}, the best path you answered about."
            )
        paths = [self.scenario.train_paths[i], self.scenario.train_paths[shown]]
        labels = [
            f"pool's best (path {i}): d={float(x[0]):.0f}, I={float(x[1]):.0f}",
            f"best answered (path {shown}{', recommended' if plan['source'] == 'fallback' else ''}): "
            f"d={plan['shown_objectives'][0]:.0f}, I={plan['shown_objectives'][1]:.0f}",
        ]
        if plan["source"] != "fallback":
            paths.append(torch.tensor(plan["path"]))
            labels.append(f"planned (recommended): d={d:.0f}, I={info:.0f}")
        png = plot_map(
            self.scenario,
            paths,
            labels,
            self.out_dir / "best-path.png",
            title="The pool's best path, the best answered path and the planned path",
        )
        print(f"{text} Map: {png}", file=out)


def plot_paths(scenario: LakeScenario, rows: list[int], letters: Sequence[str], title: str, path: Path) -> Path:
    """The lake's map (:func:`torchpref.lake.plotting.plot_paths`: field with colour bar, land
    masked) with the training paths ``rows``, labelled by ``letters``, as a PNG."""
    from torchpref.lake.plotting import plot_paths as plot_map

    X = scenario.train_X
    labels = [
        f"{letter}: d={float(X[r, 0]):.0f}, I={float(X[r, 1]):.0f}".lstrip(": ") for r, letter in zip(rows, letters)
    ]
    return plot_map(scenario, [scenario.train_paths[r] for r in rows], labels, Path(path), title=title, dpi=90)


# ----------------------------------------------------------------------------- terminal
def _table(
    world: FeaturesWorld,
    rows: list[int | None],
    X: Tensor,
    letters,
    out: TextIO,
    extra: str = "",
    extras: list[str] | None = None,
) -> None:
    """Items as rows: a letter (or rank), the label, the objectives' values, and ``extras``."""
    names = world.names
    width = [max(10, len(n)) for n in names]
    lw = max([12] + [len(world.label(r)) + 2 for r in rows])
    print("      " + f"{world.noun:<{lw}}" + "  ".join(f"{n:>{w}}" for n, w in zip(names, width)) + extra, file=out)
    for k, (letter, r, x) in enumerate(zip(letters, rows, X)):
        vals = "  ".join(f"{float(v):>{w}.4g}" for v, w in zip(x, width))
        print(f"  {letter:>2}  {world.label(r):<{lw}}{vals}" + (extras[k] if extras else ""), file=out)


def _read(prompt: str, inp: TextIO, out: TextIO) -> str | None:
    out.write(prompt)
    out.flush()
    line = inp.readline()
    if not line:
        return None
    return line.strip()


def _ask_answer(query: Query, inp: TextIO, out: TextIO):
    """Read an answer: ``("answer", value)``, ``("undo",)`` or ``("quit",)``; re-ask on bad input."""
    ranking = isinstance(query, RankingQuery)
    if isinstance(query, RankingQuery):
        valid = LETTERS[: query.m]
        prompt = f"Which is best? [{valid[0]}-{valid[-1]}, = no preference, u undo, ? help, q quit]: "
    else:
        prompt = f"Your rating [1-{NUM_LEVELS}, u undo, ? help, q quit]: "
    while True:
        text = _read(prompt, inp, out)
        if text is None:
            return ("quit",)
        low = text.lower()
        if low in ("q", "quit", "exit"):
            return ("quit",)
        if low in ("u", "undo"):
            return ("undo",)
        if low in ("?", "h", "help"):
            print(HELP, file=out)
            continue
        if ranking:
            if low == "=":
                return ("answer", None)
            if len(text) == 1 and text.upper() in valid:
                return ("answer", valid.index(text.upper()))
            print(
                f"{printable(text)!r} is not one of the items: type a letter from {valid[0]} to {valid[-1]} "
                "(or ? for help).",
                file=out,
            )
        else:
            if text.isascii() and text.isdigit() and 1 <= int(text) <= NUM_LEVELS:  # not '²' or '①'
                return ("answer", int(text))
            print(
                f"{printable(text)!r} is not a rating: type a whole number from 1 (unacceptable) to {NUM_LEVELS} "
                "(excellent), or ? for help.",
                file=out,
            )


def _show_query(world: FeaturesWorld, session: PreferenceSession, query: Query, out: TextIO) -> None:
    number = session.step + 1
    print("", file=out)
    if isinstance(query, RankingQuery):
        print(f"Query {number} of {session.num_queries}: which {world.noun} is best?", file=out)
        rows: list[int | None] = list(query.indices) if query.indices is not None else [None] * query.m
        _table(world, rows, query.items, LETTERS[: query.m], out)
    else:
        print(
            f"Query {number} of {session.num_queries}: rate this {world.noun} from 1 (unacceptable) to "
            f"{NUM_LEVELS} (excellent).",
            file=out,
        )
        _table(world, [query.index], query.items, [" "], out)
    world.show(query, number, out)


def _summary(world: FeaturesWorld, session: PreferenceSession, out: TextIO, top: int = 5) -> None:
    X = world.X
    distinct = first_unique_rows(X)  # identical items (the lake's identical paths) listed once
    mean, std = session.predict(X)
    level = (NUM_LEVELS * session.expected_rating(X) + 0.5).clamp(1, NUM_LEVELS)  # inverse of likert_to_unit
    order = distinct[mean[distinct].argsort(descending=True)[:top]]
    print("", file=out)
    print(
        f"Learned utility: your top {order.numel()} {world.noun}s "
        f"(from {_plural(session.step, 'answer')}; utility: posterior mean +- standard deviation, higher is "
        "better; expected rating: on the 1-5 scale):",
        file=out,
    )
    extras = [
        f"  {float(mean[i]):+6.2f} +- {float(std[i]):.2f}   {float(level[i]):.1f} / {NUM_LEVELS}"
        for i in order.tolist()
    ]
    _table(
        world,
        order.tolist(),
        X[order],
        [str(k + 1) for k in range(order.numel())],
        out,
        "     utility   expected rating",
        extras,
    )
    world.finish(session, out)


def _plural(n: int, noun: str, nouns: str | None = None) -> str:
    return f"{n} {noun}" if n == 1 else f"{n} {nouns or noun + 's'}"


def session_path(args: argparse.Namespace) -> Path | None:
    """The session file: ``--session``, none with ``--no-session``, else ``NAME.session.jsonl``
    in the current folder (``NAME``: the CSV's name, or ``lake``)."""
    if args.no_session:
        return None
    if args.session:
        return Path(args.session)
    return Path(f"{Path(args.features).stem if args.features else args.world}.session.jsonl")


def _open_session(
    world: FeaturesWorld, args, path: Path | None, seed: int, inp: TextIO, out: TextIO
) -> PreferenceSession | None:
    n = torch.unique(world.X, dim=0).shape[0]  # distinct items
    if n < 2:
        raise SessionFileError("need at least two distinct items to elicit preferences.")
    kwargs = dict(
        selector=None if getattr(args, "selector", None) is None else named_selector(args.selector, n, NUM_LEVELS),
        queries=question_list(getattr(args, "question_list", None), world.X),
        seed=seed,
        num_queries=args.queries,
        num_levels=NUM_LEVELS,
        names=world.names,
        session_file=path,
        metadata={"world": args.world or "features", "features": args.features},
    )
    try:
        return PreferenceSession(world.X, **kwargs)
    except SessionMismatchError as err:
        what = "CSV" if args.features else "world"
        theirs, mine = err.theirs.strip("()"), err.mine.strip("()")
        raise SessionFileError(
            f"{path} was started with other {err.setting} ({theirs}) than this {what}'s ({mine}); "
            f"give another --session file, or the {what} it was started with."
        ) from None
    except SessionFileCorrupt as err:
        print(f"torchpref elicit: {err}", file=sys.stderr)
        if not err.repairable:
            return None
        answer = _read("Repair the file now (the partial line is kept in a .dropped file)? [y/N]: ", inp, out)
        if (answer or "").lower() not in ("y", "yes"):
            return None
        return PreferenceSession(world.X, repair=True, **kwargs)


def question_list(path: str | None, X: torch.Tensor) -> list[Query] | None:
    """The questions of ``--question-list`` (:func:`~torchpref.sessions.query_list.read_question_list`),
    ``None`` without a file."""
    return None if path is None else read_question_list(path, X)


def _file_seed(path: Path | None) -> int | None:
    """The seed of an existing session file (so a resumed lake has the same paths), if any."""
    if path is None or not path.is_file():
        return None
    try:
        header = read_session_header(path)
    except SessionFileError:
        return None  # reported when the session is opened
    return None if header is None else header.seed


def run(args: argparse.Namespace, stdin: TextIO | None = None, stdout: TextIO | None = None) -> int:
    """Run an elicitation in the terminal (``args`` from :mod:`torchpref.cli`); returns the exit code.

    Raises:
        FeaturesError, SessionFileError, OSError: a file that cannot be used (the command line
            prints them as one line).
    """
    inp = sys.stdin if stdin is None else stdin
    out = sys.stdout if stdout is None else stdout
    path = session_path(args)
    seed = _file_seed(path)
    if seed is not None and args.seed is not None and args.seed != seed:
        print(
            f"Note: {path} was started with seed {seed}; continuing with it (--seed {args.seed} is for a new session).",
            file=out,
        )
    seed = seed if seed is not None else (0 if args.seed is None else args.seed)
    if args.features is not None:
        X, names, labels = read_features_csv(args.features, getattr(args, "id_column", None))
        world: FeaturesWorld = FeaturesWorld(X, names, labels)
    else:
        print(f"Building the lake scenario (seed {seed}) ...", file=out, flush=True)
        world = LakeWorld(seed, Path(args.out))
    session = _open_session(world, args, path, seed, inp, out)
    if session is None:
        return 2
    with session:
        return _loop(world, session, path, inp, out)


def _loop(world: FeaturesWorld, session: PreferenceSession, path: Path | None, inp: TextIO, out: TextIO) -> int:
    n = world.X.shape[0]
    print(
        f"{_plural(n, world.noun)}, objectives: {', '.join(world.names)}. "
        f"{_plural(session.num_queries, 'query', 'queries')}; type ? for help.",
        file=out,
    )
    if path is not None:
        note = f"resuming with {_plural(session.step, 'answer')}" if session.step else "a new session"
        print(f"Answers are saved to {path} as you give them ({note}).", file=out)
    else:
        print("Answers are not saved (--no-session).", file=out)
    saved = f"saved in {path}; run the same command to continue" if path else "nothing saved: --no-session"
    try:
        while not session.done:
            query = session.ask()
            _show_query(world, session, query, out)
            reply = _ask_answer(query, inp, out)
            if reply[0] == "quit":
                print(f"\nStopped after {_plural(session.step, 'answer')} ({saved}).", file=out)
                return 0
            if reply[0] == "undo":
                if session.step == 0:
                    print("Nothing to undo yet.", file=out)
                else:
                    undone = session.undo()
                    print(f"Undid your answer to query {session.step + 1} ({_describe(undone)}).", file=out)
                continue
            try:
                session.tell(query, reply[1])
            except ValueError as exc:  # not expected for a validated answer; never lose the session
                print(f"That answer could not be used ({exc}); please try again.", file=out)
                continue
            if reply[1] is None:
                print("Noted: no preference. The model now takes these items to be about equally good.", file=out)
    except KeyboardInterrupt:
        print(f"\nInterrupted after {_plural(session.step, 'answer')} ({saved}).", file=out)
        return 130
    print(f"\nThank you: {_plural(session.step, 'answer')}.", file=out)
    _summary(world, session, out)
    return 0


def _describe(answer) -> str:
    if answer.kind == "rating":
        return f"rating {answer.answer}"
    if answer.kind == "choice":
        return f"chose {LETTERS[answer.answer]}"
    return "no preference"
