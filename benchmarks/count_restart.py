"""The source files a supervised restart runs, counted in every process of the tree.

A supervisor in this process runs two manager processes: `provider` (serves `res`, with
a backup) and `consumer` (holds one of its resources). The window counted runs from the
SIGKILL of `provider` to its new incarnation answering the consumer's first call after
it: the supervisor sees the exit and restarts it (`wait_restarted` returns), then a
thread of the consumer's own calls it (woken through a socket of its own, so no
rr_actors code carries the request) and answers.

How: every process of the tree is traced from its start, all threads (`sys.setprofile`
and `threading.setprofile`: each function and module code run is a "call"); a
`sitecustomize` on `PYTHONPATH` installs it in the forkservers the tree starts, and so in
every process forked from them (a forked child forgets what its parent recorded), and
this process installs it before the tree starts. At the mark every process forgets what
it recorded (SIGUSR1, acknowledged); after the call every process writes the files it
ran (SIGUSR2). Counted: the distinct files under `rr_actors/` and `rr_actors_lab/`, per
process (the supervisor's, which also runs this script's `wait_restarted`; the provider's
new incarnation; the consumer; the rest, forkservers and spares, as "other") and in all.
The heartbeat is off (`--heartbeat` on): its pings run whether or not a restart does.
Run it from the root of the tree to count: the forkservers' `python -c` puts the working
folder first on `sys.path`, so the managers import that tree's packages.

`--hit` counts the same window with no kill: the consumer's call is a dedup hit (its
request loaded already), a cross-process call's files by the same method.

Usage: python benchmarks/count_restart.py [--rounds 3] [--heartbeat] [--list] [--hit]
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import importlib
import os
import signal
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

HOOK = """
import os, signal, sys, threading
FOLDER = os.environ.get("RR_COUNT_FILES")
if FOLDER:
    SEEN = set()

    def _profile(frame, event, arg):
        if event == "call":
            SEEN.add(frame.f_code.co_filename)

    def _write(name, text):
        path = os.path.join(FOLDER, name)
        with open(path + ".part", "w") as out:
            out.write(text)
        os.replace(path + ".part", path)

    def _mark(signum, frame):
        SEEN.clear()
        _write(f"{os.getpid()}.marked", "")

    def _dump(signum, frame):
        _write(f"{os.getpid()}.files", "\\n".join(sorted(SEEN)))

    os.register_at_fork(after_in_child=SEEN.clear)
    signal.signal(signal.SIGUSR1, _mark)
    signal.signal(signal.SIGUSR2, _dump)
    threading.setprofile(_profile)
    sys.setprofile(_profile)
"""
"""The tracer each process runs at its start (as `sitecustomize`)."""

PACKAGES = ("rr_actors", "rr_actors_lab")

BOUND = 120.0
"""Seconds any one step may take (the processes run traced, on a loaded machine)."""


def provider_setup(registrar: Any) -> None:
    registrar.register_server("res", load=lambda r: r, unload=lambda r, s: None)


def consumer_setup(path: str, provider: str, registrar: Any) -> None:
    """Listen on `path`; for each connection, call `provider` and answer its query id."""
    server = socket.socket(socket.AF_UNIX)
    server.bind(path)
    server.listen()

    def serve() -> None:
        while True:
            conn, _ = server.accept()
            with conn:
                request = conn.recv(1024).decode()
                try:
                    query = registrar.call(provider, "res", request, timeout=BOUND)
                    conn.sendall(f"ok {query.id}".encode())
                except Exception as exc:
                    conn.sendall(f"error {exc!r}".encode())

    threading.Thread(target=serve, name="count-consumer", daemon=True).start()


def ask(path: str, request: str) -> str:
    """The consumer's answer to a call of `request`."""
    with socket.socket(socket.AF_UNIX) as conn:
        conn.settimeout(BOUND)
        conn.connect(path)
        conn.sendall(request.encode())
        answer = conn.recv(1024).decode()
    if not answer.startswith("ok "):
        raise RuntimeError(f"the consumer's call failed: {answer}")
    return answer


def traced() -> list[int]:
    """The processes of this run's tree, other than this one: its descendants (a manager's
    environment is no sign: its process title overwrites it)."""
    parents: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        with contextlib.suppress(OSError, ValueError, IndexError):
            if entry.name.isdigit():  # (the command, in brackets, may hold spaces)
                state, parent = (entry / "stat").read_text().rsplit(")", 1)[1].split()[:2]
                if state != "Z":  # (a zombie answers no signal)
                    parents[int(entry.name)] = int(parent)
    found, pids = {os.getpid()}, []
    while grown := [pid for pid, parent in parents.items() if parent in found and pid not in found]:
        found.update(grown)
        pids += grown
    return pids


def signal_all(folder: str, signum: int, suffix: str) -> dict[int, Path]:
    """Send `signum` to every traced process, this one too; the file each then wrote."""
    pids = [*traced(), os.getpid()]
    for pid in pids:
        for old in Path(folder).glob(f"{pid}.*"):
            old.unlink()
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signum)
    written: dict[int, Path] = {}
    deadline = time.monotonic() + BOUND
    while time.monotonic() < deadline:
        alive = [pid for pid in pids if pid in {*traced(), os.getpid()}]
        written = {pid: Path(folder, f"{pid}{suffix}") for pid in alive}
        if all(path.exists() for path in written.values()):
            return written
        time.sleep(0.01)  # (a benchmark's wait, bounded: the handlers run when they can)
    raise RuntimeError(f"not every process answered signal {signum} within {BOUND:g} s")


def ours(paths: list[str]) -> set[str]:
    """The files of `paths` in the packages, from the package's folder on (whichever copy
    a process imported: the forkservers' `-c` puts their working folder first)."""
    found = set()
    for path in paths:
        parts = Path(path).parts
        for at in range(len(parts) - 1, -1, -1):
            if parts[at] in PACKAGES:
                found.add("/".join(parts[at:]))
                break
    return found


def restart_round(sup: Any, folder: str, path: str, n: int, kill: bool) -> dict[str, set[str]]:
    """One restart counted (or, not `kill`, one dedup hit): the files each process ran."""
    signal_all(folder, signal.SIGUSR1, ".marked")
    if kill:
        os.kill(sup.child("provider").pid, signal.SIGKILL)
        sup.wait_restarted("provider", timeout=BOUND)
    ask(path, f"after-{n}" if kill else "warm-up")
    files = signal_all(folder, signal.SIGUSR2, ".files")
    roles = {
        os.getpid(): "supervisor",
        sup.child("provider").pid: "provider",
        sup.child("consumer").pid: "consumer",
    }
    counted: dict[str, set[str]] = {
        "supervisor": set(),
        "provider": set(),
        "consumer": set(),
        "other": set(),
    }
    for each, written in files.items():
        counted[roles.get(each, "other")] |= ours(written.read_text().split("\n"))
    return counted


@contextlib.contextmanager
def traced_work() -> Iterator[tuple[str, str]]:
    """A work folder and its marks folder, with `HOOK` installed as `sitecustomize` in
    this process and every process started from it (through `PYTHONPATH`)."""
    with tempfile.TemporaryDirectory() as work:
        folder, hooks = Path(work, "marks"), Path(work, "hooks")
        folder.mkdir()
        hooks.mkdir()
        (hooks / "sitecustomize.py").write_text(HOOK)
        os.environ["RR_COUNT_FILES"] = str(folder)
        os.environ["PYTHONPATH"] = os.pathsep.join(
            [str(hooks), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
        )
        sys.path.insert(0, str(hooks))
        importlib.import_module("sitecustomize")  # (this process's tracer)
        yield work, str(folder)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3, help="restarts counted (default 3)")
    parser.add_argument("--heartbeat", action="store_true", help="the managers' heartbeat on")
    parser.add_argument("--list", action="store_true", help="the files of the last round")
    parser.add_argument("--hit", action="store_true", help="no kill: a dedup hit's files")
    args = parser.parse_args()
    with traced_work() as (work, folder):
        rounds = run(args.rounds, args.heartbeat, folder, work, kill=not args.hit)
    report(rounds, args.list, "a dedup hit" if args.hit else "SIGKILL to the first call answered")
    return 0


def run(
    rounds: int, heartbeat: bool, folder: str, work: str, *, kill: bool
) -> list[dict[str, set[str]]]:
    import rr_actors as rr  # noqa: PLC0415 - after the tracer is installed

    path = str(Path(work, "consumer.sock"))
    beat = 0.25 if heartbeat else None
    specs = [
        rr.ManagerSpec("provider", provider_setup, isolation="process", heartbeat=beat),
        rr.ManagerSpec(
            "consumer",
            functools.partial(consumer_setup, path, "provider"),
            isolation="process",
            heartbeat=beat,
        ),
    ]
    state_dir = Path(work, "state")
    sup = rr.Supervisor(specs, max_restarts=rounds + 1, period=3600.0, state_dir=state_dir)
    with sup:
        ask(path, "warm-up")
        return [restart_round(sup, folder, path, n, kill) for n in range(rounds)]


def report(rounds: list[dict[str, set[str]]], listed: bool, window: str) -> None:
    print(f"distinct rr_actors/ and rr_actors_lab/ files run, {window}")
    print("| round | supervisor | provider | consumer | other | all processes |")
    print("|---|---:|---:|---:|---:|---:|")
    for n, counted in enumerate(rounds, 1):
        every = set().union(*counted.values())
        row = " | ".join(
            str(len(counted[role])) for role in ("supervisor", "provider", "consumer", "other")
        )
        print(f"| {n} | {row} | {len(every)} |")
    if listed and rounds:
        for role, files in rounds[-1].items():
            print(f"\n{role} ({len(files)}):")
            for name in sorted(files):
                print(f"  {name}")


if __name__ == "__main__":
    sys.exit(main())
