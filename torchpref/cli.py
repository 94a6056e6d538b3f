r"""The ``torchpref`` command line.

    torchpref reproduce wave [--trials N] [--queries Q] [--seed S] [--out DIR] [--workers W]
    torchpref reproduce lake [--trials N] [--queries Q] [--seed S] [--out DIR] [--workers W]
    torchpref reproduce replay [--people N] [--splits S] [--datasets D ...] [--seed S] [--data DIR] [--out DIR] [--population]
    torchpref reproduce suite [--families F ...] [--strategies S ...] [--effort E] [--trials N] [--queries Q] [--seed S] [--out DIR]
    torchpref reproduce sushi --data DIR [--people N] [--train N] [--seeds S] [--conditions C ...] [--out DIR]
    torchpref reproduce twins [--twins N] [--folds F] [--datasets D ...] [--strategies S ...] [--queries Q] [--seed S] [--data DIR] [--out DIR]
    torchpref elicit lake [--session FILE]
    torchpref elicit --features items.csv [--id COLUMN] [--session FILE]
    torchpref fast-path build [--if-needed] [--force] | status
    torchpref --version

Each subcommand lives in its own module, imported only when it runs. Every argument is checked
before any work starts; an error a person can cause (a bad value, a file that cannot be read or
written, Ctrl-C, an optional dependency that is not installed) is one line on stderr and a non-zero exit status, never a traceback (set
``TORCHPREF_DEBUG=1`` to see one).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import importlib
import os
import signal
import sys
import threading
import time
import warnings
from pathlib import Path

from torchpref.version import __version__

# subcommand -> module with ``run(args) -> int``
REPRODUCE = {
    "wave": "torchpref.experiments.wave",
    "lake": "torchpref.experiments.lake",
    "suite": "torchpref.experiments.suite",
    "replay": "torchpref.experiments.replay_population",  # --population, else the replay's own run
    "twins": "torchpref.experiments.twins",
    "sushi": "torchpref.experiments.sushi_report",
}
ELICIT = "torchpref.frontends.elicit"
SERVE = "torchpref.frontends.serve"
NEEDS = {
    "reproduce": ("matplotlib",),  # every experiment writes figures
    "elicit lake": ("matplotlib",),  # each query shows the paths on the lake's map
    "serve": ("starlette", "uvicorn", "jinja2", "matplotlib"),  # the web page and its plots
    "study": ("starlette", "uvicorn", "jinja2", "matplotlib"),  # the study's pages, report and plots
}
"""Command (``"reproduce"``, or ``"elicit WORLD"``) -> the optional modules it needs, checked
before any work starts (a missing one: one line naming the extra, exit status 3)."""
MISSING_EXTRA = 3
RESULTS = "torchpref-results"
"""The folder (in the current one) that holds a fresh folder per ``reproduce`` run by default."""

LEGEND = {
    "wave": "mean ± standard error over the trials; WRMS (eq. 14): lower is better; "
    "TP: true positives, how many of the 15 truly best items are among the model's 15 best "
    "(higher is better)",
    "lake": "mean ± standard error over the trials; error5: mean |expected - true rating| on the test paths "
    "rated 5 (lower is better); WRMS: lower is better; chosen: the operator's level (1-5) of the path "
    "the model ranks best; share 5: fraction of trials whose chosen path is rated 5",
    "replay": "area: mean held-out comparison accuracy / top-1 over 1..n answers revealed; p: paired Wilcoxon "
    "against random over (person, split); see docs/suite.md",
    "twins": "area: mean concordance of the posterior mean with the twin's true utility over questions 1..Q; "
    "p: paired Wilcoxon against random over twins; see docs/selection.md",
    "sushi": "concordance of the posterior mean with the person's ranking / ratings on pairs touching a held-out "
    "item, at equal seconds; see docs/real_raters.md",
    "suite": "mean ± standard error over the trials; WRMS and regret: lower is better; TP: true positives "
    "among the 15 best items (higher is better); see docs/suite.md",
}


class UsageError(ValueError):
    """A command-line value that cannot be used (reported as one line, exit status 2)."""


def positive_int(text: str) -> int:
    """An argparse type: a whole number >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def non_negative_int(text: str) -> int:
    """An argparse type: a whole number >= 0."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be at least 0, got {value}")
    return value


def seconds(text: str) -> float:
    """An argparse type: a finite number of seconds >= 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not 0 <= value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a number of seconds >= 0, got {text}")
    return value


def _experiment_args(p: argparse.ArgumentParser, trials: int, queries: int) -> None:
    p.add_argument("--trials", type=positive_int, default=trials, help=f"number of trials (default {trials})")
    p.add_argument("--queries", type=positive_int, default=queries, help=f"queries per trial (default {queries})")
    p.add_argument("--seed", type=int, default=10, help="seed of the whole run (default 10)")
    p.add_argument(
        "--out",
        default=None,
        help=f"output folder (default: a new folder in ./{RESULTS}/; the committed results are in benchmarks/results)",
    )
    p.add_argument("--workers", type=positive_int, default=None, help="worker processes (default: CPU count)")


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``torchpref``'s arguments (its help texts are plain text, no markup)."""
    parser = argparse.ArgumentParser(
        prog="torchpref", description="Reproduce the paper's experiments, or learn your preferences in the terminal."
    )
    parser.add_argument("--version", action="version", version=f"torchpref {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    _reproduce_parser(sub)
    _elicit_parser(sub)
    _serve_parser(sub)
    _study_parser(sub)
    fast = sub.add_parser("fast-path", help="build (compile) the compiled small-problem path, or say where it stands")
    fast.add_argument(
        "action",
        choices=("build", "status"),
        help="build: compile it (about 2 minutes) unless the cache is current; status: say where it stands",
    )
    fast.add_argument(
        "--if-needed", action="store_true", help="and nothing (exit 0) where numba is not installed or usable"
    )
    fast.add_argument("--force", action="store_true", help="rebuild even if the cache is current")
    return parser


def _reproduce_parser(sub) -> None:
    """``torchpref reproduce``'s experiments and their arguments."""
    rep = sub.add_parser("reproduce", help="reproduce one of the paper's experiments")
    rep_sub = rep.add_subparsers(dest="experiment", required=True)
    _experiment_args(rep_sub.add_parser("wave", help="the 1-D wave-function experiment (Fig. 6)"), 100, 20)
    lake = rep_sub.add_parser("lake", help="the lake-monitoring experiment (Fig. 9)")
    _experiment_args(lake, 20, 14)
    lake.add_argument(
        "--lakes", type=positive_int, default=1, help="number of lakes, seeds SEED, SEED+1, ... (default 1)"
    )
    lake.add_argument("--cache", default=None, help="folder of cached lake scenarios (default ~/.cache/torchpref/lake)")
    suite = rep_sub.add_parser("suite", help="every strategy on the user-family benchmark suite (docs/suite.md)")
    _experiment_args(suite, 50, 20)
    suite.add_argument(
        "--families",
        nargs="+",
        default=None,
        help="families or groups ('idealised', 'realistic', 'all') to run (default: the idealised families)",
    )
    suite.add_argument(
        "--effort",
        choices=["units", "plain", "trajectories"],
        default="units",
        help="effort model: units (a rating 1, a ranking 2), plain (seconds) or trajectories (seconds with "
        "viewing time per option); default units",
    )
    suite.add_argument(
        "--strategies",
        nargs="+",
        default=None,
        metavar="STRATEGY",
        help="strategies to compare, e.g. 'UCBC' 'profile per effort' (default: the suite's eight; "
        "any of torchpref.experiments.runner.STRATEGIES)",
    )
    _replay_parser(rep_sub)
    _sushi_parser(rep_sub)
    _twins_parser(rep_sub)


def _sushi_parser(rep_sub) -> None:
    """``torchpref reproduce sushi``'s arguments (docs/real_raters.md)."""
    sp = rep_sub.add_parser("sushi", help="real people who both rated and ranked (SUSHI; docs/real_raters.md)")
    sp.add_argument(
        "--data",
        default=None,
        help="the folder of the SUSHI release (sushi3-2016, from https://www.kamishima.net/sushi/; or "
        "$TORCHPREF_SUSHI_DATA): torchpref ships none of it",
    )
    sp.add_argument("--people", type=positive_int, default=200, help="people replayed (default 200)")
    sp.add_argument("--train", type=positive_int, default=400, help="people the population is fitted on (400)")
    sp.add_argument(
        "--calibration", type=non_negative_int, default=300, help="people of the rating-model table (300; 0: skip)"
    )
    sp.add_argument("--rating-model-only", action="store_true", help="write the rating-model table only")
    sp.add_argument("--seeds", type=positive_int, default=3, help="askable / held-out splits per person (3)")
    sp.add_argument("--queries", type=positive_int, default=8, help="questions per person (8: 27 s of ratings)")
    sp.add_argument("--seed", type=int, default=0, help="seed of the draws of people (default 0)")
    sp.add_argument("--conditions", nargs="+", choices=["none", "population"], default=["none", "population"])
    sp.add_argument(
        "--policies", nargs="+", default=None, metavar="POLICY", help="default: torchpref.experiments.sushi.POLICIES"
    )
    sp.add_argument("--out", default=None, help=f"output folder (default: a new folder in ./{RESULTS}/)")
    sp.set_defaults(trials=None)


def _replay_parser(rep_sub) -> None:
    """``torchpref reproduce replay``'s arguments (docs/suite.md, docs/selection.md)."""
    rp = rep_sub.add_parser("replay", help="selectors replaying real people's recorded choices (docs/suite.md)")
    rp.add_argument("--people", type=positive_int, default=80, help="people per data set (default 80)")
    rp.add_argument("--splits", type=positive_int, default=3, help="train / held-out splits per person (default 3)")
    rp.add_argument(
        "--datasets",
        nargs="+",
        choices=["electricity", "rail"],
        default=["electricity", "rail"],
        help="which recorded choice data sets to replay (default both; copies ship in benchmarks/)",
    )
    rp.add_argument("--seed", type=int, default=0, help="seed of the people, splits and selectors (default 0)")
    rp.add_argument("--data", default=None, help="folder of the data (default: benchmarks/studies/data of a clone)")
    rp.add_argument("--out", default=None, help=f"output folder (default: a new folder in ./{RESULTS}/)")
    rp.add_argument(
        "--selectors",
        nargs="+",
        default=["random", "UCBC", "information", "per second", "information + 0.5 random"],
        metavar="SELECTOR",
        help="selectors to compare with random (torchpref.experiments.replay.SELECTORS; default: random, UCBC, "
        "information, per second, information + 0.5 random)",
    )
    rp.add_argument(
        "--population", action="store_true", help="start each person from the population fitted without them"
    )
    rp.add_argument("--folds", type=positive_int, default=3, help="--population: leave-people-out folds (3)")
    rp.add_argument(
        "--random-orders", type=positive_int, default=5, help="--population: random orders averaged (default 5)"
    )
    rp.add_argument("--cache", default=None, help="folder of fitted populations (default ~/.cache/torchpref/twins)")
    rp.set_defaults(trials=None)


def _twins_parser(rep_sub) -> None:
    """``torchpref reproduce twins``'s arguments (docs/selection.md)."""
    tw = rep_sub.add_parser("twins", help="selectors on twins of real people, with and without their population")
    tw.add_argument("--twins", type=positive_int, default=20, help="twins per data set and fold (default 20)")
    tw.add_argument("--folds", type=positive_int, default=3, help="leave-people-out folds, one population each (3)")
    tw.add_argument("--datasets", nargs="+", choices=["electricity", "rail"], default=["electricity", "rail"])
    tw.add_argument("--queries", type=positive_int, default=20, help="questions per twin (default 20)")
    tw.add_argument("--seed", type=int, default=0, help="seed of the folds and twins (default 0)")
    tw.add_argument("--data", default=None, help="folder of the data (default: benchmarks/studies/data of a clone)")
    tw.add_argument("--out", default=None, help=f"output folder (default: a new folder in ./{RESULTS}/)")
    tw.add_argument("--cache", default=None, help="folder of fitted populations (default ~/.cache/torchpref/twins)")
    tw.add_argument(
        "--strategies",
        nargs="+",
        default=None,
        metavar="STRATEGY",
        help="strategies to compare (torchpref.experiments.runner.STRATEGIES; default: "
        "torchpref.experiments.twins.SELECTORS)",
    )
    tw.set_defaults(trials=None)


def _elicit_parser(sub) -> None:
    """``torchpref elicit``'s arguments (docs/sessions.md)."""
    el = sub.add_parser("elicit", help="learn your preferences in the terminal")
    el.add_argument("world", nargs="?", metavar="WORLD", help="a built-in world to elicit over: lake")
    el.add_argument("--features", help="CSV of items' objective values (a header row, one row per item)")
    el.add_argument(
        "--id",
        dest="id_column",
        metavar="COLUMN",
        help="the CSV column that names the items (default: a first column named id, name, label or "
        "item, or holding any text)",
    )
    el.add_argument(
        "--session",
        help="session file (JSON Lines) to append to / resume from (default: "
        "NAME.session.jsonl in the current folder, NAME the CSV's or 'lake')",
    )
    el.add_argument("--no-session", action="store_true", help="keep nothing: answers are lost when it ends")
    el.add_argument("--queries", type=positive_int, default=14, help="number of queries (default 14)")
    el.add_argument(
        "--question-list",
        metavar="FILE",
        help="ask only these questions: one per line, the items' row numbers (0-based, comma-separated; "
        "one row: rate it, several: pick the best of them); the selector chooses among them",
    )
    _selector_arg(el)
    el.add_argument(
        "--seed", type=int, default=None, help="seed of a new session (default 0; a resumed session keeps its own)"
    )
    el.add_argument("--out", default=".", help="where to write figures (default: current folder)")


def _serve_parser(sub) -> None:
    """``torchpref serve``'s arguments (docs/serve.md)."""
    sv = sub.add_parser("serve", help="the answering page in a browser, one session per participant")
    sv.add_argument("world", nargs="?", metavar="WORLD", help="a built-in world to serve: lake")
    sv.add_argument("--features", help="CSV of items' objective values (as for elicit)")
    sv.add_argument("--id", dest="id_column", metavar="COLUMN", help="the CSV column that names the items")
    sv.add_argument("--image-column", metavar="COLUMN", help="the CSV column naming each item's image file")
    sv.add_argument("--image-dir", metavar="DIR", help="the folder of the images (default: the CSV's folder)")
    sv.add_argument("--sessions", default="torchpref-sessions", help="folder of the session files")
    sv.add_argument(
        "--population",
        metavar="FILE",
        help="a saved population (torchpref.save_population) each new session starts from (docs/population.md)",
    )
    sv.add_argument(
        "--population-without-names",
        action="store_true",
        help="accept a population file that records no feature names (it cannot be checked against the items)",
    )
    sv.add_argument("--queries", type=positive_int, default=14, help="questions per session (default 14)")
    sv.add_argument(
        "--question-list",
        metavar="FILE",
        help="ask only these questions (the format of elicit's --question-list: one per line, the items' "
        "0-based row numbers, comma-separated; one row: rate it, several: pick the best of them)",
    )
    _selector_arg(sv)
    sv.add_argument("--levels", type=positive_int, default=5, help="rating levels 1..K (default 5)")
    sv.add_argument("--no-ties", action="store_true", help="no 'no preference' button")
    sv.add_argument("--seed", type=int, default=0, help="seed of new sessions (and of the lake; default 0)")
    _network_args(sv)


def _selector_arg(p) -> None:
    """``--selector NAME`` (``elicit``, ``serve``): torchpref.selection.defaults.named_selector."""
    p.add_argument(
        "--selector",
        choices=("default", "ucbc", "information", "random"),
        default=None,
        help="how a new session picks its questions: default (expected information and the clipped profile per "
        "second), ucbc (the paper's: rankings early, ratings late), information, random (default: default; a "
        "resumed session keeps the one its file records)",
    )


def _network_args(sv) -> None:
    """Where a server listens and how long its sessions stay open (``serve``, ``study serve``)."""
    sv.add_argument("--host", default="127.0.0.1", help="interface to listen on (default 127.0.0.1 only)")
    sv.add_argument("--port", type=int, default=8000, help="port (default 8000; 0: a free one)")
    sv.add_argument("--allow-remote", action="store_true", help="allow --host other than this machine (needs a token)")
    sv.add_argument("--token", help="the token a browser must give (made and printed for --allow-remote if not given)")
    sv.add_argument(
        "--max-open",
        type=positive_int,
        default=None,
        metavar="N",
        help="sessions open at once; idle ones close and reopen from their files (default: from the open-files limit)",
    )
    sv.add_argument(
        "--idle-close",
        type=seconds,
        default=120.0,
        metavar="S",
        help="close a session after S seconds without a request (default 120)",
    )
    sv.add_argument(
        "--finished-close",
        type=seconds,
        default=1.0,
        metavar="S",
        help="the same once all its questions are answered (default 1)",
    )


def _study_parser(sub) -> None:
    """``torchpref study``'s commands (docs/study.md)."""
    st = sub.add_parser("study", help="a preference study: serve participants, export, report")
    st_sub = st.add_subparsers(dest="study_command", required=True)
    sv = st_sub.add_parser("serve", help="serve a study's participants (the population is refitted as they finish)")
    sv.add_argument("folder", metavar="DIR", help="the study's folder (created with its first serve)")
    sv.add_argument("world", nargs="?", metavar="WORLD", help="a built-in world to serve: lake")
    sv.add_argument("--features", help="CSV of items' objective values (as for elicit; copied into the study)")
    sv.add_argument("--id", dest="id_column", metavar="COLUMN", help="the CSV column that names the items")
    sv.add_argument("--image-column", metavar="COLUMN", help="the CSV column naming each item's image file")
    sv.add_argument("--image-dir", metavar="DIR", help="the folder of the images (default: the CSV's folder)")
    sv.add_argument("--queries", type=positive_int, default=None, help="questions per participant (default 14)")
    _selector_arg(sv)
    sv.add_argument("--levels", type=positive_int, default=None, help="rating levels 1..K (default 5)")
    sv.add_argument("--no-ties", action="store_true", help="no 'no preference' button")
    sv.add_argument("--seed", type=int, default=None, help="seed of the sessions (and of the lake; default 0)")
    sv.add_argument(
        "--completion-code",
        metavar="CODE",
        help="shown to each participant once they have answered every question (a recruitment platform's code)",
    )
    sv.add_argument(
        "--redirect-url",
        metavar="URL",
        help="where a participant who has answered every question is sent on (a recruitment platform's address)",
    )
    sv.add_argument(
        "--refit-timeout",
        type=seconds,
        default=600.0,
        metavar="S",
        help="a population refit running longer is stopped; the previous population stays (default 600)",
    )
    _network_args(sv)
    for name, what in (
        ("export", "write the answers, participants and population as CSV"),
        ("report", "write report.html"),
    ):
        p = st_sub.add_parser(name, help=what)
        p.add_argument("folder", metavar="DIR", help="the study's folder")
        p.add_argument("--out", default=None, help="where to write (default: DIR/exports)")


def seconds_since_start() -> float:
    """Seconds since this process started (Python's and torch's start-up included), where the
    system says (Linux ``/proc``); otherwise since this module was imported."""
    try:
        with open("/proc/self/stat") as f:
            after_name = f.read().rsplit(")", 1)[1].split()
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return max(0.0, uptime - int(after_name[19]) / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError, AttributeError):
        return time.perf_counter() - _IMPORTED


_IMPORTED = time.perf_counter()


def output_folder(out: str | None, experiment: str) -> Path:
    """The checked output folder: ``out`` (created, and tested for writing), or a new folder
    ``./torchpref-results/EXPERIMENT-YYYYMMDD-HHMMSS`` that did not exist before.

    Raises:
        UsageError: ``out`` is a file, cannot be created or cannot be written to.
    """
    if out is None:
        stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
        base = Path(RESULTS) / f"{experiment}-{stamp}"
        path, k = base, 1
        while path.exists():
            k += 1
            path = base.with_name(f"{base.name}-{k}")
    else:
        path = Path(out)
    return writable_folder(path, "--out")


def writable_folder(path: str | os.PathLike, flag: str) -> Path:
    """``path`` as a folder (created if missing) that this process can write to.

    Raises:
        UsageError: naming ``flag``: ``path`` is a file, cannot be created or cannot be written to.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UsageError(f"{flag} {path}: is a file, not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / f".torchpref-write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise UsageError(f"{flag} {path}: cannot write there ({exc.strerror or exc})") from None
    return path


def one_line(exc: BaseException) -> str:
    """An exception's message on one line."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) < 2000 else text[:1997] + "..."


def _import(name: str):
    """Import module ``name`` with Ctrl-C held until the import is done, then raise it: an import
    of NumPy or SciPy interrupted half-way leaves them broken (a RecursionError on next use)."""
    if threading.current_thread() is not threading.main_thread():
        return importlib.import_module(name)
    pressed = []
    previous = signal.signal(signal.SIGINT, lambda *_: pressed.append(True))
    try:
        module = importlib.import_module(name)
    finally:
        signal.signal(signal.SIGINT, previous)
    if pressed:
        raise KeyboardInterrupt
    return module


def _reproduce(args) -> int:
    if getattr(args, "cache", None) is not None:
        writable_folder(args.cache, "--cache")
    made = [p for p in (Path(args.out or RESULTS),) if not p.exists()]  # the folders this run creates
    folder = output_folder(args.out, args.experiment)
    made = ([folder] if args.out is None else []) + made
    args.out = str(folder)
    try:
        module = _import(REPRODUCE[args.experiment])
        code = int(module.run(args) or 0)
    except BaseException:
        for p in made:  # a run that failed (or was interrupted) before writing anything leaves no folder
            if p.is_dir() and not any(p.iterdir()):
                p.rmdir()
        raise
    legend = LEGEND.get(args.experiment, "mean ± standard error over the trials")
    print(f"({legend}{'; one trial has no standard error' if args.trials == 1 else ''})")
    print(f"Total wall time {seconds_since_start():.1f} s, start-up included; files in {args.out}")
    return code


WORLDS = ("lake",)
"""The built-in worlds of ``elicit`` and ``serve``."""
CSV_OPTIONS = ("--csv", "--items", "--file", "--input", "--data", "--feature")
"""Options a newcomer may try for the CSV of items (``--features`` is the one)."""


def _check_world(world: str | None, features: str | None = None) -> None:
    """A world's name, or a CSV given where the world goes: named, with ``--features``."""
    if world is None or world in WORLDS:
        return
    if features is not None:
        raise UsageError(f"unexpected argument {world!r}: the items are the --features CSV ({features})")
    if world.lower().endswith((".csv", ".tsv", ".txt")) or Path(world).is_file():
        raise UsageError(f"{world!r} is not a built-in world: to use a CSV of items, give it as --features {world}")
    raise UsageError(f"unknown world {world!r}: the built-in world is {', '.join(WORLDS)} (or --features FILE)")


def _unknown_options(unknown: list[str]) -> UsageError:
    """The error for options the command does not have, naming them (and ``--features`` for a CSV)."""
    names = [u for u in unknown if u.startswith("-")] or unknown
    hint = ""
    if any(u.split("=")[0] in CSV_OPTIONS or u.lower().endswith(".csv") for u in unknown):
        hint = "; a CSV of items is given with --features FILE"
    what = "option" if len(names) == 1 else "options"
    return UsageError(f"unknown {what} {' '.join(names)} (see --help){hint}")


def _elicit(args) -> int:
    _check_world(args.world, args.features)
    if (args.world is None) == (args.features is None):
        raise UsageError("give either a world (lake) or --features FILE")
    if args.no_session and args.session:
        raise UsageError("give --session FILE or --no-session, not both")
    if args.id_column is not None and args.features is None:
        raise UsageError("--id names a column of the --features CSV")
    if args.world is not None:  # the lake's figures: checked before its scenario is built
        writable_folder(args.out, "--out")
    return int(_import(ELICIT).run(args) or 0)


def _serve(args) -> int:
    _check_world(args.world, args.features)
    if (args.world is None) == (args.features is None):
        raise UsageError("give either a world (lake) or --features FILE")
    if args.features is None and (args.image_column or args.image_dir or args.id_column):
        raise UsageError("--id, --image-column and --image-dir are about the --features CSV")
    if args.image_dir and not args.image_column:
        raise UsageError("--image-dir needs --image-column")
    if args.levels < 2:
        raise UsageError(f"--levels must be at least 2, got {args.levels}")
    writable_folder(args.sessions, "--sessions")
    return int(_import(SERVE).run(args) or 0)


def _study(args) -> int:
    if args.study_command == "serve":
        _check_world(args.world, args.features)
        study_json = Path(args.folder) / "study.json"
        if args.world is not None and args.features is not None:
            raise UsageError("give either a world (lake) or --features FILE, not both")
        if args.world is None and args.features is None and not study_json.is_file():
            raise UsageError("a new study needs its items: a world (lake) or --features FILE")
        if args.world is None and args.features is None:  # an existing study: its own items
            from torchpref.study.folder import StudyFolder

            args.world = StudyFolder(Path(args.folder)).settings().get("world")
            args.features = None if args.world is not None else str(Path(args.folder) / "items.csv")
        if args.levels is not None and args.levels < 2:
            raise UsageError(f"--levels must be at least 2, got {args.levels}")
        return int(_import("torchpref.study.server").run(args) or 0)
    from torchpref.study.folder import StudyFolder

    folder = StudyFolder(Path(args.folder))
    folder.settings()  # a folder that is not a study: said before anything is written
    out = None if args.out is None else writable_folder(args.out, "--out")
    if args.study_command == "export":
        for f in _import("torchpref.study.export").export(folder, out):
            print(f"wrote {f}")
        return 0
    print(f"wrote {_import('torchpref.study.report').report(folder, None if out is None else out / 'report.html')}")
    return 0


def _fast_path(args) -> int:
    """``torchpref fast-path build``: compile the compiled path into its cache (progress on stdout,
    the cache's folder at the end), or say that the cache is current and do nothing (``--force``
    rebuilds it); ``status``: the setting, the cache and whether it loads."""
    from torchpref.inference import fast_cache, fast_path

    if args.action == "status":
        print(fast_path.status())
        return 0
    if args.if_needed and fast_cache.problem() is not None:
        print(f"torchpref fast-path: nothing to build: {fast_cache.problem()}")
        return 0
    if not args.force and fast_cache.problem() is None and fast_path.loads():
        print(
            f"torchpref fast-path: the cache in {fast_path.cache_folder()} is current for this installation: "
            "nothing to build (--force rebuilds it)"
        )
        return 0
    print("torchpref fast-path: compiling the compiled path for this installation (about 2 minutes, once) ...")
    try:
        fast_path.build(progress=lambda line: print(line, flush=True))
    except fast_cache.CacheUnusable as exc:
        raise ValueError(f"the compiled path cannot be built: {exc}") from None
    return 0


def _missing_extra(args: argparse.Namespace) -> str | None:
    """The one-line message for an optional module the command needs and does not find, or ``None``."""
    from torchpref.extras import missing

    key = args.command if args.command != "elicit" or args.world is None else f"elicit {args.world}"
    name = f"{args.command} {args.experiment}" if args.command == "reproduce" else key
    return missing(NEEDS.get(key, ()), f"torchpref {name}")


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status (errors and warnings: one line each on stderr)."""
    shown = warnings.showwarning
    warnings.showwarning = _warning_line
    try:
        return _main(argv)
    finally:
        warnings.showwarning = shown


def _warning_line(message, category, filename, lineno, file=None, line=None) -> None:
    """A warning as one line (no source line): ``torchpref: SomeWarning: message``."""
    print(f"torchpref: {category.__name__}: {one_line(message)}", file=sys.stderr if file is None else file)


def _main(argv: list[str] | None) -> int:
    command = "torchpref"
    try:
        args, unknown = build_parser().parse_known_args(argv)
        command = f"torchpref {args.command}"
        if unknown:
            raise _unknown_options(unknown)
        if (line := _missing_extra(args)) is not None:
            print(line, file=sys.stderr)
            return MISSING_EXTRA
        if os.environ.get("TORCHPREF_FAST_PATH", "").strip():  # only then: checking it imports torch
            from torchpref.inference.fast_path import check_setting

            check_setting()  # a mistyped TORCHPREF_FAST_PATH is named now, not at the first solve or page
        if args.command == "fast-path":
            return _fast_path(args)
        if args.command == "serve":
            return _serve(args)
        if args.command == "study":
            return _study(args)
        if args.command == "reproduce":
            from torchpref.experiments.stamp import recording_subprocesses

            with recording_subprocesses():  # its stamps hash the code its worker processes ran too
                return _reproduce(args)
        return _elicit(args)
    except KeyboardInterrupt:
        print(f"\n{command}: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError) as exc:  # what a person can cause: bad values, unreadable files
        if os.environ.get("TORCHPREF_DEBUG"):
            raise
        print(f"{command}: {one_line(exc)}", file=sys.stderr)
        return 2
    except Exception as exc:  # a bug: still one line, with a way to see more
        if os.environ.get("TORCHPREF_DEBUG"):
            raise
        print(
            f"{command}: internal error ({type(exc).__name__}: {one_line(exc)}); run with TORCHPREF_DEBUG=1 "
            "to see where, and please report it",
            file=sys.stderr,
        )
        return 1


if __name__ == "__main__":
    sys.exit(main())
