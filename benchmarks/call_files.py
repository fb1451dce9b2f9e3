"""The source files one call crosses, counted in every thread of every process.

Three windows, each counted the way `count_restart.py` counts a restart (its tracer, as
`sitecustomize` on `PYTHONPATH`: `sys.setprofile` and `threading.setprofile` in every
process of the tree from its start; each process forgets what it recorded at the mark
and writes the files it ran after the window):

    thread    one `registrar.call(...)` from a registrar of this process (the
              supervisor's `registrar()`) to a manager with `isolation="thread"`
    process   the same call to a manager with `isolation="process"`
    restart   a SIGKILL of a process manager until its new incarnation answers a call
              (`count_restart.py`'s window: the consumer is a manager process too)

The heartbeat is off (its pings run whether or not a call does), as in `count_restart.py`.
Each call is a dedup hit (its request loaded in the warm-up), after a warm-up call, so
neither the first client nor a `load` is counted; the tree has a `state_dir`, so both
registrars are durable, as a supervisor's managers are (a hit commits a consumer id).
Counted: the distinct files under `rr_actors/` and `rr_actors_lab/` run by any thread of
any process of the tree in the window; `--list` prints them. Read the rounds after the
first: the first window also counts the spare manager process the supervisor forks and
warms in the background. Run it from the root of the tree to count (the managers'
forkservers put the working folder first on `sys.path`).

pykka's own `ask` (an actor answering a message in this process), counted the same way
over pykka's files, is printed as the floor.

`--fresh`: each counted call asks for a new request (a load, not a hit).

Usage: python benchmarks/call_files.py [--rounds 3] [--list] [--only thread|process|restart]
       [--fresh]
"""

from __future__ import annotations

import argparse
import functools
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

from count_restart import BOUND, ours, provider_setup, run, signal_all, traced_work

CASES = ("thread", "process", "restart")


def counted_files(folder: str, action: Callable[[], object]) -> set[str]:
    """The package files every process ran while `action` ran."""
    signal_all(folder, signal.SIGUSR1, ".marked")
    action()
    files = signal_all(folder, signal.SIGUSR2, ".files")
    found: set[str] = set()
    for written in files.values():
        found |= ours(written.read_text().split("\n"))
    return found


def call_rounds(
    folder: str, work: str, isolation: Literal["thread", "process"], rounds: int, *, fresh: bool
) -> list[set[str]]:
    """`rounds` dedup-hit calls to a manager of `isolation`, each counted (`fresh`: each
    call a new request, so a load)."""
    import rr_actors as rr  # noqa: PLC0415 - after the tracer is installed

    spec = rr.ManagerSpec("provider", provider_setup, isolation=isolation, heartbeat=None)
    with rr.Supervisor([spec], state_dir=Path(work, f"state-{isolation}")) as sup:
        caller = sup.registrar(f"caller-{isolation}")
        try:
            for _ in range(2):  # (warm-up: the client, the load, the first hit)
                caller.call("provider", "res", "warm-up", timeout=BOUND)
            return [
                counted_files(
                    folder,
                    functools.partial(
                        caller.call,
                        "provider",
                        "res",
                        f"fresh-{n}" if fresh else "warm-up",
                        timeout=BOUND,
                    ),
                )
                for n in range(rounds)
            ]
        finally:
            caller.stop()


def pykka_floor(rounds: int) -> list[set[str]]:
    """pykka's files run by one `ask` of a started actor, in this process (every thread:
    the actor's thread starts after the tracer)."""
    import pykka  # noqa: PLC0415 - after the tracer is installed

    class Echo(pykka.ThreadingActor):
        def on_receive(self, message: Any) -> Any:
            return message

    seen = sys.modules["sitecustomize"].SEEN
    ref = Echo.start()
    try:
        ref.ask("warm-up", timeout=BOUND)
        counts = []
        for _ in range(rounds):
            seen.clear()
            ref.ask("counted", timeout=BOUND)
            counts.append(
                {name[name.rindex("/pykka/") + 1 :] for name in seen.copy() if "/pykka/" in name}
            )
        return counts
    finally:
        ref.stop()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3, help="windows counted per case")
    parser.add_argument("--list", action="store_true", help="the files of each case's last round")
    parser.add_argument("--only", choices=CASES, help="one case")
    parser.add_argument("--fresh", action="store_true", help="calls that load (thread, process)")
    args = parser.parse_args()
    cases = (args.only,) if args.only else CASES
    with traced_work() as (work, folder):
        found: dict[str, list[set[str]]] = {"pykka ask (floor)": pykka_floor(args.rounds)}
        for case in cases:
            if case == "restart":
                restarts = run(args.rounds, False, folder, work, kill=True)
                found[case] = [set().union(*each.values()) for each in restarts]
            else:
                isolation: Literal["thread", "process"] = (
                    "thread" if case == "thread" else "process"
                )
                found[case] = call_rounds(folder, work, isolation, args.rounds, fresh=args.fresh)
    print("distinct rr_actors/ and rr_actors_lab/ files run in the window, every process")
    print("| case | " + " | ".join(f"round {n}" for n in range(1, args.rounds + 1)) + " |")
    print("|---|" + "---:|" * args.rounds)
    for case, rounds in found.items():
        print(f"| {case} | " + " | ".join(str(len(files)) for files in rounds) + " |")
    if args.list:
        for case, rounds in found.items():
            print(f"\n{case} ({len(rounds[-1])}):")
            for name in sorted(rounds[-1]):
                print(f"  {name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
