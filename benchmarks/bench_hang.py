"""Hang detection: healthy managers on a loaded machine are not hangs; a stopped one is.

Two measurements (issue 40, item 4):

* **load**: `--managers` process managers (default heartbeat: a ping every 0.25 s, hung
  after 0.75 s) start in order beside `--hogs` CPU-bound processes (a busy loop each),
  then keep running for `--hold` seconds. Two kinds of manager, in alternate rows:
  *idle* ones (one server, nothing else) and *busy* ones, which also run a CPU-bound
  thread of their own, as a manager that does perception work in its callbacks would
  (50 of them load 2 cores some 25 times over). Per run it counts the managers the
  heartbeat killed as hung (`ChildExited` reasons that start with "hung") and those it
  spared (the "could run for only" WARNING: a silence past the bound, mostly spent
  waiting for a CPU). Every manager here is healthy: nothing in them stops or blocks,
  they only wait for a CPU. Target: 0 killed in every run. The load average is the
  kernel's 1-minute figure at the end of the run (it lags: the hogs run a few seconds).
  Each kill's reason goes to stderr as it happens.
* **stop**: one process manager is stopped with `SIGSTOP` (a real hang: it can never
  answer) and the time from the signal until the supervisor has killed and restarted it,
  serving again, is measured (`wait_restarted`, then a call), on a quiet machine and
  beside the hogs. Target: within 3 s on the quiet machine. Its floor in the same run is
  the configured bound itself (`hang_after`, 0.75 s), below which no detector that waits
  for a missed answer can go.

Run: `python benchmarks/bench_hang.py [--runs 10] [--managers 50] [--hogs 4] [--hold 3]
[--stops 10] [--kinds idle busy]` (10-25 minutes with the defaults on 2 cores).
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import statistics
import sys
import threading
import time

import _harness

import rr_actors as rr
from rr_actors._process.manager import start_forkserver

TARGET_FALSE_KILLS = 0
TARGET_STOP_S = 3.0


def setup(registrar: rr.ResourceRegistrar) -> None:
    """An idle manager's setup: one server."""
    registrar.register_server("res", load=lambda r: r, unload=lambda r, s: None)


def spin() -> None:
    while True:
        pass


def busy_setup(registrar: rr.ResourceRegistrar) -> None:
    """A busy manager's setup: one server, and a thread that keeps computing."""
    setup(registrar)
    threading.Thread(target=spin, name="perception", daemon=True).start()


class Lines(logging.Handler):
    """Counts the heartbeat's log lines of this process (the supervisor's)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.spared = 0

    def emit(self, record: logging.LogRecord) -> None:
        if "could run for only" in record.getMessage():
            self.spared += 1


table = _harness.print_table


def load_run(
    managers: int, hog_count: int, hold: float, *, busy: bool
) -> tuple[float, float, list[str], int]:
    """One run: start `managers` beside `hog_count` hogs, hold; (start s, load, hung, spared)."""
    hung: list[str] = []
    lock = threading.Lock()

    def seen(event: object) -> None:
        if isinstance(event, rr.events.ChildExited) and event.reason.startswith("hung"):
            with lock:
                hung.append(event.child)
                print(f"  {event.child}: {event.reason}", file=sys.stderr)

    kind = busy_setup if busy else setup
    specs = [rr.ManagerSpec(f"m{n}", setup=kind, isolation="process") for n in range(managers)]
    # no give-up while counting: every false kill is restarted and counted
    sup = rr.Supervisor(specs, max_restarts=10_000, period=1.0)
    lines = Lines()
    log = logging.getLogger("rr_actors")
    log.addHandler(lines)
    try:
        with _harness.busy(hog_count), sup.subscribe(seen):
            started = time.monotonic()
            with sup:
                start_s = time.monotonic() - started
                time.sleep(hold)  # the heartbeat goes on under load (a benchmark, not a test)
            load = os.getloadavg()[0]
    finally:
        log.removeHandler(lines)
    return start_s, load, hung, lines.spared


def stop_run(hog_count: int) -> tuple[float, float]:
    """One `SIGSTOP` beside `hog_count` hogs: seconds from the signal to the manager
    serving again, and its `hang_after`."""
    spec = rr.ManagerSpec("stopped", setup=setup, isolation="process")
    with rr.Supervisor([spec]) as sup:
        app = sup.registrar("app")
        pid = sup.child("stopped").pid
        assert pid is not None
        with _harness.busy(hog_count):
            stopped = time.monotonic()
            os.kill(pid, signal.SIGSTOP)
            info = sup.wait_restarted("stopped", timeout=60.0)
            app.call("stopped", "res", 1, timeout=30.0)
            took = time.monotonic() - stopped
        assert info.last_exit is not None
        assert info.last_exit.startswith("hung"), info
    assert spec.hang_after is not None
    return took, spec.hang_after


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--managers", type=int, default=50)
    parser.add_argument("--hogs", type=int, default=4)
    parser.add_argument("--hold", type=float, default=3.0, help="seconds after the start")
    parser.add_argument("--stops", type=int, default=10)
    parser.add_argument("--kinds", nargs="+", choices=("idle", "busy"), default=["idle", "busy"])
    args = parser.parse_args()
    start_forkserver()
    print(f"{os.cpu_count()} CPUs, rr_actors {rr.__version__}, {rr.__file__}")

    rows = []
    total = {False: 0, True: 0}
    for run in range(1, args.runs + 1):
        for busy in (kind == "busy" for kind in args.kinds):
            start_s, load, hung, spared = load_run(args.managers, args.hogs, args.hold, busy=busy)
            total[busy] += len(hung)
            which = " ".join(hung[:8]) + (" ..." if len(hung) > 8 else "") or "-"
            kind = "busy" if busy else "idle"
            rows.append((run, kind, f"{start_s:.1f}", f"{load:.1f}", len(hung), spared, which))
    table(
        f"load: {args.managers} managers start beside {args.hogs} busy loops, then "
        f"{args.hold:g} s of heartbeats (target: {TARGET_FALSE_KILLS} killed as hung)",
        ("run", "managers", "start s", "load 1 min", "killed as hung", "spared", "which"),
        rows,
    )
    for busy in (kind == "busy" for kind in args.kinds):
        verdict = "met" if total[busy] == TARGET_FALSE_KILLS else "NOT met"
        print(
            f"healthy {'busy' if busy else 'idle'} managers killed as hung: {total[busy]} "
            f"in {args.runs} runs ({verdict})"
        )

    stops: list[tuple[str, str, str, str, str]] = []
    for hog_count in (0, args.hogs):
        took = []
        hang_after = 0.0
        for _ in range(args.stops):
            seconds, hang_after = stop_run(hog_count)
            took.append(seconds)
        if took:
            quiet = hog_count == 0
            stops.append(
                (
                    "quiet machine" if quiet else f"beside {hog_count} busy loops",
                    f"{statistics.median(took):.3f}",
                    f"{max(took):.3f}",
                    f"{hang_after:.3f}",
                    ("yes" if max(took) <= TARGET_STOP_S else "NO") if quiet else "(no target)",
                )
            )
    if stops:
        table(
            f"stop: SIGSTOP to killed, restarted and serving, {args.stops} stops each "
            f"(target: {TARGET_STOP_S:g} s on a quiet machine)",
            ("row", "median s", "max s", "floor: hang_after s", "met"),
            stops,
        )


if __name__ == "__main__":
    main()
