"""Supervisor benchmark: SIGKILL -> detected -> respawned, restored and serving.

For each catalog size, a manager process whose backup holds that many served resources
is SIGKILLed repeatedly. Per crash it measures

* detected: from `os.kill(pid, SIGKILL)` until the supervisor handles the exit (the
  watcher thread blocked on the process's exit wakes; no polling), taken from the
  supervisor's `ChildExited` event (its `at`, wall clock);
* restart: the supervisor's own figure, `ChildRestarted.restart_s` (from the exit seen to
  the new incarnation serving);
* serving: from the kill until a call answered by the new incarnation returned, i.e.
  respawned (forkserver), catalog restored from SQLite, setup run, served and a round trip.

Targets (issue 4): detected <= 5 ms; serving <= 30 ms at 1k entries, <= 250 ms at 100k.

The floor of "detected", in the same run: a bare forkserver process holding a dict of as
many entries (36-character keys, like consumer ids) is SIGKILLed and its sentinel waited
on. The kernel frees a process's memory before its parent can see it exit, so this floor
grows with what the process holds.

Crashes are spaced `--gap` seconds apart (default 0.2) so that each one meets a settled
system: the supervisor's spare manager processes, topped up once restarts have been quiet
for 0.1 s, have warmed up. `--gap 0` kills the manager right after each restart (a
crash loop): the restart takes the second spare, and no spare's warm-up competes with it.
Target (issue 16): serving with `--gap 0` within 2x of the spaced figure.

`--forkserver-first` runs a `multiprocessing` forkserver Process of the program's own
before anything of rr_actors, as a program that used a `forkserver` pool or Process
before its `Supervisor` did (CPython's forkserver started without rr_actors' preload).
Target (issue 34 item 6): the same serving times with and without it (the figures of
either come from separate runs, alternated: which forkserver runs is per program).

`--subscriber` compares kill to serving with and without a subscriber (issue 52 part 5),
round robin in one run: a fork floor (a bare child of this process SIGKILLed, its exit
waited on, a new one forked and its first byte read from a pipe), then the manager
killed with nobody subscribed (its events are not built), then with a subscriber that
takes every event. Targets: with a subscriber within 1.3x without, and within 2x the
fork floor (medians; the 10th percentiles are printed too: under load, the nearer to a
quiet machine's figures).

`--subscriber --interleaved` runs both trees at once and kills them in turn with the
floor (a triple per round): a load that comes and goes meets the three alike; it prints
the median of each triple's ratios. (A shared machine's figures: the two trees' spares
and restarts take turns on the CPU with each other too.)

Run: `python benchmarks/bench_supervisor.py [--sizes 1000 100000] [--crashes 10] [--gap 0.2]
[--forkserver-first] [--subscriber [--rounds 5 | --interleaved]]`
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing
import multiprocessing.connection
import os
import queue
import signal
import tempfile
import time
import uuid
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import _harness

import rr_actors as rr
from rr_actors._catalog import Changes, Resource, ResourceState
from rr_actors._process.manager import start_forkserver
from rr_actors._store.saver import SqliteStore

median = _harness.median
TARGET_DETECT_MS = 5.0
TARGET_SERVE_MS = {1_000: 30.0, 100_000: 250.0}


def setup(registrar: rr.ResourceRegistrar) -> None:
    """The manager's setup: one server; the catalog was restored before this runs."""
    registrar.register_server("res", load=lambda r: r, unload=lambda r, s: None)


def fill_backup(path: Path, entries: int) -> None:
    """Write `entries` loaded resources (one consumer each) straight into a backup."""
    store = SqliteStore.open(path)
    resources: dict[str, Resource | None] = {}
    for n in range(entries):
        rid = str(uuid.uuid4())
        resources[rid] = Resource(
            id=rid,
            server="res",
            request={"n": n},
            response={"pid": n, "start_time": n},
            state=ResourceState.LOADED,
            consumers={str(uuid.uuid4()): "app"},
        )
    store.write(Changes(resources, {}))
    store.close(erase=False)


class ChildEvents:
    """The supervisor's events about one child: exits and restarts, as they are published."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.exits: queue.SimpleQueue[rr.events.ChildExited] = queue.SimpleQueue()
        self.restarts: queue.SimpleQueue[rr.events.ChildRestarted] = queue.SimpleQueue()

    def __call__(self, event: rr.events.Event) -> None:
        if isinstance(event, rr.events.ChildExited) and event.child == self.name:
            self.exits.put(event)
        elif isinstance(event, rr.events.ChildRestarted) and event.child == self.name:
            self.restarts.put(event)


def measure(entries: int, crashes: int, gap: float) -> tuple[list[float], ...]:
    """Kill the manager `crashes` times; detect, restart and serving times in ms."""
    tag = uuid.uuid4().hex[:6]
    name, app_name = f"bench-{tag}", f"app-{tag}"
    heard = ChildEvents(name)
    detect: list[float] = []
    restart: list[float] = []
    serve: list[float] = []
    with tempfile.TemporaryDirectory() as state_dir:
        fill_backup(Path(state_dir) / f"{name}.db", entries)
        spec = rr.ManagerSpec(name, setup, isolation="process", start_timeout=120.0)
        sup = rr.Supervisor([spec], max_restarts=crashes + 1, period=3600.0, state_dir=state_dir)
        with sup.subscribe(heard), sup:
            app = sup.registrar(app_name)
            app.call(name, "res", "warm-up", timeout=60.0)
            for n in range(crashes):
                time.sleep(gap)  # let the previous restart settle (spare process warmed up)
                pid = sup.child(name).pid
                assert pid is not None
                killed_at = time.time()  # (events carry wall-clock times)
                killed = time.perf_counter()
                os.kill(pid, signal.SIGKILL)
                sup.wait_restarted(name, timeout=120.0)
                app.call(name, "res", f"after-{n}", timeout=60.0)
                done = time.perf_counter()
                detect.append((heard.exits.get(timeout=10).at - killed_at) * 1000)
                restart.append(heard.restarts.get(timeout=10).restart_s * 1000)
                serve.append((done - killed) * 1000)
    return detect, restart, serve


class Restarting:
    """One tree whose one manager process (its backup holding `entries` served resources)
    is killed at will, with a subscriber that takes every event of the tree or with nobody
    subscribed; a context manager (the tree runs inside it)."""

    def __init__(self, entries: int, crashes: int, *, subscribed: bool) -> None:
        tag = uuid.uuid4().hex[:6]
        self.name, self.app_name = f"bench-{tag}", f"app-{tag}"
        self.entries, self.crashes, self.subscribed = entries, crashes, subscribed
        self.heard: list[rr.events.Event] = []
        self.kills = 0
        self._stack = contextlib.ExitStack()

    def __enter__(self) -> Restarting:
        stack = self._stack
        state_dir = stack.enter_context(tempfile.TemporaryDirectory())
        fill_backup(Path(state_dir) / f"{self.name}.db", self.entries)
        spec = rr.ManagerSpec(self.name, setup, isolation="process", start_timeout=120.0)
        sup = rr.Supervisor(
            [spec], max_restarts=self.crashes + 1, period=3600.0, state_dir=state_dir
        )
        self.sup = sup
        if self.subscribed:  # (closed after the tree stopped: its last events too)
            stack.enter_context(sup.subscribe(self.heard.append))
        stack.enter_context(sup)
        self.app = sup.registrar(self.app_name)
        self.app.call(self.name, "res", "warm-up", timeout=60.0)
        return self

    def __exit__(self, *exc: object) -> None:
        self._stack.close()
        if self.subscribed and exc[0] is None:
            assert any(isinstance(e, rr.events.CatalogRestored) for e in self.heard), (
                "no CatalogRestored"
            )

    def kill_to_serving(self) -> float:
        """SIGKILL the manager; milliseconds until a call its new incarnation answered
        returned."""
        pid = self.sup.child(self.name).pid
        assert pid is not None
        killed = time.perf_counter()
        os.kill(pid, signal.SIGKILL)
        self.sup.wait_restarted(self.name, timeout=120.0)
        self.app.call(self.name, "res", f"after-{self.kills}", timeout=60.0)
        self.kills += 1
        return (time.perf_counter() - killed) * 1000


def measure_serving(entries: int, crashes: int, gap: float, *, subscribed: bool) -> list[float]:
    """Milliseconds from each SIGKILL until a call the new incarnation answered returned,
    with a subscriber that takes every event of the tree, or with nobody subscribed."""
    serve: list[float] = []
    with Restarting(entries, crashes, subscribed=subscribed) as tree:
        for _ in range(crashes):
            time.sleep(gap)  # let the previous restart settle (spare warmed up)
            serve.append(tree.kill_to_serving())
    return serve


def _forked() -> tuple[int, int]:
    """Fork a bare child that writes one byte to a pipe, then idles until killed; the
    child's pid and the pipe's read end, once the byte came."""
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: say so, then wait to be killed
        try:
            os.write(write_end, b"r")
            while True:
                signal.pause()
        finally:
            os._exit(0)
    os.close(write_end)
    os.read(read_end, 1)
    return pid, read_end


def fork_floor(kills: int, gap: float) -> list[float]:
    """Milliseconds from the SIGKILL of a bare forked process to a round trip with a new
    one: its exit waited on (`waitpid`), a new process forked (`os.fork` of this one) and
    its first byte read. What a restart costs with nothing to restore, set up or serve."""
    times: list[float] = []
    pid, read_end = _forked()
    for _ in range(kills):
        time.sleep(gap)
        killed = time.perf_counter()
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        os.close(read_end)
        pid, read_end = _forked()
        times.append((time.perf_counter() - killed) * 1000)
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    os.close(read_end)
    return times


def compare_subscriber(entries: int, crashes: int, gap: float, rounds: int) -> None:
    """Round robin: fork floor, serving without a subscriber, serving with one."""
    samples: dict[str, list[float]] = {row: [] for row in ROWS}
    for n in range(rounds):
        samples["fork floor"] += fork_floor(crashes, gap)
        samples["no subscriber"] += measure_serving(entries, crashes, gap, subscribed=False)
        samples["subscriber"] += measure_serving(entries, crashes, gap, subscribed=True)
        so_far = ", ".join(f"{row} {median(v):.1f}" for row, v in samples.items())
        print(f"round {n + 1}: medians so far (ms): {so_far}", flush=True)
    summary(f"at {entries} entries, {rounds} rounds of {crashes} kills", samples)
    floor, without, heard = (samples[row] for row in ROWS)
    print(  # (under load the lower tail is the nearer to a quiet machine's figure)
        f"p10s: subscriber / none: {p10(heard) / p10(without):.2f}x; subscriber / fork floor: "
        f"{p10(heard) / p10(floor):.2f}x; none / fork floor: {p10(without) / p10(floor):.2f}x"
    )


def compare_interleaved(entries: int, crashes: int, gap: float) -> None:
    """Both trees run at once, killed in turn (fork floor, no subscriber, subscriber), so
    that a load that comes and goes meets the three alike; the ratios of each triple."""
    samples: dict[str, list[float]] = {row: [] for row in ROWS}
    pid, read_end = _forked()
    with (
        Restarting(entries, crashes, subscribed=False) as plain,
        Restarting(entries, crashes, subscribed=True) as heard,
    ):
        for _ in range(crashes):
            time.sleep(gap)
            killed = time.perf_counter()
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            os.close(read_end)
            pid, read_end = _forked()
            samples["fork floor"].append((time.perf_counter() - killed) * 1000)
            time.sleep(gap)
            samples["no subscriber"].append(plain.kill_to_serving())
            time.sleep(gap)
            samples["subscriber"].append(heard.kill_to_serving())
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    os.close(read_end)
    summary(f"at {entries} entries, {crashes} interleaved triples", samples, paired=True)


ROWS = ("fork floor", "no subscriber", "subscriber")


def summary(what: str, samples: dict[str, list[float]], *, paired: bool = False) -> None:
    """The three rows' median, p10 and p90, then the ratios against the targets: of the
    medians, or (`paired`: the samples are triples taken in turn) the median of each
    triple's ratios."""
    _harness.print_table(
        f"kill to serving {what}, ms",
        ("", "median", "p10", "p90"),
        [(row, *(f"{f(v):.1f}" for f in (median, p10, p90))) for row, v in samples.items()],
    )
    floor, without, heard = (samples[row] for row in ROWS)

    def ratio(a: list[float], b: list[float]) -> float:
        return (
            median([x / y for x, y in zip(a, b, strict=True)]) if paired else median(a) / median(b)
        )

    said = "median of the triples' ratios" if paired else "medians"
    print(
        f"{said}: subscriber / none {ratio(heard, without):.2f}x (target <= 1.3x), "
        f"subscriber / fork floor {ratio(heard, floor):.2f}x (target <= 2x), "
        f"none / fork floor {ratio(without, floor):.2f}x"
    )


def _hold(entries: int, ready: Connection) -> None:
    """A bare child process: hold `entries` dict entries, say so, then idle until killed."""
    held = {f"{n:036d}": str(n) for n in range(entries)}
    ready.send(len(held))
    ready.recv()  # never answered: the parent kills this process


def teardown_floor(entries: int, kills: int) -> list[float]:
    """Milliseconds from SIGKILL to the sentinel of a bare process holding `entries`."""
    context = multiprocessing.get_context("forkserver")
    times = []
    for _ in range(kills):
        ours, theirs = context.Pipe()
        process = context.Process(target=_hold, args=(entries, theirs), daemon=True)
        process.start()
        ours.recv()
        killed = time.perf_counter()
        os.kill(process.pid or 0, signal.SIGKILL)
        multiprocessing.connection.wait([process.sentinel])
        times.append((time.perf_counter() - killed) * 1000)
        process.join()
        ours.close()
        theirs.close()
    return times


def use_forkserver_first() -> None:
    """Start and join one `forkserver` Process, as the program's own, before rr_actors.

    This starts CPython's forkserver (its preload list empty): what a program that made a
    `forkserver` pool or Process before its `Supervisor` had running.
    """
    process = multiprocessing.get_context("forkserver").Process(target=int, daemon=True)
    process.start()
    process.join(60)


def p90(values: list[float]) -> float:
    return _harness.percentile(values, 0.9)


def p10(values: list[float]) -> float:
    return _harness.percentile(values, 0.1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1_000, 100_000])
    parser.add_argument("--crashes", type=int, default=10)
    parser.add_argument(
        "--gap", type=float, default=0.2, help="seconds between a restart and the next kill"
    )
    parser.add_argument(
        "--forkserver-first",
        action="store_true",
        help="run a multiprocessing forkserver Process before rr_actors starts its own",
    )
    parser.add_argument(
        "--subscriber",
        action="store_true",
        help="compare kill to serving with and without a subscriber, and a fork floor",
    )
    parser.add_argument("--rounds", type=int, default=5, help="round robin rounds (--subscriber)")
    parser.add_argument(
        "--interleaved",
        action="store_true",
        help="with --subscriber: both trees at once, killed in turn with the floor",
    )
    args = parser.parse_args()
    print(_harness.header(f"{_harness.commit()}; kill to serving"))
    if args.forkserver_first:
        use_forkserver_first()
    start_forkserver()
    if args.subscriber:
        for entries in args.sizes:
            if args.interleaved:
                compare_interleaved(entries, args.crashes, args.gap)
            else:
                compare_subscriber(entries, args.crashes, args.gap, args.rounds)
        return
    rows: list[tuple[Any, ...]] = []
    served: dict[int, list[float]] = {}
    for entries in args.sizes:
        detect, restart, serve = measure(entries, args.crashes, args.gap)
        served[entries] = serve
        floor = teardown_floor(entries, args.crashes)
        target = TARGET_SERVE_MS.get(entries)
        rows.append(
            (
                entries,
                *(f"{x:.2f}" for x in (median(detect), p90(detect), median(floor))),
                *(f"{x:.1f}" for x in (median(restart), median(serve), p90(serve))),
                "-" if target is None else f"<= {target:g}",
            )
        )
    _harness.print_table(
        f"SIGKILL -> detected -> respawned, restored and serving ({args.crashes} crashes each), ms",
        (
            "entries", "detect med", "detect p90", "floor med", "restart med",
            "serve med", "serve p90", "serve target",
        ),
        rows,
    )  # fmt: skip
    print("floor: SIGKILL -> sentinel of a bare process holding as many dict entries")
    print("detect: from the kill to the ChildExited event; restart: ChildRestarted.restart_s")
    print(f"detect target: <= {TARGET_DETECT_MS:g} ms")
    first = "the program's, then rr_actors'" if args.forkserver_first else "rr_actors' only"
    for entries, serve in served.items():
        each = ", ".join(f"{ms:.1f}" for ms in serve)
        print(f"serving at {entries} (forkserver: {first}), each kill in ms: {each}")


if __name__ == "__main__":
    main()
