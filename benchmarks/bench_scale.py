"""Scale benchmark: how costs grow with the number of process managers, beside their floor.

Section "start": a `Supervisor` of N process managers is started (`start()` returns once
every one serves, in order: OTP's ordered start) and stopped; beside it, in the same run
and alternated with it round by round, its floor: N plain `multiprocessing` children
started the same way, one after the other, each telling its parent "ready" over a pipe
before the next is started (the forkserver context, as rr_actors uses; its forkserver is
started before the clock runs, as the supervisor's is). Also the memory of one process
manager (PSS, from `/proc/<pid>/smaps_rollup`, Linux) beside a plain child's.

Target (issue 34 item 1): 50 process managers start within 3x the time of the floor.

Section "fresh": the same start, a tree of N process managers on a fresh `state_dir`
(each makes its backup: issue 69 goal 2) beside the same tree without one, and the plain
children, alternated round by round; per manager, ms to start and its `setup()`'s ms
(timed inside it: one `register_server`). Target: with a fresh `state_dir` within 2x
without, for the start and for `setup()`. `--durability power` makes them with "power".

Section "serve": kill to serving with N catalog entries. A manager process whose backup
holds N served resources (one consumer id each) is SIGKILLed; the time runs from the kill
until a call answered by its new incarnation returned (`bench_supervisor.measure`:
respawned, restored, setup run, serving, one call), with the supervisor subscribed (as
an experiment is: the restored registrar publishes `CatalogRestored`). Beside it, in
the same run and alternated round by round, its floor: a plain forkserver child (of a
Python of its own, importing nothing) SIGKILLed, its exit waited on and a new one
started until it says "ready".
Target (issue 34 item 3): at 100k entries within 2x of the figure at 1k.

Section "status": `send_status` to N consumers, each a registrar of its own holding one
id of the resource with a status callback; `send_status` returns once every callback
ran. "other processes": the provider is a registrar in a process of its own, the N
consumers are registrars of this process (the call is timed in the provider's process);
its floor, in the same run and alternated round by round, is a Pipe burst to N: N small
objects (`(id, status, message)`) sent over one `multiprocessing.Pipe` to another
process, each echoed back, until the N answers are read. "one process": the provider
and the N consumers in this process; its floor a pykka fan-out to N: N `ask`s to N pykka
actors (each answers at once), until the N answers are read.
Targets (issue 34 item 2): to 100 consumers in other processes within 5x the Pipe
burst; in one process within 1.5x the pykka fan-out.

Run: `python benchmarks/bench_scale.py [--sections start fresh serve status] [--counts 1 10 50]
[--durability process|power]
[--sizes 1000 10000 100000] [--consumers 1 10 100] [--rounds 5] [--kills 5]
[--sends 50] [--pin]`
(`--pin`: under `taskset -c 0`, one CPU, as `benchmarks/alternate.py --pin` runs).
"""

from __future__ import annotations

import argparse
import contextlib
import inspect
import multiprocessing
import multiprocessing.connection
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import _harness
import pykka

import rr_actors as rr
from rr_actors.testing import System, start_forkserver


def setup(registrar: rr.ResourceRegistrar) -> None:
    """Each manager's setup: one server (what a small experiment's manager has)."""
    registrar.register_server("res", load=lambda r: r, unload=lambda r, s: None)


FLOOR = """
import multiprocessing, os, sys, time
from multiprocessing import forkserver
context = multiprocessing.get_context("forkserver")
context.set_forkserver_preload([])
forkserver.ensure_running()
CHILD = "import os\\nready.send(os.getpid())\\n"
CHILD += "try:\\n    ready.recv()\\nexcept EOFError:\\n    pass"
for line in sys.stdin:
    children = []
    began = time.perf_counter()
    for _ in range(int(line)):
        ours, theirs = context.Pipe()
        names = {"ready": theirs}
        process = context.Process(target=exec, args=(CHILD, names), daemon=True)
        process.start()
        theirs.close()
        ours.recv()
        children.append((process, ours))
    elapsed = (time.perf_counter() - began) * 1000
    pss = open(f"/proc/{children[-1][0].pid}/smaps_rollup").read().split("Pss:")[1].split()[0]
    began = time.perf_counter()
    for process, ours in reversed(children):
        ours.close()
        process.join(10)
    stopped = (time.perf_counter() - began) * 1000
    print(elapsed, pss, stopped, flush=True)
"""
"""The floor, run by a Python of its own (`python -c`): its children have no main module
to re-import and import nothing of rr_actors or of this script. Each line it reads is a
count N; it starts N children in order (each runs `exec` of a few lines: say "ready",
then wait for EOF), stops them in reverse order (each told by EOF and its exit waited on
before the next), and prints the milliseconds to start, the last child's PSS (KiB) and the
milliseconds to stop."""


class Floor:
    """The floor's process: `start(n)` times n plain children there."""

    def __init__(self) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-c", FLOOR], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )

    def start(self, count: int) -> tuple[float, int | None, float]:
        """ms to start `count` children in order, a child's PSS, ms to stop them."""
        assert self.process.stdin is not None
        assert self.process.stdout is not None
        self.process.stdin.write(f"{count}\n")
        self.process.stdin.flush()
        elapsed, pss, stopped = self.process.stdout.readline().split()
        return float(elapsed), int(pss), float(stopped)

    def close(self) -> None:
        assert self.process.stdin is not None
        self.process.stdin.close()
        self.process.wait(30)


def pss_kib(pid: int) -> int | None:
    return _harness.memory_kib(pid, "Pss")


def start_managers(
    count: int, *, isolation: str = "process", state_dir: bool = False, parallel: bool = False
) -> tuple[float, int | None, float]:
    """Start and stop a supervisor of `count` managers; ms to start, a PSS, ms to stop
    (`parallel`: `stop(parallel=True)`; `state_dir`: the catalogs kept in a fresh one)."""
    specs = [rr.ManagerSpec(f"m{n}", setup, isolation=isolation) for n in range(count)]  # type: ignore[arg-type]
    with tempfile.TemporaryDirectory() as folder:
        supervisor = rr.Supervisor(
            specs, name=f"scale-{count}", state_dir=folder if state_dir else None
        )
        began = time.perf_counter()
        supervisor.start()
        elapsed = (time.perf_counter() - began) * 1000
        pid = supervisor.child(f"m{count - 1}").pid
        memory = pss_kib(pid) if pid is not None else None
        began = time.perf_counter()
        if parallel:
            supervisor.stop(parallel=True)
        else:
            supervisor.stop()
        stopped = (time.perf_counter() - began) * 1000
    return elapsed, memory, stopped


def spread(values: list[float]) -> str:
    return f"{min(values):.0f}-{max(values):.0f}"


def row(name: str, ours: list[float], plain: list[float]) -> str:
    ratio = statistics.median(ours) / statistics.median(plain)
    return (
        f"| {name} | {statistics.median(ours):.0f} | {spread(ours)} "
        f"| {statistics.median(plain):.0f} | {spread(plain)} | {ratio:.1f}x |"
    )


def section_start(
    counts: list[int], rounds: int, *, isolation: str, state_dir: bool, parallel: bool = True
) -> None:
    start_forkserver()  # rr_actors' forkserver (preloaded), before the clocks run
    floor = Floor()
    start_managers(1, isolation=isolation)  # warm both sides (imports, first forks)
    floor.start(1)
    kept = " (catalogs in a state_dir)" if state_dir else ""
    print(f"## start, stop: N {isolation} managers{kept} vs N plain forkserver children (ms)")
    print()
    print("| N | rr_actors med | rr_actors min-max | floor med | floor min-max | ratio |")
    print("|---|---|---|---|---|---|")
    memory: dict[str, int | None] = {}
    for count in counts:
        figures: dict[str, list[float]] = {
            k: [] for k in ("start", "stop", "stop parallel", "floor", "floor stop")
        }
        for _ in range(rounds):  # alternated: all meet the same noise
            began, memory["rr_actors"], stopped = start_managers(
                count, isolation=isolation, state_dir=state_dir
            )
            figures["start"].append(began)
            figures["stop"].append(stopped)
            if parallel:
                began, _, stopped = start_managers(
                    count, isolation=isolation, state_dir=state_dir, parallel=True
                )
                figures["start"].append(began)
                figures["stop parallel"].append(stopped)
            began, memory["plain"], stopped = floor.start(count)
            figures["floor"].append(began)
            figures["floor stop"].append(stopped)
        print(row(f"start {count}", figures["start"], figures["floor"]))
        print(row(f"stop {count}", figures["stop"], figures["floor stop"]))
        if parallel:
            print(row(f"stop {count} parallel", figures["stop parallel"], figures["floor stop"]))
    floor.close()
    print()
    mine, theirs = memory.get("rr_actors"), memory.get("plain")
    if mine is not None and theirs is not None:
        print(
            f"memory (PSS) of one process manager: {mine / 1024:.1f} MiB; "
            f"of one plain child: {theirs / 1024:.1f} MiB"
        )
    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


def timed_setup(log: str) -> Callable[[rr.ResourceRegistrar], None]:
    """`setup`, its milliseconds appended to the file `log` (run in the manager's process)."""

    def setup_timed(registrar: rr.ResourceRegistrar) -> None:
        began = time.perf_counter()
        setup(registrar)
        with open(log, "a") as out:
            out.write(f"{(time.perf_counter() - began) * 1000}\n")

    return setup_timed


def start_fresh(count: int, *, state: bool, durability: str) -> tuple[float, float]:
    """Start (and stop) `count` process managers, on a fresh `state_dir` or none: ms per
    manager to start, and the median ms of their `setup()`."""
    with tempfile.TemporaryDirectory() as work:
        log = os.path.join(work, "setup.log")
        specs = [
            rr.ManagerSpec(f"m{n}", timed_setup(log), isolation="process") for n in range(count)
        ]
        state_dir = os.path.join(work, "state") if state else None
        if state_dir is not None:
            os.mkdir(state_dir)
        supervisor = rr.Supervisor(
            specs,
            name=f"fresh-{count}",
            state_dir=state_dir,
            durability=durability,  # type: ignore[arg-type]
        )
        began = time.perf_counter()
        supervisor.start()
        elapsed = (time.perf_counter() - began) * 1000
        supervisor.stop()
        setups = [float(line) for line in Path(log).read_text().split()]
    return elapsed / count, statistics.median(setups)


def section_fresh(counts: list[int], rounds: int, durability: str) -> None:
    start_forkserver()
    floor = Floor()
    start_fresh(1, state=True, durability=durability)  # (warm: imports, first forks)
    floor.start(1)
    print(f"## fresh: N process managers on a fresh state_dir ({durability}) vs none (ms)")
    print()
    print(
        "| N | start/manager, fresh state_dir | without | ratio | setup(), fresh state_dir "
        "| without | ratio | floor/child |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for count in counts:
        fresh: list[tuple[float, float]] = []
        bare: list[tuple[float, float]] = []
        plain: list[float] = []
        for _ in range(rounds):  # alternated: all three meet the same noise
            fresh.append(start_fresh(count, state=True, durability=durability))
            bare.append(start_fresh(count, state=False, durability=durability))
            plain.append(floor.start(count)[0] / count)
        starts = [statistics.median(x[0] for x in runs) for runs in (fresh, bare)]
        setups = [statistics.median(x[1] for x in runs) for runs in (fresh, bare)]
        print(
            f"| {count} | {starts[0]:.0f} | {starts[1]:.0f} | {starts[0] / starts[1]:.2f}x "
            f"| {setups[0]:.2f} | {setups[1]:.2f} | {setups[0] / setups[1]:.2f}x "
            f"| {statistics.median(plain):.0f} |"
        )
    floor.close()
    print()
    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


RESPAWN = """
import multiprocessing, os, signal, sys, time
from multiprocessing import forkserver
context = multiprocessing.get_context("forkserver")
context.set_forkserver_preload([])
forkserver.ensure_running()
CHILD = "import os\\nready.send(os.getpid())\\n"
CHILD += "try:\\n    ready.recv()\\nexcept EOFError:\\n    pass"
def spawn():
    ours, theirs = context.Pipe()
    process = context.Process(target=exec, args=(CHILD, {"ready": theirs}), daemon=True)
    process.start()
    theirs.close()
    ours.recv()
    return process, ours
process, ours = spawn()
for line in sys.stdin:
    times = []
    for _ in range(int(line)):
        began = time.perf_counter()
        os.kill(process.pid, signal.SIGKILL)
        process.join()
        ours.close()
        process, ours = spawn()
        times.append((time.perf_counter() - began) * 1000)
    print(*times, flush=True)
os.kill(process.pid, signal.SIGKILL)
process.join()
"""
"""The respawn floor, run by a Python of its own (as `FLOOR`): it keeps one plain child;
each line it reads is a count k: k times it SIGKILLs the child, waits for its exit and
starts a new one until it says "ready", and prints the k times in ms."""


class Respawn:
    """The respawn floor's process: `kill(k)` times k respawns of a plain child."""

    def __init__(self) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-c", RESPAWN],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )

    def kill(self, count: int) -> list[float]:
        assert self.process.stdin is not None
        assert self.process.stdout is not None
        self.process.stdin.write(f"{count}\n")
        self.process.stdin.flush()
        return [float(ms) for ms in self.process.stdout.readline().split()]

    def close(self) -> None:
        assert self.process.stdin is not None
        self.process.stdin.close()
        self.process.wait(30)


class Served:
    """A supervisor of one manager process whose backup holds `size` entries."""

    def __init__(self, size: int, *, listen: bool) -> None:
        from bench_supervisor import fill_backup  # noqa: PLC0415 - a sibling script

        self.state = tempfile.TemporaryDirectory()
        self.name = f"serve{size}"
        fill_backup(Path(self.state.name) / f"{self.name}.db", size)
        spec = rr.ManagerSpec(self.name, setup, isolation="process", start_timeout=120.0)
        self.supervisor = rr.Supervisor(
            [spec], max_restarts=10_000, period=3600.0, state_dir=self.state.name
        )
        self.listening = self.supervisor.subscribe(lambda _event: None) if listen else None
        self.supervisor.start()
        self.app = self.supervisor.registrar(f"app{size}")
        self.app.call(self.name, "res", "warm-up", timeout=120.0)
        self.calls = 0

    def kill(self) -> float:
        """SIGKILL the manager; ms until a call answered by its next incarnation returned."""
        time.sleep(0.2)  # the last restart settled (its spare process warmed up)
        pid = self.supervisor.child(self.name).pid
        assert pid is not None
        killed = time.perf_counter()
        os.kill(pid, signal.SIGKILL)
        self.supervisor.wait_restarted(self.name, timeout=120.0)
        self.calls += 1
        self.app.call(self.name, "res", f"after-{self.calls}", timeout=120.0)
        return (time.perf_counter() - killed) * 1000

    def close(self) -> None:
        self.supervisor.stop()
        if self.listening is not None:
            self.listening.close()
        self.state.cleanup()


def section_serve(sizes: list[int], rounds: int, kills: int, *, listen: bool) -> None:
    start_forkserver()
    floor = Respawn()
    floor.kill(1)  # warm its forkserver's first fork
    served = [Served(size, listen=listen) for size in sizes]
    heard = "subscribed (events on)" if listen else "nobody subscribed"
    print(f"## serve: kill to serving with N catalog entries (ms; {heard})")
    print()
    print("| N | rr_actors med | rr_actors min-max | floor med | floor min-max | to 1k |")
    print("|---|---|---|---|---|---|")
    ours: dict[int, list[float]] = {size: [] for size in sizes}
    plain: dict[int, list[float]] = {size: [] for size in sizes}
    for _ in range(rounds):  # alternated: every size and the floor meet the same noise
        for tree in served:
            size = int(tree.name.removeprefix("serve"))
            ours[size].extend(tree.kill() for _ in range(kills))
            plain[size].extend(floor.kill(kills))
    for tree in served:
        tree.close()
    floor.close()
    base = statistics.median(ours[sizes[0]])
    for size in sizes:
        median = statistics.median(ours[size])
        print(
            f"| serve {size} | {median:.1f} | {spread(ours[size])} "
            f"| {statistics.median(plain[size]):.1f} | {spread(plain[size])} "
            f"| {median / base:.2f}x |"
        )
    print()
    print(f"(to 1k: the median over that of N = {sizes[0]})")
    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


NOTICE = ("0f3b7b2c-1111-2222-3333-444455556666", 2, "tick")
"""What the Pipe burst sends per consumer: about what a status notice says."""


def _echo(conn: multiprocessing.connection.Connection) -> None:
    """The Pipe burst's other end: echo every object until the pipe closes."""
    with contextlib.suppress(EOFError, OSError):
        while True:
            conn.send(conn.recv())


class PipeBurst:
    """The floor across processes: `burst(n)` sends n objects to a child, reads n echoes."""

    def __init__(self) -> None:
        context = multiprocessing.get_context("forkserver")
        self.conn, theirs = context.Pipe()
        self.process = context.Process(target=_echo, args=(theirs,), daemon=True)
        self.process.start()
        theirs.close()

    def burst(self, count: int) -> float:
        """Seconds to send `count` objects and read their `count` echoes."""
        began = time.perf_counter()
        for _ in range(count):
            self.conn.send(NOTICE)
        for _ in range(count):
            self.conn.recv()
        return time.perf_counter() - began

    def close(self) -> None:
        self.conn.close()
        self.process.join(10)


class _Answer(pykka.ThreadingActor):
    def on_receive(self, message: Any) -> None:
        return None


class PykkaFanOut:
    """The floor in one process: `fan_out()` asks each of `count` pykka actors, waits all."""

    def __init__(self, count: int) -> None:
        self.refs = [_Answer.start() for _ in range(count)]

    def fan_out(self) -> float:
        """Seconds to ask every actor and read every answer."""
        began = time.perf_counter()
        futures = [ref.ask(NOTICE, block=False) for ref in self.refs]
        for future in futures:
            future.get(timeout=60)
        return time.perf_counter() - began

    def close(self) -> None:
        for ref in self.refs:
            ref.stop()


def setup_echo(registrar: rr.ResourceRegistrar) -> None:
    """The provider's one server."""
    registrar.register_server("echo", load=lambda r: r, unload=lambda r, s: None)


def status_sends(request: Any, sends: int) -> Callable[[rr.ResourceRegistrar], list[float]]:
    """A function to run in the provider: `sends` timed `send_status` to `request`'s
    consumers (after 5 untimed), in seconds each."""

    def measure(registrar: rr.ResourceRegistrar) -> list[float]:
        (query_id,) = [q.id for q in registrar.server_queries("echo") if q.request == request][:1]
        samples = []
        for number in range(sends + 5):
            began = time.perf_counter()
            registrar.send_status(query_id, rr.Status.UPDATE, "tick", timeout=60)
            if number >= 5:
                samples.append(time.perf_counter() - began)
        return samples

    return measure


class Consumers:
    """`count` consumer registrars of this process, each holding one id of `request` at
    `provider` with a callback that counts what it heard."""

    def __init__(self, provider: str, request: Any, count: int, network: Any | None = None) -> None:
        suffix = uuid.uuid4().hex[:6]
        self.heard: list[int] = []
        self.registrars = [
            rr.ResourceRegistrar.start(f"c{count}-{n}-{suffix}", network=network)
            for n in range(count)
        ]
        for registrar in self.registrars:
            registrar.call(provider, "echo", request, on_status=lambda _q, _u: self.heard.append(1))

    def close(self) -> None:
        for registrar in self.registrars:
            registrar.stop()


def status_row(name: str, ours: list[float], floor: list[float]) -> str:
    ms = [x * 1000 for x in ours]
    plain = [x * 1000 for x in floor]
    ratio = statistics.median(ms) / statistics.median(plain)
    return (
        f"| {name} | {statistics.median(ms):.2f} | {min(ms):.2f}-{max(ms):.2f} "
        f"| {statistics.median(plain):.3f} | {min(plain):.3f}-{max(plain):.3f} | {ratio:.1f}x |"
    )


def section_status(counts: list[int], rounds: int, sends: int) -> None:
    from bench_transport import registrar_process  # noqa: PLC0415 - a sibling script

    context = multiprocessing.get_context("forkserver")
    system = System.create()
    provider = f"provider-{uuid.uuid4().hex[:6]}"
    print("## status: send_status to N consumer registrars vs its floor (ms per send)")
    print()
    print("| N | rr_actors med | rr_actors min-max | floor med | floor min-max | ratio |")
    print("|---|---|---|---|---|---|")
    try:
        with registrar_process(context, system.address, provider, setup_echo):
            burst = PipeBurst()
            for count in counts:
                request = {"other": count}
                consumers = Consumers(provider, request, count, network=system)
                ours: list[float] = []
                plain: list[float] = []
                for _ in range(rounds):  # alternated: both meet the same noise
                    ours.extend(system.run(provider, status_sends(request, sends), timeout=600))
                    burst.burst(count)
                    plain.extend(burst.burst(count) for _ in range(sends))
                expected = count * rounds * (sends + 5)
                if len(consumers.heard) != expected:
                    raise RuntimeError(f"{len(consumers.heard)} callbacks ran, not {expected}")
                consumers.close()
                print(status_row(f"other processes, {count}", ours, plain))
            burst.close()
    finally:
        system.close()
    local = rr.ResourceRegistrar.start(f"local-{uuid.uuid4().hex[:6]}")
    setup_echo(local)
    try:
        for count in counts:
            request = {"local": count}
            consumers = Consumers(local.name, request, count)
            fan = PykkaFanOut(count)
            ours, plain = [], []
            for _ in range(rounds):
                ours.extend(status_sends(request, sends)(local))
                fan.fan_out()
                plain.extend(fan.fan_out() for _ in range(sends))
            fan.close()
            consumers.close()
            print(status_row(f"one process, {count}", ours, plain))
    finally:
        local.stop()
    print()
    print(
        "(floor: a Pipe burst to N across processes, a pykka fan-out to N in one process; "
        f"{rounds} rounds of {sends} sends, alternated)"
    )
    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--sections",
        nargs="+",
        choices=["start", "fresh", "serve", "status"],
        default=["start"],
    )
    parser.add_argument("--isolation", choices=["process", "thread"], default="process")
    parser.add_argument("--state-dir", action="store_true", help="start: catalogs kept")
    parser.add_argument("--counts", type=int, nargs="+", default=[1, 10, 50])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1_000, 10_000, 100_000])
    parser.add_argument("--consumers", type=int, nargs="+", default=[1, 10, 100])
    parser.add_argument("--sends", type=int, default=50, help="timed sends per round (status)")
    parser.add_argument("--kills", type=int, default=5, help="kills per size and round (serve)")
    parser.add_argument("--listen", action="store_true", help="serve: subscribe to the tree")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--pin", action="store_true", help="run under taskset -c 0")
    parser.add_argument("--durability", choices=["process", "power"], default="process")
    args = parser.parse_args()
    if args.pin and not os.environ.get("RR_BENCH_PINNED"):
        command = ["taskset", "-c", "0", sys.executable, *sys.argv]
        env = {**os.environ, "RR_BENCH_PINNED": "1"}
        raise SystemExit(subprocess.run(command, env=env, check=False).returncode)
    if "start" in args.sections:
        section_start(
            args.counts,
            args.rounds,
            isolation=args.isolation,
            state_dir=args.state_dir,
            parallel="parallel" in inspect.signature(rr.Supervisor.stop).parameters,
        )
    if "fresh" in args.sections:
        section_fresh(args.counts, args.rounds, args.durability)
    if "serve" in args.sections:
        section_serve(args.sizes, args.rounds, args.kills, listen=args.listen)
    if "status" in args.sections:
        section_status(args.consumers, args.rounds, args.sends)


if __name__ == "__main__":
    main()
