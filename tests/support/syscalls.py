"""A real supervision tree traced with `strace`: which answers left before the writes they
acknowledge were synced.

```
 traced(state_dir, durability, replies) --strace -f -y--> a driver program: a Supervisor
   (`durability`) with one process manager on a fresh `state_dir`, a consumer that loads
   and unloads one after the other, a mark written to /dev/null before and after (after
   one load and unload: the first commit begins the backup's log, SQLite syncing its
   header and name, and makes its commit count; the start's traffic is over)
 unsynced_sends(trace, state_dir) --> every send on a socket between the marks taken
   while a write to the backup (file, -wal, -commits) or a name made in its directory was
   not synced yet
 started(state_dir, durability) --strace--> `STARTING`: the same tree's `start()` alone,
   on a fresh `state_dir` (its backup made): what it synced
```
"""

from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

DRIVER = textwrap.dedent(
    """
    import os, sys
    import rr_actors as rr

    def setup(reg):
        reg.register_server("res", load=lambda r: {"r": r}, unload=lambda r, s: None)

    state, durability, loads = sys.argv[1], sys.argv[2], int(sys.argv[3])
    spec = rr.ManagerSpec("erm", setup=setup, isolation="process", heartbeat=None)
    mark = os.open(os.devnull, os.O_WRONLY)
    with rr.Supervisor([spec], state_dir=state, durability=durability) as sup:
        app = sup.registrar("app")
        warm = app.call("erm", "res", -1, timeout=60.0)  # (a fresh backup's log begins)
        app.unload(warm.id, timeout=60.0)
        os.write(mark, b"s" * 4001)  # (the marks: their sizes, to /dev/null)
        ids = [app.call("erm", "res", i, timeout=60.0).id for i in range(loads)]
        for query_id in ids:
            app.unload(query_id, timeout=60.0)
        os.write(mark, b"e" * 4002)
    """
)

STARTING = textwrap.dedent(
    """
    import os, sys
    import rr_actors as rr

    def setup(reg):
        reg.register_server("res", load=lambda r: {"r": r}, unload=lambda r, s: None)

    state, durability = sys.argv[1], sys.argv[2]
    spec = rr.ManagerSpec("erm", setup=setup, isolation="process", heartbeat=None)
    mark = os.open(os.devnull, os.O_WRONLY)
    sup = rr.Supervisor([spec], state_dir=state, durability=durability)
    os.write(mark, b"s" * 4001)
    sup.start()
    os.write(mark, b"e" * 4002)
    sup.stop()
    """
)
"""The driver of `started`: a tree of one process manager started on a fresh
`state_dir`, marked before `start()` and after it returned."""

TRACED = (
    "fdatasync,fsync,write,pwrite64,sendmsg,sendto,openat,link,linkat,rename,renameat2,"
    "clone,clone3,fork,vfork"
)
_CALL = re.compile(r"^(\d+)\s+(?:<\.\.\. )?(\w+)(?: resumed>)?\(?(.*)$")
_FD = re.compile(r"^(\d+)<([^>]*)>")
_PATHS = re.compile(r'"([^"]*)"')
_MARKS = tuple(f"{fd}</dev/null>" for fd in range(3, 64))


@dataclasses.dataclass
class Traced:
    """What a traced run did between its marks."""

    syncs: int  # fdatasync and fsync calls, every process
    syncs_of: dict[str, int]  # by the name synced
    syncs_of_all: dict[str, int]  # by the name synced, the whole trace (marks or not)
    unsynced_sends: list[str]  # the trace lines of sends taken with something unsynced
    sends: int


def traced(tmp_path: Path, durability: str, loads: int) -> Traced:
    """Run the driver under `strace` (`loads` loads, then as many unloads)."""
    state = tmp_path / "state"
    trace = tmp_path / "trace.txt"
    command = ["strace", "-f", "-qq", "-y", "-s", "0", "-e", f"trace={TRACED}", "-o", str(trace)]
    command += [sys.executable, "-c", DRIVER, str(state), durability, str(loads)]
    subprocess.run(command, check=True, timeout=300, env=os.environ.copy())
    return unsynced_sends(trace.read_text().splitlines(), state)


def started(tmp_path: Path, durability: str) -> Traced:
    """Run `STARTING` under `strace`: what a manager's start on a fresh `state_dir` did
    (its `syncs` and `syncs_of`: every process, between the marks)."""
    state = tmp_path / "state"
    trace = tmp_path / "trace.txt"
    command = ["strace", "-f", "-qq", "-y", "-s", "0", "-e", f"trace={TRACED}", "-o", str(trace)]
    command += [sys.executable, "-c", STARTING, str(state), durability]
    subprocess.run(command, check=True, timeout=300, env=os.environ.copy())
    return unsynced_sends(trace.read_text().splitlines(), state)


def processes(lines: list[str]) -> dict[str, str]:
    """Each thread id of the trace -> its process id (from the `clone`s: a thread of its
    parent's process unless `CLONE_THREAD` is not set)."""
    spawned: dict[str, tuple[str, bool]] = {}  # child -> (parent thread, a thread)
    unfinished: dict[str, bool] = {}
    for line in lines:
        match = _CALL.match(line)
        if match is None or match.group(2) not in ("clone", "clone3", "fork", "vfork"):
            continue
        tid = match.group(1)
        if "<unfinished" in line:
            unfinished[tid] = "CLONE_THREAD" in line
            continue
        thread = unfinished.pop(tid, False) if "resumed>" in line else "CLONE_THREAD" in line
        child = line.rsplit("= ", 1)[-1].strip()
        if child.isdigit():
            spawned[child] = (tid, thread)

    def process(tid: str) -> str:
        while tid in spawned and spawned[tid][1]:
            tid = spawned[tid][0]
        return tid

    return {tid: process(tid) for tid in {*spawned, *(p for p, _ in spawned.values())}}


def unsynced_sends(lines: list[str], state: Path) -> Traced:
    """Replay the trace: each write to the backup's files dirties that file (a name made
    in the state directory, the directory) until a sync of it completes; each send on a
    socket, between the marks, by a process that writes the backup (its answers) must
    find nothing dirty."""
    replay = _Replay(str(state), processes(lines))
    calls = [
        (m.group(1), m.group(2), m.group(3), line) for line in lines if (m := _CALL.match(line))
    ]
    for tid, call, rest, _ in calls:
        fd = _FD.match(rest) if call == "pwrite64" else None
        if fd and _backup_file(fd.group(2), replay.folder):
            replay.writers.add(replay.process.get(tid, tid))
    for tid, call, rest, line in calls:
        if call == "write" and rest.startswith(_MARKS):
            replay.marked = ", 4001)" in rest
        elif call in ("fdatasync", "fsync"):
            replay.synced(tid, call, rest, line)
        elif "resumed>" not in line:
            replay.called(tid, call, rest, line)
    return replay.result


@dataclasses.dataclass
class _Replay:
    folder: str
    process: dict[str, str]
    writers: set[str] = dataclasses.field(default_factory=set)
    dirty: dict[str, str] = dataclasses.field(default_factory=dict)  # name -> its line
    pending: dict[str, str] = dataclasses.field(default_factory=dict)  # thread -> name
    marked: bool = False
    result: Traced = dataclasses.field(default_factory=lambda: Traced(0, {}, {}, [], 0))

    def synced(self, tid: str, call: str, rest: str, line: str) -> None:
        """A sync counts once it returned (`<... resumed>` of an unfinished one)."""
        if "resumed>" in line:
            name = self.pending.pop(tid, "")
        else:
            fd = _FD.match(rest)
            name = fd.group(2) if fd else ""
            if "<unfinished" in line:
                self.pending[tid] = name
                return
        short = os.path.basename(name) if name != self.folder else "(directory)"
        self.result.syncs_of_all[short] = self.result.syncs_of_all.get(short, 0) + 1
        if self.marked:
            self.result.syncs += 1
            self.result.syncs_of[short] = self.result.syncs_of.get(short, 0) + 1
        self.dirty.pop(name, None)

    def called(self, tid: str, call: str, rest: str, line: str) -> None:
        fd = _FD.match(rest)
        target = fd.group(2) if fd else ""
        paths = _PATHS.findall(rest)
        folder = self.folder
        if call in ("write", "pwrite64") and _backup_file(target, folder):
            self.dirty[target] = line
        elif call in ("link", "linkat", "rename", "renameat2"):
            if any(os.path.dirname(path) == folder for path in paths[1:]):
                self.dirty[folder] = line  # (a name made there)
        elif call == "openat" and "O_CREAT" in rest and paths:
            if paths[0].endswith("-commits") and os.path.dirname(paths[0]) == folder:
                self.dirty[folder] = line
        elif self.marked and call in ("write", "sendmsg", "sendto") and _socket(target):
            self.sent(tid, line)

    def sent(self, tid: str, line: str) -> None:
        if self.process.get(tid, tid) in self.writers:
            self.result.sends += 1
            if self.dirty:
                unsynced = sorted(self.dirty)
                self.result.unsynced_sends.append(f"{line}  (unsynced: {unsynced})")


def _backup_file(name: str, folder: str) -> bool:
    """A file a restore reads: the backup, its -wal, its commit count (not -shm, rebuilt;
    not a -journal: none is left behind after a commit in WAL mode)."""
    if os.path.dirname(name) != folder:
        return False
    return not name.endswith(("-shm", "-journal", ".lock"))


def _socket(name: str) -> bool:
    return name.startswith(("UNIX", "socket:"))
