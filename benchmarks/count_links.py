"""Threads and sockets per manager process as a tree of process managers grows (issue 69).

A `Supervisor` of N process managers with a `state_dir` (each a catalog of its own, one
server) is started and timed; every manager answers one call from a registrar of this
process; then each manager process's threads (`/proc/<pid>/task`) and open sockets
(`/proc/<pid>/fd`, links to `socket:`) are counted, and again after `--restarts`
managers were SIGKILLed and restarted one at a time; then it is stopped. Linux only.
A tree of more than 100 processes goes through the machine's lock on a shared machine
(`flock /work/big.lock python benchmarks/count_links.py --counts 1000`).

Usage: python benchmarks/count_links.py [--counts 10 100] [--restarts 3] [--no-state]
"""

from __future__ import annotations

import argparse
import os
import signal
import tempfile
import time

import _harness

import rr_actors as rr


def setup(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("res", load=lambda r: r, unload=lambda r, s: None)


def counts(pid: int) -> tuple[int, int]:
    """Process `pid`'s threads and open sockets."""
    sockets = 0
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            sockets += os.readlink(f"/proc/{pid}/fd/{fd}").startswith("socket:")
        except OSError:  # (closed meanwhile)
            continue
    return len(os.listdir(f"/proc/{pid}/task")), sockets


def spread(sup: rr.Supervisor) -> str:
    """Threads and sockets per manager: min/median/max."""
    found = [counts(info.pid) for info in sup.which_children() if info.pid]
    threads, sockets = [c[0] for c in found], [c[1] for c in found]
    return (
        f"{min(threads)}/{_harness.median(threads):g}/{max(threads)} | "
        f"{min(sockets)}/{_harness.median(sockets):g}/{max(sockets)}"
    )


def run(size: int, restarts: int, state: bool) -> None:
    with tempfile.TemporaryDirectory() as state_dir:
        specs = [rr.ManagerSpec(f"m{i}", setup, isolation="process") for i in range(size)]
        sup = rr.Supervisor(specs, state_dir=state_dir if state else None, max_restarts=1000)
        began = time.perf_counter()
        sup.start()
        started = time.perf_counter() - began
        try:
            app = sup.registrar("app")
            for i in range(size):
                app.call(f"m{i}", "res", i, timeout=60.0)
            row = f"| {size} | {state} | {started:.2f} | {spread(sup)} |"
            for k in range(restarts):
                name = f"m{(k * 7) % size}"
                os.kill(sup.child(name).pid or 0, signal.SIGKILL)
                sup.wait_restarted(name, timeout=60.0)
            after = spread(sup) if restarts else "-"
            load = os.getloadavg()[0]
            print(f"{row} {after} | {load:.1f} |", flush=True)
        finally:
            sup.stop()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[10, 100])
    parser.add_argument("--restarts", type=int, default=3)
    parser.add_argument("--no-state", action="store_true", help="no state_dir (no catalogs)")
    args = parser.parse_args()
    _harness.head(
        _harness.header("threads and sockets per manager process"),
        (
            "managers", "state_dir", "start (s)", "threads min/med/max \\| sockets min/med/max",
            "the same after the restarts", "load",
        ),
        right=6,
    )  # fmt: skip
    for size in args.counts:
        run(size, args.restarts, not args.no_state)


if __name__ == "__main__":
    main()
