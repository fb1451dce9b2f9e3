"""The Linux tricks (`rr_actors._platform.linux`) that a test can watch on their own."""

from __future__ import annotations

import multiprocessing
import os
import time

from rr_actors._platform.linux import LinuxPlatform

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
