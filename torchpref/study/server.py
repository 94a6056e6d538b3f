r"""``torchpref study serve DIR``: the participants' page (as ``torchpref serve``) over a study
folder, the population refitted as participants finish, and the experimenter's page.

* :class:`StudyStore`: a :class:`~torchpref.frontends.serve.store.SessionStore` whose new sessions
  start from the study's current population (its version recorded in the session's header) and
  whose reopened sessions start from the version they recorded; a finished participant starts a
  refit (:class:`~torchpref.study.refit.RefitRunner`, a process of its own: no answer waits).
* the experimenter's page at ``/study/`` (:mod:`~torchpref.study.page`), reached only with the
  study's key (``?key=``, printed at start and kept in ``DIR/.experimenter-key``); a
  participant's link never carries it.
"""

from __future__ import annotations

import argparse
import os
import sys

from torchpref.frontends.serve.app import Listen, NewSessions, serve_store
from torchpref.frontends.serve.items import ServeItems, items_from_csv, lake_items
from torchpref.frontends.serve.pool import PoolLimits
from torchpref.frontends.serve.store import SessionStore
from torchpref.study.folder import StudyFolder, create_study
from torchpref.study.page import study_routes
from torchpref.study.refit import RefitRunner
from torchpref.study.store import StudyStore, experimenter_key

__all__ = ["run", "study_items"]


def study_items(folder: StudyFolder) -> ServeItems:
    """The study's items, from its settings: its copy of the features CSV, or the lake."""
    settings = folder.settings()
    if settings.get("world") == "lake":
        return lake_items(int(settings.get("seed", 0)))
    return items_from_csv(
        str(folder.path / "items.csv"),
        settings.get("id_column"),
        settings.get("image_column"),
        settings.get("image_dir"),
    )


def run(args: argparse.Namespace) -> int:
    """``torchpref study serve`` (``args`` from :mod:`torchpref.cli`); returns the exit code."""
    world = args.world
    folder = create_study(
        args.folder,
        items=args.features,
        world=world,
        id_column=args.id_column,
        image_column=args.image_column,
        image_dir=args.image_dir,
        num_queries=args.queries,
        num_levels=args.levels,
        ties=not args.no_ties,
        seed=args.seed,
    )
    settings = folder.settings()
    if world is not None:
        print(f"Building the lake scenario (seed {args.seed}; cached after the first time) ...", file=sys.stderr)
    items = study_items(folder)
    new = NewSessions(settings["num_queries"], settings.get("seed", 0), settings["num_levels"], settings["ties"])
    limits = PoolLimits(max_open=args.max_open, idle_close=args.idle_close, finished_close=args.finished_close)
    refits = RefitRunner(folder, timeout=args.refit_timeout)
    key = experimenter_key(folder)

    def started(store: SessionStore, url: str) -> None:
        base = url.split("?")[0]
        print(f"torchpref study: the experimenter's page is {base}study/?key={key}  (keep it to yourself)", flush=True)

    folder.log("serving", pid=os.getpid())
    store_of_study: list[StudyStore] = []

    def make_store() -> StudyStore:
        store_of_study.append(StudyStore(folder, items, new, limits, refits))
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
