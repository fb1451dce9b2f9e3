"""The robot's programs: a LiDAR, a motor driver and a navigation node, as real processes.

The external resource manager starts these with `python programs.py <program> ...` (the
standard library only: up in tens of milliseconds). They talk over *topics*: small JSON
files in a bus directory, each replaced atomically (`os.replace`) on every publish:

- `lidar` publishes `scan.json` (`{"lidar", "seq", "t", "ranges"}`) at `--rate` Hz.
- `navigation` reads `scan.json`, `odom.json` and the mission's `goal.json`, and publishes
  `cmd_vel.json`: the goal speed while the goal is ahead, not paused and the latest scan
  is fresh and clear; 0 otherwise (a robot without a working LiDAR must not drive).
- `driver` reads `cmd_vel.json` and integrates it into odometry: it publishes `odom.json`
  and appends every sample to `odom.jsonl`. A command older than `--cmd-timeout` means 0.

Every program writes `pids/<pid>.json` (pid and creation time) when it starts, and exits
when the process `--watch-pid` dies. Times are `time.monotonic()` seconds (system-wide).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import selectors
import signal
import sys
import time
from pathlib import Path
from typing import Any

SAFETY_DISTANCE_M = 0.3
"""Navigation stops when any LiDAR range is shorter than this (metres)."""


def read_topic(bus: Path, topic: str) -> dict[str, Any] | None:
    """The latest message on `topic` (`bus/<topic>.json`), or `None` before the first one."""
    try:
        data: dict[str, Any] = json.loads((bus / f"{topic}.json").read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None
    return data


def publish(bus: Path, topic: str, message: dict[str, Any]) -> None:
    """Replace `bus/<topic>.json` by `message` atomically (readers see old or new)."""
    tmp = bus / f".{topic}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(message))
    os.replace(tmp, bus / f"{topic}.json")


def start_time(pid: int) -> int | None:
    """Creation time of process `pid` (field 22 of `/proc/<pid>/stat`, in clock ticks).

    Returns `None` if there is no such process or it is a zombie (it has exited).
    """
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[1].split()
    if fields[0] == "Z":  # field 3, the state: a zombie has exited already
        return None
    return int(fields[19])  # field 22 (fields here start at field 3)


class Ticker:
    """Waits one period at a time, and ends the program when the watched process dies.

    The wait is on a pidfd of the watched process (Linux 5.3+; through `selectors`,
    epoll, which takes a descriptor of any number), so the death of the mission is
    noticed at once, without polling.
    """

    def __init__(self, rate_hz: float, watch_pid: int | None) -> None:
        self.period = 1.0 / rate_hz
        self.next = time.monotonic()
        self.watch: selectors.BaseSelector | None = None  # (readable: the watched one died)
        if watch_pid is not None:
            try:
                pidfd = os.pidfd_open(watch_pid)
            except ProcessLookupError:
                sys.exit(0)
            self.watch = selectors.DefaultSelector()
            self.watch.register(pidfd, selectors.EVENT_READ)

    def wait(self) -> None:
        """Wait until the next period starts; exit the program if the watched one died."""
        self.next += self.period
        delay = self.next - time.monotonic()
        if delay < -self.period:  # far behind (the machine was busy): do not catch up
            self.next = time.monotonic()
            delay = 0.0
        if self.watch is None:
            time.sleep(max(0.0, delay))
            return
        if self.watch.select(max(0.0, delay)):
            sys.exit(0)


def _startup(args: argparse.Namespace, program: str) -> Path:
    """Common start: register the pid file, exit cleanly on SIGTERM, report ready."""
    bus = Path(args.bus)

    def terminate(*_: object) -> None:
        sys.exit(0)

    signal.signal(signal.SIGTERM, terminate)
    pids = bus / "pids"
    pids.mkdir(parents=True, exist_ok=True)
    pid = os.getpid()
    record = {"pid": pid, "start_time": start_time(pid), "program": program, "name": args.name}
    (pids / f"{pid}.json").write_text(json.dumps(record))
    return bus


def _ready(args: argparse.Namespace) -> None:
    """Tell the manager that started us that we are up (one byte on `--ready-fd`)."""
    if args.ready_fd is not None:
        os.write(args.ready_fd, b"R")
        os.close(args.ready_fd)


def run_lidar(args: argparse.Namespace) -> None:
    """A 2D LiDAR in a corridor: publish a scan of `--beams` ranges at `--rate` Hz."""
    bus = _startup(args, "lidar")
    rng = random.Random(args.seed)  # noqa: S311 - sensor noise, not cryptography
    ticker = Ticker(args.rate, args.watch_pid)
    seq = 0
    first = True
    while True:
        ranges = []
        for beam in range(args.beams):
            angle = math.pi * beam / max(1, args.beams - 1)  # 0..180 degrees, ahead
            wall = 1.0 / max(abs(math.cos(angle)), 0.05)  # a corridor 2 m wide
            ranges.append(round(min(wall, 10.0) + rng.gauss(0.0, 0.01), 3))
        scan = {"lidar": args.name, "seq": seq, "t": time.monotonic(), "ranges": ranges}
        publish(bus, "scan", scan)
        seq += 1
        if first:
            _ready(args)
            first = False
        ticker.wait()


def _last_distance(bus: Path) -> float:
    """The distance of the last whole sample a driver logged (0.0 before the first)."""
    try:
        lines = (bus / "odom.jsonl").read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        return 0.0
    for line in reversed(lines):
        try:
            return float(json.loads(line)["x"])
        except (ValueError, KeyError):
            continue  # a line cut short by a kill
    return 0.0


def run_driver(args: argparse.Namespace) -> None:
    """A motor driver: integrate velocity commands into odometry at `--rate` Hz.

    It starts from the last sample its predecessor logged: the robot did not move while
    its driver was down.
    """
    bus = _startup(args, "driver")
    x = _last_distance(bus)
    ticker = Ticker(args.rate, args.watch_pid)
    last = time.monotonic()
    with (bus / "odom.jsonl").open("a", encoding="utf-8") as log:
        v = 0.0  # the first sample: up, and the robot has not moved since the last one
        while True:
            now = time.monotonic()
            x += v * (now - last)
            last = now
            sample = {"t": now, "x": round(x, 6), "v": v, "pid": os.getpid()}
            log.write(json.dumps(sample) + "\n")  # the record first: a successor resumes
            log.flush()  # from it, so a kill between the two cannot hide a stop
            publish(bus, "odom", sample)
            if args.ready_fd is not None:
                _ready(args)
                args.ready_fd = None
            ticker.wait()
            cmd = read_topic(bus, "cmd_vel")
            fresh = cmd is not None and time.monotonic() - float(cmd["t"]) <= args.cmd_timeout
            v = float(cmd["v"]) if cmd is not None and fresh else 0.0


def run_navigation(args: argparse.Namespace) -> None:
    """Drive to the mission's goal: command the goal speed while it is safe, else 0."""
    bus = _startup(args, "navigation")
    ticker = Ticker(args.rate, args.watch_pid)
    first = True
    while True:
        now = time.monotonic()
        goal = read_topic(bus, "goal")
        odom = read_topic(bus, "odom")
        scan = read_topic(bus, "scan")
        scan_ok = (
            scan is not None
            and now - float(scan["t"]) <= args.scan_timeout
            and min(scan["ranges"]) > SAFETY_DISTANCE_M
        )
        v = 0.0
        if goal is not None and odom is not None and scan_ok and not goal.get("paused", False):
            remaining = float(goal["distance_m"]) - float(odom["x"])
            if remaining > 0:
                v = float(goal["speed"])
        publish(bus, "cmd_vel", {"t": now, "v": v})
        if first:
            _ready(args)
            first = False
        ticker.wait()


def parser() -> argparse.ArgumentParser:
    """The command line of the programs (`python programs.py <program> --bus DIR ...`)."""
    top = argparse.ArgumentParser(prog="programs.py", description=__doc__.split("\n")[0])
    sub = top.add_subparsers(dest="program", required=True)
    for name in ("lidar", "driver", "navigation"):
        p = sub.add_parser(name)
        p.add_argument("--bus", required=True, help="topic directory")
        p.add_argument("--name", default=name, help="instance name (e.g. lidar1)")
        p.add_argument("--rate", type=float, default=20.0, help="loop rate in Hz")
        p.add_argument("--watch-pid", type=int, default=None, help="exit when this pid dies")
        p.add_argument("--ready-fd", type=int, default=None, help="write one byte when up")
        if name == "lidar":
            p.add_argument("--beams", type=int, default=37)
            p.add_argument("--seed", type=int, default=0)
        elif name == "driver":
            p.add_argument("--cmd-timeout", type=float, default=0.5, help="watchdog, seconds")
        else:
            p.add_argument("--scan-timeout", type=float, default=0.5, help="seconds")
    return top


def main(argv: list[str] | None = None) -> None:
    """Run the program named on the command line until SIGTERM or the watched pid dies."""
    args = parser().parse_args(argv)
    {"lidar": run_lidar, "driver": run_driver, "navigation": run_navigation}[args.program](args)


if __name__ == "__main__":
    main()
