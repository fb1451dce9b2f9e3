"""The Linux tricks (`rr_actors._platform.linux`) that a test can watch on their own."""

from __future__ import annotations

import multiprocessing
import os
import select
import signal
import time
from collections.abc import Iterator
from multiprocessing.connection import Connection
from pathlib import Path

import pytest

from rr_actors._platform import linux_names
from rr_actors._platform.linux import LinuxPlatform, PidfdExitWatch, ProcCpuWatch

# -- freed memory goes back to the system (the observer's server uses it) -------------------


def _resident_bytes() -> int:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def test_releasing_free_memory_hands_freed_heap_pages_back_to_the_system() -> None:
    # 40 MB of C-heap blocks (bytes over 512 B bypass pymalloc); every 100th one and the
    # last stay alive, so the freed space is in the middle of the heap, where glibc's
    # free() keeps it resident
    blocks = [bytes(1024) for _ in range(40_000)]
    kept = blocks[::100] + blocks[-1:]
    del blocks
    freed = _resident_bytes()

    LinuxPlatform().release_free_memory()  # glibc's malloc_trim (CI runs on glibc)

    assert len(kept) == 401
    returned = freed - _resident_bytes()
    assert returned > 20 * 2**20, f"only {returned / 2**20:.1f} MB went back to the system"


# -- one clock for every process of a host (a Load's deadline crosses as itself) -----------


def _clock_and_time() -> tuple[str | None, float]:
    return LinuxPlatform().monotonic_clock(), time.monotonic()


def test_another_process_of_this_host_names_the_same_monotonic_clock_and_reads_it() -> None:
    before = time.monotonic()
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        clock, there = pool.apply(_clock_and_time)
    after = time.monotonic()

    assert LinuxPlatform().monotonic_clock() == clock is not None
    assert before <= there <= after  # a time of the other process is a time of this one


# -- a killed manager's exit does not wait for its inotify watches to be torn down ---------


def _watch_a_file_then_wait(path: str, ready: Connection) -> None:
    """A process with an inotify watch armed on `path` (as a catalog backup's store arms
    one in a pool's process: one of two stores); it says so, then waits to be killed."""
    watch, _ = linux_names.watch_names(), linux_names.watch_names()
    assert watch is not None
    watch.arm([path])
    ready.send(os.getpid())
    ready.recv()  # never answered: the test kills this process


@pytest.fixture
def watcher(tmp_path: Path) -> Iterator[int]:
    """The pid of a spawned process whose inotify watch on a backup file is armed; killed
    and reaped after the test."""
    watched = tmp_path / "backup.db"
    watched.touch()
    ours, theirs = multiprocessing.Pipe()
    process = multiprocessing.get_context("spawn").Process(
        target=_watch_a_file_then_wait, args=(str(watched), theirs), daemon=True
    )
    process.start()
    try:
        assert ours.poll(60), "the process did not arm its watch"
        yield ours.recv()
    finally:
        process.kill()
        process.join(30)


def test_the_exit_watch_holds_the_processes_inotify_watches_past_its_kill(watcher: int) -> None:
    watch = PidfdExitWatch.open(watcher)
    assert watch is not None
    os.kill(watcher, signal.SIGKILL)
    assert select.select([watch], [], [], 30)[0], "its exit was not seen"
    assert watch.exitcode() == -signal.SIGKILL  # (a zombie: seen before it is reaped)
    # its watch outlived it in the copy held here: the kill did not destroy it
    (held,) = watch.held
    assert "inotify wd:" in Path(f"/proc/self/fdinfo/{held}").read_text()
    watch.close()
    assert not Path(f"/proc/self/fd/{held}").exists()


def test_a_child_forked_from_the_watcher_does_not_keep_the_watches_copies(watcher: int) -> None:
    # a copy kept in a fork of the supervisor's process would keep the manager's inotify
    # instance (one of 128 a user) alive as long as that child runs
    watch = PidfdExitWatch.open(watcher)
    assert watch is not None
    try:
        (held,) = watch.held
        child = os.fork()
        if child == 0:  # (the child: exit 0 only if its copy of `held` was closed)
            os._exit(0 if not os.path.exists(f"/proc/self/fd/{held}") else 1)
        _, status = os.waitpid(child, 0)
        assert os.waitstatus_to_exitcode(status) == 0, "the forked child kept the copy"
        assert Path(f"/proc/self/fd/{held}").exists()  # (the watcher's own is kept)
    finally:
        watch.close()


# -- a manager waiting for the disk is not hung (issue 69: a fresh catalog's fdatasync) ----


def _spawn_through(fifo: str, said: Connection) -> None:
    """A process whose one thread waits in the kernel, state D, as in a disk's flush:
    `posix_spawn` (a vfork) waits for its child, whose file action opens `fifo` for reading
    and blocks there until a writer opens it; it says when the spawn returned."""
    said.send(os.getpid())
    child = os.posix_spawn(
        "/bin/true", ["true"], {}, file_actions=[(os.POSIX_SPAWN_OPEN, 3, fifo, os.O_RDONLY, 0)]
    )
    os.waitpid(child, 0)
    said.send("spawned")
    said.recv()  # (never answered: the test kills this process)


def _states(pid: int) -> list[str]:
    task = Path(f"/proc/{pid}/task")
    return [
        (task / tid / "stat").read_text().rsplit(")", 1)[1].split()[0] for tid in os.listdir(task)
    ]


def test_the_time_a_thread_waits_in_state_d_counts_as_waited_and_stays_counted(
    tmp_path: Path,
) -> None:
    # a fresh catalog's first commit syncs its log (SQLite's WAL header): at 600 managers
    # on a busy disk that took 0.94 s, "0.001 s of it waiting for a CPU", and the heartbeat
    # killed the manager as hung in the middle of a call
    fifo = str(tmp_path / "fifo")
    os.mkfifo(fifo)
    ours, theirs = multiprocessing.Pipe()
    process = multiprocessing.get_context("spawn").Process(
        target=_spawn_through, args=(fifo, theirs), daemon=True
    )
    process.start()
    try:
        assert ours.poll(60), "the process did not start"
        pid = ours.recv()
        watch = ProcCpuWatch.open(pid)
        assert watch is not None
        deadline = time.monotonic() + 30
        while "D" not in _states(pid):  # (bounded: the vfork's wait begins soon)
            assert time.monotonic() < deadline, f"never in state D: {_states(pid)}"
            select.select([], [], [], 0.01)
        first = watch.sample()
        between = time.monotonic()  # (after the first sample's reading, before the second's:
        select.select([], [], [], 0.02)  # the time read after the second, as this read once,
        before_second = time.monotonic()  # was later than its reading by a preemption)
        second = watch.sample()
        assert first is not None
        assert second is not None
        assert second.waited - first.waited >= before_second - between > 0.0

        os.close(os.open(fifo, os.O_WRONLY))  # the child's open returns: the spawn ends
        assert ours.poll(30)
        assert ours.recv() == "spawned"
        after = watch.sample()
        assert after is not None
        assert after.waited >= second.waited  # (kept once it ran)
        watch.close()
    finally:
        process.kill()
        process.join(30)
