r"""``torchpref study serve DIR``: the participants' page (as ``torchpref serve``) over a study
folder, the population refitted as participants finish, and the experimenter's page.

* :class:`StudyStore`: a :class:`~torchpref.frontends.serve.store.SessionStore` whose new sessions
  start from the study's current population (its version recorded in the session's header) and
  whose reopened sessions start from the version they recorded; a finished participant starts a
  refit (:class:`~torchpref.study.refit.RefitRunner`, a process of its own: no answer waits).
* the experimenter's page at ``/study/`` (:mod:`~torchpref.study.page`), reached only with the
  study's key (``?key=``, printed at start and kept in ``DIR/.experimenter-key``); a
  participant's link never carries it.
* one server per folder (:class:`~torchpref.study.lock.ServerLock`).
"""

from __future__ import annotations

import argparse
import os
import sys

from torchpref.frontends.serve.app import Listen, NewSessions, serve_store
from torchpref.frontends.serve.items import ServeItems, items_from_csv
from torchpref.frontends.serve.pool import PoolLimits
from torchpref.frontends.serve.store import SessionStore
from torchpref.selection.defaults import named_selector
from torchpref.study.create import create_study
from torchpref.study.folder import StudyFolder
from torchpref.study.items import study_items  # importable from here too
from torchpref.study.lock import ServerLock
from torchpref.study.page import study_routes
from torchpref.study.refit import RefitRunner
from torchpref.study.store import StudyStore, experimenter_key

__all__ = ["new_sessions", "run", "study_items"]


def new_sessions(folder: StudyFolder, items: ServeItems) -> NewSessions:
    """Each new participant's session settings, from the study's: questions, levels, ties, seed and
    the selector named in study.json (``"default"`` for a study made before it was recorded)."""
    s = folder.settings()
    selector = named_selector(str(s.get("selector") or "default"), items.X.unique(dim=0).shape[0])
    return NewSessions(s["num_queries"], s.get("seed", 0), s["num_levels"], s["ties"], selector=selector)


def _given(args: argparse.Namespace) -> dict[str, object]:
    """The study settings given on the command line (those not given are the study's own, or the defaults)."""
    given: dict[str, object] = {
        "num_queries": args.queries,
        "num_levels": args.levels,
        "seed": args.seed,
        "selector": args.selector,
        "completion_code": getattr(args, "completion_code", None),
        "redirect_url": getattr(args, "redirect_url", None),
    }
    if args.no_ties:
        given["ties"] = False
    return {k: v for k, v in given.items() if v is not None}


def run(args: argparse.Namespace) -> int:
    """``torchpref study serve`` (``args`` from :mod:`torchpref.cli`); returns the exit code."""
    world = args.world
    given = _given(args)
    if world is not None:
        print(
            f"Building the lake scenario (seed {given.get('seed', 0)}; cached after the first time) ...",
            file=sys.stderr,
        )

    def check() -> None:  # the items read whole before a new study's folder is written
        if world is None:
            items_from_csv(args.features, args.id_column, args.image_column, args.image_dir)

    folder = create_study(
        args.folder,
        items=args.features,
        world=world,
        id_column=args.id_column,
        image_column=args.image_column,
        image_dir=args.image_dir,
        check=check,
        **given,
    )
    lock = ServerLock(folder)
    try:
        return _serve(args, folder, lock)
    finally:
        lock.release()


def _serve(args: argparse.Namespace, folder: StudyFolder, lock: ServerLock) -> int:
    settings = folder.settings()
    try:
        items = study_items(folder)
    except (OSError, ValueError) as err:  # its items (or their pictures) no longer read: say how out
        people = folder.sessions.is_dir() and any(folder.sessions.glob("*.session.jsonl"))
        fix = (
            "restore the files they name (the images the study was created with)"
            if people
            else f"restore the files they name, or delete the folder {folder.path} (it has no participants yet) "
            "and create it again"
        )
        raise ValueError(f"the study {folder.path}'s items cannot be read ({err}): {fix}.") from None
    new = new_sessions(folder, items)
    limits = PoolLimits(max_open=args.max_open, idle_close=args.idle_close, finished_close=args.finished_close)
    refits = RefitRunner(folder, timeout=args.refit_timeout, say=lambda line: print(line, flush=True))
    key = experimenter_key(folder)

    def started(store: SessionStore, url: str) -> None:
        base = url.split("?")[0]
        lock.serving_at(base)
        print(f"torchpref study: the experimenter's page is {base}study/?key={key}  (keep it to yourself)", flush=True)
        print(
            f"torchpref study: questions chosen by the {settings.get('selector') or 'default'} selector; "
            f"participants' links may carry ?participant=ID (recorded and exported)",
            flush=True,
        )

    folder.log("serving", pid=os.getpid())
    store_of_study: list[StudyStore] = []

    def make_store() -> StudyStore:
        store_of_study.append(StudyStore(folder, items, new, limits, refits, say=lambda line: print(line, flush=True)))
        return store_of_study[0]

    try:
        serve_store(
            make_store,
            Listen(args.host, args.port, args.allow_remote, args.token),
            extra_routes=lambda store: study_routes(store_of_study[0], key),
            started=started,
        )
    finally:
        refits.close(wait=5.0)
        folder.log("stopped")
    return 0
