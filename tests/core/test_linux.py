"""The Linux tricks (`rr_actors._platform.linux`) that a test can watch on their own."""

from __future__ import annotations

import os

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
