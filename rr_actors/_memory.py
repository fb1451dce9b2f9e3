"""Keep a manager process's memory cheap to free, so that its crash is seen sooner.

A supervisor sees a `SIGKILL`ed manager only once the kernel has torn the process down,
and the kernel frees a process's memory before its parent can see it exit (`exit_mm`
comes before the descriptors close): about 0.12 ms per MB still mapped in 4 KiB pages on
the project's VM, most of a 100k-entry manager's detection time. Memory on 2 MiB
transparent huge pages is freed a page table at a time instead of 512 entries at a
time.

So a manager process moves its dense anonymous memory onto huge pages with
`madvise(MADV_COLLAPSE)` (Linux 6.1 and later; the `enabled` THP setting may be
`madvise`, not `never`): every 2 MiB-aligned chunk of a private anonymous mapping (the C
heap, Python's arenas, large objects) of which at least three quarters are resident, so
a collapse adds at most a third to what the chunk held; thread stacks and other sparse
mappings stay as they are. A [`Collapser`][rr_actors._memory.Collapser] does it on a
daemon thread at the lowest CPU priority (nice 19), so that it never delays serving:
while a spare process idles, once a manager is ready (its catalog restored) and then
every `interval` seconds, for what the catalog grew since. Elsewhere (another kernel or
operating system) it does nothing.

Measured (`benchmarks/bench_supervisor.py`, `docs/performance.md`): a manager restored
with 100k entries holds about 34 MB, of which 14-18 MB are collapsed; its SIGKILL was
seen after 4.1-5.1 ms instead of 4.7-6.6 ms in runs alternated with the code before.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import functools
import logging
import os
import sys
import threading

__all__ = ["Collapser", "collapse_dense_memory"]

logger = logging.getLogger("rr_actors")

_MADV_COLLAPSE = 25  # <linux/mman.h>, Linux >= 6.1
_HUGE_PAGE = 2 << 20  # bytes, x86-64 and arm64 with 4 KiB pages
_PAGE = 4096
_DENSE_PAGES = _HUGE_PAGE // _PAGE * 3 // 4  # resident pages a chunk needs to be collapsed
_LOWEST_PRIORITY = 19


@functools.cache
def _libc() -> ctypes.CDLL | None:
    """The C library with `madvise` and `mincore`, on Linux; `None` elsewhere."""
    if not sys.platform.startswith("linux") or os.sysconf("SC_PAGE_SIZE") != _PAGE:
        return None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
        libc.mincore.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_char_p]
    except (OSError, AttributeError):
        return None
    return libc


def _anonymous_chunks() -> list[tuple[int, int]]:
    """The 2 MiB-aligned `(start, end)` parts of the private anonymous rw mappings."""
    spans = []
    with open("/proc/self/maps", encoding="ascii") as maps:
        for line in maps:
            fields = line.split()  # range perms offset device inode [path]
            if fields[1] != "rw-p" or (len(fields) > 5 and fields[5] != "[heap]"):
                continue
            low, high = (int(address, 16) for address in fields[0].split("-"))
            low = -(-low // _HUGE_PAGE) * _HUGE_PAGE
            high -= high % _HUGE_PAGE
            if high > low:
                spans.append((low, high))
    return spans


def collapse_dense_memory() -> int:
    """Collapse this process's dense anonymous 2 MiB chunks into transparent huge pages.

    Runs on the calling thread (each `madvise` releases the GIL). A chunk already on a
    huge page is passed over by the kernel at once, so calling it again is cheap.

    Returns:
        The bytes of the chunks that are on huge pages afterwards; 0 where the kernel has
        no `MADV_COLLAPSE` (or THP is `never`), on other systems, and without
        `/proc/self/maps`. A chunk the kernel cannot collapse now (no free huge page,
        pages in use) is left as it is. Never raises `OSError`.
    """
    libc = _libc()
    if libc is None:
        return 0
    try:
        spans = _anonymous_chunks()
    except OSError:
        return 0
    resident = ctypes.create_string_buffer(_HUGE_PAGE // _PAGE)
    collapsed = 0
    for low, high in spans:
        for start in range(low, high, _HUGE_PAGE):
            if libc.mincore(ctypes.c_void_p(start), _HUGE_PAGE, resident) != 0:
                break  # unmapped since /proc/self/maps was read
            if sum(byte & 1 for byte in resident.raw) < _DENSE_PAGES:
                continue
            if libc.madvise(ctypes.c_void_p(start), _HUGE_PAGE, _MADV_COLLAPSE) == 0:
                collapsed += _HUGE_PAGE
            elif ctypes.get_errno() == errno.EINVAL:
                return collapsed  # no MADV_COLLAPSE in this kernel, or THP disabled
    return collapsed


class Collapser:
    """A daemon thread that runs `collapse_dense_memory` when asked and every `interval`.

    One per manager process (`COLLAPSER`). The thread starts at the first `request`, and
    lowers its own priority to nice 19 (Linux threads have their own nice value) so that
    the kernel's copying competes with nothing the manager serves.

    Args:
        interval: seconds between passes when nobody asks for one (for the memory a
            catalog grows by while serving).
    """

    def __init__(self, interval: float = 10.0) -> None:
        self.interval = interval
        self.passes = 0
        """How many passes finished, asked for or periodic."""
        self._requested = 0  # tickets handed out by `request`
        self._served = 0  # the newest ticket whose pass finished
        self._finished = threading.Condition()
        self._wake = threading.Event()
        self._closed = False
        self._thread: threading.Thread | None = None

    def request(self) -> int:
        """Ask for a pass soon; returns at once (starts the thread the first time).

        Returns:
            A ticket for `wait`: the pass it names starts after this call.
        """
        with self._finished:
            self._requested += 1
            ticket = self._requested
            if self._thread is None:
                self._thread = threading.Thread(
                    target=self._run, name="rr-memory-collapse", daemon=True
                )
                self._thread.start()
        self._wake.set()
        return ticket

    @property
    def latest(self) -> int:
        """The newest ticket `request` handed out (0 before the first)."""
        with self._finished:
            return self._requested

    def wait(self, ticket: int, timeout: float) -> bool:
        """Wait until the pass of `ticket` finished; `False` after `timeout` seconds."""
        with self._finished:
            return self._finished.wait_for(lambda: self._served >= ticket, timeout)

    def wait_for_passes(self, passes: int, timeout: float) -> bool:
        """Wait until `passes` passes finished; `False` after `timeout` seconds."""
        with self._finished:
            return self._finished.wait_for(lambda: self.passes >= passes, timeout)

    def close(self, timeout: float = 5.0) -> None:
        """Stop the thread after its current pass (waits up to `timeout` seconds).

        A manager process never needs it (it ends with `os._exit`); tests do.
        """
        with self._finished:
            self._closed = True
            thread = self._thread
        self._wake.set()
        if thread is not None:
            thread.join(timeout)

    def _run(self) -> None:
        with contextlib.suppress(OSError):  # if not allowed: at the manager's priority
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), _LOWEST_PRIORITY)
        while True:
            self._wake.wait(self.interval)
            self._wake.clear()
            with self._finished:
                if self._closed:
                    return
                ticket = self._requested
            try:
                collapse_dense_memory()
            except Exception:  # an optimisation must never end the process
                logger.exception("collapsing memory into huge pages failed")
            with self._finished:
                self._served = ticket
                self.passes += 1
                self._finished.notify_all()


COLLAPSER = Collapser()
"""This process's collapser (used in manager processes only)."""
