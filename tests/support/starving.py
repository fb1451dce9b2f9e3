"""A process kept runnable but off the CPUs, by the kernel's scheduler (Linux, root).

Every thread of the process gets the `SCHED_IDLE` policy and is pinned to one CPU that a
busy loop at nice -20 holds, so it stays runnable but runs only when that CPU has nothing
else to do (never, while the loop runs): a manager starved so, as on an overloaded
machine, is what the heartbeat's "could run for only ..." WARNING is about.
(`tests/process/test_heartbeat.py` and `tests/test_log.py` starve their managers with it.)
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Callable, Iterator


def _threads(pid: int) -> set[int]:
    return {int(tid) for tid in os.listdir(f"/proc/{pid}/task")}


def _each_thread(pid: int, change: Callable[[int], None]) -> None:
    """`change(tid)` for every thread of `pid`, again until no new thread appeared (a thread
    started meanwhile inherits its creator's policy and CPUs once its creator has them)."""
    done: set[int] = set()
    while todo := _threads(pid) - done:
        for tid in todo:
            with contextlib.suppress(ProcessLookupError):  # it ended meanwhile
                change(tid)
        done |= todo


@contextlib.contextmanager
def busy_cpu(*, nice: int = 0) -> Iterator[int]:
    """One CPU of this process's kept busy by a Python loop at `nice`; yields that CPU."""
    cpu = min(os.sched_getaffinity(0))
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        os.sched_setaffinity(hog.pid, {cpu})
        os.setpriority(os.PRIO_PROCESS, hog.pid, nice)  # (below 0: root only)
        yield cpu
    finally:
        hog.kill()
        hog.wait(10)


@contextlib.contextmanager
def pinned(pid: int, cpu: int, *, idle: bool = False) -> Iterator[None]:
    """Every thread of process `pid` on `cpu` only (and, `idle`, at `SCHED_IDLE`: it runs
    only when nothing else wants that CPU); all CPUs and the normal policy after."""
    policy = os.SCHED_IDLE if idle else os.SCHED_OTHER

    def pin(tid: int) -> None:
        os.sched_setaffinity(tid, {cpu})
        os.sched_setscheduler(tid, policy, os.sched_param(0))

    everywhere = os.sched_getaffinity(0)

    def free(tid: int) -> None:
        os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
        os.sched_setaffinity(tid, everywhere)

    _each_thread(pid, pin)
    try:
        yield
    finally:
        with contextlib.suppress(FileNotFoundError):  # (it was killed: nothing to free)
            _each_thread(pid, free)


@contextlib.contextmanager
def starved(pid: int) -> Iterator[None]:
    """Process `pid` runnable but kept off the CPUs (see the module's docstring)."""
    with busy_cpu(nice=-20) as cpu, pinned(pid, cpu, idle=True):
        yield
