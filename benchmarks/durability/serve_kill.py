r"""``torchpref serve`` killed with SIGKILL ``--kills`` times during scripted answering: how many
acknowledged answers are lost (target: 0 over 20 kills).

One session is answered over HTTP (:func:`torchpref.testing.serve.kill_run`: one or two answers, then one
sent with the server killed after a random delay of 0-300 ms, the server restarted, the answer
sent again if its reply was lost, as the page does). At the end every acknowledged answer must be
the record at its question's position in the session file, with its answer, in force, and the
file must hold no answer that was not acknowledged.

Writes ``results/serve/kill.json``.

Usage::

    .venv/bin/python benchmarks/durability/serve_kill.py [--kills 20] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
from torchpref.experiments.results import write_json  # noqa: E402
from torchpref.testing.serve import kill_run  # noqa: E402


def main() -> None:
    from tqdm import tqdm

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kills", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(HERE.parent / "results" / "serve"))
    args = ap.parse_args()
    start, load = time.perf_counter(), os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp, tqdm(total=args.kills, desc="kills", unit="kill") as bar:
        result = kill_run(Path(tmp), kills=args.kills, seed=args.seed, progress=lambda n: bar.update(1))
    result.update(
        seed=args.seed,
        wall_s=round(time.perf_counter() - start, 1),
        load_average_before=load,
        load_average_after=os.getloadavg(),
        lost_count=len(result["lost"]),
    )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json((out / "kill.json"), result, measured="user")
    print(json.dumps({k: v for k, v in result.items() if k != "kill_delays_s"}, indent=1))


if __name__ == "__main__":
    from torchpref.experiments.stamp import recording_subprocesses

    with recording_subprocesses():  # the stamp hashes the code of every process it starts too
        main()
