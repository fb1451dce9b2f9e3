"""Crash-consistency stress: 1,000 random SIGKILLs (the normal suite runs 50).

Runs `run_kills` from `tests/store/test_saver.py` (`TestCrashConsistency`) in rounds of 50
kills on fresh backups, and prints how many operations were acknowledged and checked.

    python benchmarks/stress_crash.py [--kills 1000] [--seed 1]
"""

from __future__ import annotations

import argparse
import multiprocessing
import multiprocessing.forkserver
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # the repository: the tests package

from tests.store.test_saver import run_kills


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kills", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--round", type=int, default=50, help="kills per pair of backups")
    args = parser.parse_args()
    context = multiprocessing.get_context("forkserver")
    preload = ["rr_actors", "rr_actors._registrar", "rr_actors._store.saver", "cloudpickle"]
    context.set_forkserver_preload([*preload, "tests.store.test_saver"])  # a kill: ~0.5 s, not 5
    multiprocessing.forkserver.ensure_running()
    started = time.monotonic()
    done = loads = unloads = checkpoints = 0
    while done < args.kills:
        kills = min(args.round, args.kills - done)
        with tempfile.TemporaryDirectory() as directory:
            model = run_kills(context, Path(directory), kills=kills, seed=args.seed + done)
        done += kills
        loads += len(model.loaded)
        unloads += len(model.unloaded)
        checkpoints += model.checkpoints
        print(
            f"{done:5d} kills, {loads} loads and {unloads} unloads acknowledged and checked, "
            f"{checkpoints} background checkpoints finished"
        )
    print(f"OK: {done} kills in {time.monotonic() - started:.1f} s, no torn or lost state")


if __name__ == "__main__":
    main()
