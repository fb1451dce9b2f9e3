"""Keep a manager process's memory cheap to free, so that its crash is seen sooner.

A supervisor sees a `SIGKILL`ed manager only once the kernel has torn the process down,
and the kernel frees a process's memory before its parent can see it exit (`exit_mm`
comes before the descriptors close): about 0.12 ms per MB still mapped in 4 KiB pages on
the project's VM, most of a 100k-entry manager's detection time. Memory on 2 MiB
transparent huge pages is freed a page table at a time instead of 512 entries at a
time.

So a manager process moves its dense anonymous memory onto huge pages with
`madvise(MADV_COLLAPSE)`: every huge-page-aligned chunk of a private anonymous mapping
(the C heap, Python's arenas, large objects) of which at least three quarters are
resident; thread stacks and other sparse mappings stay as they are. Only on Linux 6.1
and later (checked once with a zero-length call), and not where the administrator set
transparent huge pages to `never` (`MADV_COLLAPSE` itself would ignore that setting).

Costs: a collapsed chunk is private and fully backed, so pages the chunk shared with
the forkserver copy-on-write are copied, and resident pages that only map the zero page
are filled (a manager restored with 100k entries: Rss unchanged, about 4 MB more private
memory). A [`Collapser`][rr_actors._memory.Collapser] does it on a daemon thread at the
manager's own priority (a lower one would let that thread be preempted while it holds
the GIL, and stall every thread of the manager on a busy host): while a spare process
idles, once a manager has restored its catalog and run its setup, and then every
`interval` seconds, for what the catalog grew since.

Measured (`benchmarks/bench_supervisor.py`, `docs/performance.md`): a manager restored
with 100k entries holds about 34 MB, of which 14-18 MB are collapsed; its SIGKILL was
seen after 4.1-5.1 ms instead of 4.7-6.6 ms in runs alternated with the code before.
"""

from __future__ import annotations

import errno
import functools
import logging
import os
import sys
import threading
from typing import Any

__all__ = ["Collapser", "collapse_dense_memory", "supported"]

logger = logging.getLogger("rr_actors")

_MADV_COLLAPSE = 25  # <linux/mman.h>, Linux >= 6.1
_THP = "/sys/kernel/mm/transparent_hugepage/"
_DENSE = 3 / 4  # the resident fraction a chunk needs to be collapsed
_RETRIES = 2  # EAGAIN: the kernel's own selftest retries too


def _thp_setting(name: str) -> str | None:
    try:
        with open(_THP + name, encoding="ascii") as setting:
            return setting.read().strip()
    except OSError:
        return None


@functools.cache
def _system() -> tuple[Any, int] | None:
    """`(libc, huge page bytes)` where `MADV_COLLAPSE` works and THP is not `never`."""
    if not sys.platform.startswith("linux"):
        return None
    enabled, size = _thp_setting("enabled"), _thp_setting("hpage_pmd_size")
    if enabled is None or "[never]" in enabled or size is None:
        return None
    try:
        import ctypes  # noqa: PLC0415 - only in manager processes on Linux

        libc = ctypes.CDLL(None, use_errno=True)
        libc.madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
        libc.mincore.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_char_p]
    except (ImportError, OSError, AttributeError):
        return None
    # a zero-length call checks the advice only: EINVAL where the kernel has no MADV_COLLAPSE
    page = os.sysconf("SC_PAGE_SIZE")
    if libc.madvise(ctypes.c_void_p(page), 0, _MADV_COLLAPSE) != 0:
        return None
    return libc, int(size)


def supported() -> bool:
    """Whether `collapse_dense_memory` can do anything here."""
    return _system() is not None


def _anonymous_chunks(huge: int) -> list[tuple[int, int]]:
    """The huge-page-aligned `(start, end)` parts of the private anonymous rw mappings."""
    spans = []
    with open("/proc/self/maps", "rb") as maps:  # paths need not be ASCII, nor UTF-8
        for line in maps:
            fields = line.split(maxsplit=5)  # range perms offset device inode [path]
            name = fields[5].strip() if len(fields) > 5 else b""
            if fields[1] != b"rw-p" or not (name in (b"", b"[heap]") or name.startswith(b"[anon:")):
                continue
            low, high = (int(address, 16) for address in fields[0].split(b"-"))
            low = -(-low // huge) * huge
            high -= high % huge
            if high > low:
                spans.append((low, high))
    return spans


def collapse_dense_memory() -> int:
    """Collapse this process's dense anonymous chunks into transparent huge pages.

    Runs on the calling thread (each `mincore` and `madvise` releases the GIL). A chunk
    already on a huge page is passed over by the kernel at once, so calling it again is
    cheap.

    Returns:
        The bytes of the chunks that are on huge pages afterwards; 0 where `supported()`
        is false and without `/proc/self/maps`. A chunk the kernel cannot collapse (no
        free huge page, a mapping marked `MADV_NOHUGEPAGE`, pages in use) is left as it
        is. Never raises `OSError`.
    """
    system = _system()
    if system is None:
        return 0
    import ctypes  # noqa: PLC0415 - imported by `_system` already

    libc, huge = system
    try:
        spans = _anonymous_chunks(huge)
    except OSError:
        return 0
    pages = huge // os.sysconf("SC_PAGE_SIZE")
    resident = ctypes.create_string_buffer(pages)
    dense = int(pages * _DENSE)
    collapsed = 0
    for low, high in spans:
        for start in range(low, high, huge):
            if libc.mincore(ctypes.c_void_p(start), huge, resident) != 0:
                break  # unmapped since /proc/self/maps was read
            if pages - resident.raw.count(0) < dense:  # bit 0: resident (others reserved)
                continue
            for _ in range(_RETRIES):
                if libc.madvise(ctypes.c_void_p(start), huge, _MADV_COLLAPSE) == 0:
                    collapsed += huge
                    break
                if ctypes.get_errno() != errno.EAGAIN:
                    break  # EINVAL (say MADV_NOHUGEPAGE), ENOMEM: leave this chunk
    return collapsed


class Collapser:
    """A daemon thread that runs `collapse_dense_memory` when asked and every `interval`.

    One per manager process (`COLLAPSER`). The thread starts at the first `request`, only
    where `supported()`; elsewhere `request` and `wait` return at once. A `request` after
    `close` is never served.

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
            A ticket for `wait`: the pass it names starts after this call (0 where
            nothing can be collapsed: `wait(0)` returns at once).
        """
        if not supported():
            return 0
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
