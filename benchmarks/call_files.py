"""The source files one call crosses, counted in every thread of every process.

Three windows:

    thread    one dedup-hit `registrar.call(...)` from a registrar of this process (the
              supervisor's `registrar()`) to a manager with `isolation="thread"`
    process   the same call to a manager with `isolation="process"`
    restart   a SIGKILL of a process manager (`provider`, with a backup) until its new
              incarnation answers a call of a consumer manager process (woken through a
              socket of its own, so no rr_actors code carries the request)

How: every process of the tree is traced from its start, all threads (`sys.setprofile`
and `threading.setprofile`), by a `sitecustomize` on `PYTHONPATH` (so in the forkservers
and every process forked from them). At the mark each process forgets what it recorded
(SIGUSR1, acknowledged); after the window each writes the files it ran (SIGUSR2).
Counted: the distinct files under `rr_actors/` and `rr_actors_lab/`; `--list` prints them,
`--why` also each file's entries (its function, the caller, the thread).
The heartbeat is off (its pings run whether or not a call does); the tree has a
`state_dir` (a hit commits a consumer id). Read the rounds after the first: the first
window also counts the spare manager process the supervisor forks in the background. Run
it from the root of the tree to count (the forkservers put the working folder first on
`sys.path`). pykka's own `ask`, counted over pykka's files, is printed as the floor.

`--fresh`: each counted call asks for a new request (a load, not a hit).

Usage: python benchmarks/call_files.py [--rounds 3] [--list | --why]
       [--only thread|process|restart] [--fresh]
"""

from __future__ import annotations

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
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Literal

import _harness

HOOK = """
import os, signal, sys, threading
FOLDER, WHY = os.environ.get("RR_COUNT_FILES"), os.environ.get("RR_COUNT_WHY")
if FOLDER:
    SEEN = set()

    def _profile(frame, event, arg):
        if event == "call":
            SEEN.add(frame.f_code.co_filename)

    def _why(frame, event, arg):  # (each entry into a file from another: who, on which thread)
        if event == "call":
            code, back = frame.f_code, frame.f_back
            SEEN.add(code.co_filename)
            if back is None or back.f_code.co_filename != code.co_filename:
                caller = "-" if back is None else f"{back.f_code.co_filename}:{back.f_code.co_name}"
                try:
                    name = threading.current_thread().name
                except Exception:  # (at the interpreter's exit)
                    name = "?"
                SEEN.add(f"{code.co_filename}\t{code.co_name} <- {caller} [{name}]")

    if WHY:
        _profile = _why

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


def short(path: str) -> str | None:
    """`path` from the package's folder on (whichever copy a process imported: the
    forkservers' `-c` puts their working folder first), `None` outside the packages."""
    parts = Path(path).parts
    for at in range(len(parts) - 1, -1, -1):
        if parts[at] in PACKAGES:
            return "/".join(parts[at:])
    return None


REASONS: dict[str, set[str]] = {}
"""With `--why`: the last window's entries into each counted file."""


def ours(lines: list[str]) -> set[str]:
    """The files in the packages of a process's written `lines` (with `--why`, their
    entries go into `REASONS`)."""
    found = set()
    for line in lines:
        path, _, entry = line.partition("\t")
        name = short(path)
        if name is not None:
            found.add(name)
            if entry:
                callee, _, rest = entry.partition(" <- ")
                caller, _, thread = rest.rpartition(" [")
                caller_path, _, function = caller.rpartition(":")
                where = short(caller_path) or "/".join(Path(caller_path).parts[-2:]) or "-"
                thread = thread.rstrip("]").rstrip("0123456789-")  # (numbered threads: one)
                REASONS.setdefault(name, set()).add(f"{callee} <- {where}:{function} [{thread}]")
    return found


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


CASES = ("thread", "process", "restart")


def counted_files(folder: str, action: Callable[[], object]) -> set[str]:
    """The package files every process ran while `action` ran."""
    signal_all(folder, signal.SIGUSR1, ".marked")
    REASONS.clear()
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
                {
                    path[path.rindex("/pykka/") + 1 :]
                    for path in (line.partition("\t")[0] for line in seen.copy())
                    if "/pykka/" in path
                }
            )
        return counts
    finally:
        ref.stop()


def restart_rounds(folder: str, work: str, rounds: int) -> list[set[str]]:
    """`rounds` SIGKILLs of `provider`, each counted until the consumer's call is answered."""
    import rr_actors as rr  # noqa: PLC0415 - after the tracer is installed

    path = str(Path(work, "consumer.sock"))
    consumer = functools.partial(consumer_setup, path, "provider")
    specs = [
        rr.ManagerSpec("provider", provider_setup, isolation="process", heartbeat=None),
        rr.ManagerSpec("consumer", consumer, isolation="process", heartbeat=None),
    ]
    state_dir = Path(work, "state")
    with rr.Supervisor(specs, max_restarts=rounds + 1, period=3600.0, state_dir=state_dir) as sup:
        ask(path, "warm-up")

        def restart(n: int) -> None:
            os.kill(sup.child("provider").pid or 0, signal.SIGKILL)
            sup.wait_restarted("provider", timeout=BOUND)
            ask(path, f"after-{n}")

        return [counted_files(folder, functools.partial(restart, n)) for n in range(rounds)]


def main() -> int:
    parser = _harness.options(__doc__, rounds=3)
    parser.add_argument("--list", action="store_true", help="the files of each case's last round")
    parser.add_argument("--only", choices=CASES, help="one case")
    parser.add_argument("--fresh", action="store_true", help="calls that load (thread, process)")
    parser.add_argument(
        "--why", action="store_true", help="each file's entries, of each case's last round"
    )
    args = _harness.parse(parser, None)
    if args.why:
        os.environ["RR_COUNT_WHY"] = "1"
    why: dict[str, dict[str, set[str]]] = {}
    with traced_work() as (work, folder):
        found: dict[str, list[set[str]]] = {"pykka ask (floor)": pykka_floor(args.rounds)}
        for case in (args.only,) if args.only else CASES:
            if case == "restart":
                found[case] = restart_rounds(folder, work, args.rounds)
            else:
                kind: Literal["thread", "process"] = "thread" if case == "thread" else "process"
                found[case] = call_rounds(folder, work, kind, args.rounds, fresh=args.fresh)
            why[case] = dict(REASONS)
    rounds = [f"round {n}" for n in range(1, args.rounds + 1)]
    _harness.print_table(
        "distinct rr_actors/ and rr_actors_lab/ files run in the window, every process",
        ["case", *rounds],
        [(case, *(len(files) for files in each)) for case, each in found.items()],
    )
    if args.list or args.why:
        for case, each in found.items():
            print(f"\n{case} ({len(each[-1])}):")
            for name in sorted(each[-1]):
                print(f"  {name}")
                for entry in sorted(why.get(case, {}).get(name, ())):
                    print(f"      {entry}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
