"""A manager process keeps its dense memory on huge pages (`rr_actors._memory`).

The kernel frees a killed process's memory before its supervisor can see it exit; on
2 MiB pages that is faster (docs/performance.md, "Where detection goes"). These tests
read the kernel's own account (`/proc/<pid>/smaps`) of where the pages are.
"""

from __future__ import annotations

import ctypes
import logging
import mmap
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from supervision import process

import rr_actors as rr
from rr_actors import _memory
from rr_actors._memory import Collapser, collapse_dense_memory


def _huge_pages_by_request() -> bool:
    """`MADV_COLLAPSE` works here, and THP comes on request only (`[madvise]`)."""
    try:
        enabled = Path("/sys/kernel/mm/transparent_hugepage/enabled").read_text()
    except OSError:
        return False
    return _memory.supported() and "[madvise]" in enabled


collapsing = pytest.mark.skipif(
    not _huge_pages_by_request(),
    reason="needs Linux >= 6.1 with transparent huge pages set to `madvise`",
)

_SIZE = 8 << 20
_PAGE = mmap.PAGESIZE
_PROT_NONE = 0
_libc = ctypes.CDLL(None, use_errno=True)
_libc.mprotect.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]


def _mapping(resident_every: int) -> mmap.mmap:
    """8 MiB of private anonymous memory, every `resident_every`-th page touched.

    Between two inaccessible guard pages, so that the kernel cannot merge it with a
    neighbouring mapping (whose pages would then count in its `smaps` entry).
    """
    buffer = mmap.mmap(-1, _SIZE + 2 * _PAGE, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    start = ctypes.addressof(ctypes.c_char.from_buffer(buffer))
    for guard in (start, start + _PAGE + _SIZE):
        assert _libc.mprotect(guard, _PAGE, _PROT_NONE) == 0, ctypes.get_errno()
    for offset in range(_PAGE, _PAGE + _SIZE, _PAGE * resident_every):
        buffer[offset] = 1
    return buffer


def _address(buffer: mmap.mmap) -> int:
    """Where the usable part of a `_mapping` starts."""
    return ctypes.addressof(ctypes.c_char.from_buffer(buffer)) + _PAGE


def _smaps_of(address: int, pid: int | str = "self") -> dict[str, int]:
    """The kB fields of the mapping that holds `address` (`Rss`, `AnonHugePages`, ...)."""
    fields: dict[str, int] = {}
    inside = False
    with open(f"/proc/{pid}/smaps", encoding="ascii") as smaps:
        for line in smaps:
            head = line.split()
            if "-" in head[0] and not head[0].endswith(":"):
                low, high = (int(bound, 16) for bound in head[0].split("-"))
                if inside:
                    break
                inside = low <= address < high
            elif inside and head[-1] == "kB":
                fields[head[0].rstrip(":")] = int(head[1])
    assert fields, f"no mapping holds {address:#x}"
    return fields


@collapsing
def test_dense_chunks_go_onto_huge_pages_and_sparse_ones_stay() -> None:
    dense, sparse = _mapping(resident_every=1), _mapping(resident_every=4)
    try:
        sparse_before = _smaps_of(_address(sparse))["Rss"]
        collapse_dense_memory()
        dense_after = _smaps_of(_address(dense))
        sparse_after = _smaps_of(_address(sparse))
    finally:
        dense.close()
        sparse.close()
    # 8 MiB not aligned to 2 MiB holds at least three aligned chunks
    assert dense_after["AnonHugePages"] >= 3 * 2048, dense_after
    assert sparse_after["AnonHugePages"] == 0, sparse_after
    assert sparse_after["Rss"] == sparse_before, "a quarter-resident chunk was filled up"


@collapsing
def test_a_chunk_the_kernel_refuses_does_not_end_the_pass() -> None:
    # the refused mapping is made second: it lies below the first, and is visited first
    dense = _mapping(resident_every=1)
    refused = _mapping(resident_every=1)
    try:
        madvise = ctypes.CDLL(None).madvise
        madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
        assert madvise(_address(refused), _SIZE, 15) == 0  # MADV_NOHUGEPAGE: EINVAL later
        assert _address(refused) < _address(dense)
        collapse_dense_memory()
        assert _smaps_of(_address(refused))["AnonHugePages"] == 0
        assert _smaps_of(_address(dense))["AnonHugePages"] >= 3 * 2048
    finally:
        dense.close()
        refused.close()


def test_nothing_is_collapsed_where_thp_is_never_or_unsupported(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    for enabled, advice in (("always madvise [never]", 25), ("[madvise] never", 0x7FFF)):
        monkeypatch.setattr(_memory, "_MADV_COLLAPSE", advice)  # 0x7FFF: as on Linux < 6.1
        monkeypatch.setattr(
            _memory, "_thp_setting", lambda name, e=enabled: e if name == "enabled" else "2097152"
        )
        _memory._system.cache_clear()
        try:
            dense = _mapping(resident_every=1)
            try:
                assert not _memory.supported()
                assert collapse_dense_memory() == 0
                assert _smaps_of(_address(dense))["AnonHugePages"] == 0
                ticker = Collapser()
                assert ticker.request() == 0
                assert ticker.wait(0, timeout=0.0)
                assert not any(t.name == "rr-memory-collapse" for t in threading.enumerate())
            finally:
                dense.close()
        finally:
            _memory._system.cache_clear()


@pytest.fixture
def collapser() -> Iterator[Callable[..., Collapser]]:
    made: list[Collapser] = []

    def make(**kwargs: Any) -> Collapser:
        made.append(Collapser(**kwargs))
        return made[-1]

    yield make
    for one in made:
        one.close()


@collapsing
def test_the_collapser_passes_when_asked(collapser: Callable[..., Collapser]) -> None:
    ticker = collapser(interval=60.0)
    dense = _mapping(resident_every=1)
    try:
        assert ticker.wait(ticker.request(), timeout=10.0)
        assert _smaps_of(_address(dense))["AnonHugePages"] >= 3 * 2048
    finally:
        dense.close()


def test_the_collapser_also_passes_periodically(
    collapser: Callable[..., Collapser], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(_memory, "supported", lambda: True)
    monkeypatch.setattr(_memory, "collapse_dense_memory", lambda: 0)
    ticker = collapser(interval=0.01)
    assert ticker.wait(ticker.request(), timeout=10.0)
    assert ticker.wait_for_passes(ticker.passes + 3, timeout=10.0), "no periodic pass"


def test_a_failing_pass_is_logged_and_the_collapser_goes_on(
    collapser: Callable[..., Collapser],
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    failures = iter([RuntimeError("no /proc here")])

    def collapse() -> int:
        for failure in failures:
            raise failure
        return 0

    monkeypatch.setattr(_memory, "supported", lambda: True)
    monkeypatch.setattr(_memory, "collapse_dense_memory", collapse)
    ticker = collapser(interval=60.0)
    with caplog.at_level(logging.ERROR, logger="rr_actors"):
        assert ticker.wait(ticker.request(), timeout=10.0)
        assert ticker.wait(ticker.request(), timeout=10.0)
    assert ticker.passes == 2
    assert "collapsing memory into huge pages failed" in caplog.text


def test_closing_the_collapser_ends_its_thread(
    collapser: Callable[..., Collapser], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(_memory, "supported", lambda: True)
    ticker = collapser(interval=60.0)
    assert ticker.wait(ticker.request(), timeout=10.0)
    ticker.close()
    assert not any(t.name == "rr-memory-collapse" for t in threading.enumerate())


def _dense_setup(registrar: rr.ResourceRegistrar) -> None:
    """Setup of a manager that holds 8 MiB of dense memory."""
    registrar.dense_buffer = _mapping(resident_every=1)  # type: ignore[attr-defined]


def _after_the_ready_pass(registrar: rr.ResourceRegistrar) -> tuple[int, int]:
    """In the manager: wait for the pass it asked for before ready; huge kB, Rss kB."""
    from rr_actors._memory import COLLAPSER  # noqa: PLC0415 - the manager's own

    assert COLLAPSER.wait(COLLAPSER._requested, timeout=10.0)  # not a pass of our own
    fields = _smaps_of(_address(registrar.dense_buffer))  # type: ignore[attr-defined]
    return fields["AnonHugePages"], fields["Rss"]


@collapsing
@pytest.mark.usefixtures("process_helpers")  # the forkserver: not this test's leftover
def test_a_manager_process_moves_what_setup_allocated_onto_huge_pages(
    supervisors: Callable[..., rr.Supervisor], uid: str, tmp_path: Path
) -> None:
    name = f"dense-{uid}"
    sup = supervisors([process(name, _dense_setup)], state_dir=tmp_path)
    sup.start()

    huge, rss = sup.run_in(name, _after_the_ready_pass, timeout=20.0)

    assert huge >= 3 * 2048, (huge, rss)
