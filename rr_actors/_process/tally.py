"""A manager process's events that outlive a SIGKILL: a journal, and a count of them.

```
 supervisor's process                         manager process
   Tally.create() ── a file ──────────────►   Journal(path): each event published
                                              appended (pickled) to the file, then its
                                              seq stored as the last one kept
   ... the process exits (or is killed) ...
   tally.after(last seq received) ─────────►  the events it never sent, delivered
   tally.built() - what arrived ───────────►  EventsDropped(lost, cause="killed")
```

A manager process numbers its events (`seq`) and forwards them in batches from a thread
of its own; a SIGKILL (a fault, or the heartbeat killing a hung manager) would lose the
events still in its buffer, and nothing comes after them to show a gap. So the child
appends each event it publishes to a file of its incarnation (one `write` per event, on
the publishing thread), then stores that event's number in the file's first 8 bytes
(one store into a memory map). After the exit the supervisor's side delivers the
journal's events that never arrived, then counts what is still missing (numbered but
not in the journal: cut from it, below, or not picklable) and publishes it as one
`EventsDropped` with the dead process's pid. The file is removed once it was read.

The number is stored after the write, not when the event is built: a kill between the
two (the few microseconds of pickling) would otherwise count as lost an event that the
registrar had not yet published, and so had not yet answered on (a registrar publishes
an event before it answers the call it records). A kill there is a kill just before the
event: the restored catalog (`CatalogRestored`) has what it would have said.

The journal is cut back to nothing after a batch was sent once it holds more than
`JOURNAL_BYTES`: an event published between the batch's start and the cut is then not
in the journal; if the process dies before it sends it, it is counted as lost, not
kept. The file layout: the counter (8 bytes), then one record per event: its number and
the length of its pickle (`_RECORD`: 8 and 4 bytes), then the pickle. The reader skips
the records of events that arrived without unpickling them (a restart's
`CatalogRestored` lists up to 10,000 rows of each kind: unpickling it took 1-5 ms of
each exit, before the supervisor heard of it).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import mmap
import os
import pickle
import struct
import tempfile
from collections.abc import Callable
from typing import Any

__all__ = ["JOURNAL_BYTES", "Journal", "Tally"]

logger = logging.getLogger("rr_actors")

_SIZE = 8  # one unsigned 64-bit counter, in the machine's byte order

_RECORD = struct.Struct("=QI")
"""A journal record's head: the event's number (`seq`, 0 if it has none) and the length
of its pickle in bytes, in the machine's byte order; the pickle follows."""

JOURNAL_BYTES = 1 << 20
"""Past this size (bytes) the journal is cut back after a sent batch (about 5 000 events)."""


class Tally:
    """The shared counter of one manager process's events (one incarnation each).

    Attributes:
        path: the file, to hand to the child (`open`).
    """

    def __init__(self, path: str, fd: int, mapped: mmap.mmap) -> None:
        self.path = path
        self._fd = fd
        self._map: mmap.mmap | None = mapped
        self._view = memoryview(mapped).cast("Q")

    @classmethod
    def create(cls) -> Tally | None:
        """A new counter at 0 (supervisor's side); `None` if no file could be made.

        Without one the manager runs as before: a loss at a kill is then not counted.
        """
        try:
            fd, path = tempfile.mkstemp(prefix="rr-events-")
        except OSError:
            return None
        try:
            os.ftruncate(fd, _SIZE)
            mapped = mmap.mmap(fd, _SIZE)
        except (OSError, ValueError):
            os.close(fd)
            with contextlib.suppress(OSError):
                os.unlink(path)
            return None
        return cls(path, fd, mapped)

    def built(self) -> int:
        """The number of the last event the child kept (0: none, or not read)."""
        if self._map is None:
            return 0
        return int(self._view[0])

    def after(self, seq: int) -> list[Any]:
        """The journal's events numbered above `seq`, in their order (after the exit).

        Only those records are unpickled. A record cut short (the process died within its
        `write`), or one that does not unpickle, ends the reading.
        """
        if self._map is None:
            return []
        found: list[Any] = []
        try:
            with open(self.path, "rb") as file:
                file.seek(_SIZE)
                data = file.read()
        except OSError:
            return []
        at, end = 0, len(data)
        while at + _RECORD.size <= end:
            number, length = _RECORD.unpack_from(data, at)
            at += _RECORD.size
            if at + length > end:
                break  # cut short by the kill
            if number > seq:
                try:
                    found.append(pickle.loads(memoryview(data)[at : at + length]))
                except Exception:  # noqa: BLE001 - not ours to judge: the reading ends
                    break
            at += length
        found.sort(key=lambda e: e.seq)
        return found

    def close(self) -> None:
        """Remove the file and unmap it. Idempotent."""
        if self._map is None:
            return
        self._view.release()
        self._map.close()
        self._map = None
        with contextlib.suppress(OSError):
            os.close(self._fd)
        with contextlib.suppress(OSError):
            os.unlink(self.path)


class Journal:
    """The child's side: events kept as published, the number of the last one kept.

    The number is stored after the event's record was written (a `write` to a file is
    not cut short by a signal), so a SIGKILL between the two leaves a record the count
    does not name yet: `Tally.after` finds it all the same.
    """

    def __init__(self, path: str, mark: Callable[[int], object], fd: int) -> None:
        self.path = path
        self._mark = mark
        self._last = 0
        self._fd = fd
        self._dumps = functools.partial(pickle.dumps, protocol=pickle.HIGHEST_PROTOCOL)
        self._write = os.write

    @classmethod
    def open(cls, path: str) -> Journal | None:
        """Open the file the supervisor's process made; `None` if it cannot be used.

        Without one the events are numbered all the same: a loss then shows only as a
        gap, and not at all at the end of an incarnation.
        """
        try:
            fd = os.open(path, os.O_RDWR | os.O_APPEND)
        except OSError:
            return None
        try:
            mapped = mmap.mmap(fd, _SIZE)
        except (OSError, ValueError):
            os.close(fd)
            return None
        view = memoryview(mapped).cast("Q")
        return cls(path, functools.partial(view.__setitem__, 0), fd)  # one C call per event

    def __call__(self, event: Any) -> bytes | None:
        """Append `event` (a sink of the manager's event hub: the publishing thread).

        Returns:
            Its pickle (what the forwarder may send instead of pickling it again), or
            `None` if it could not be kept.
        """
        seq = getattr(event, "seq", 0)
        data: bytes | None = None
        try:  # per event: a try costs nothing, `suppress` a context manager
            data = self._dumps(event)
            self._write(self._fd, _RECORD.pack(seq, len(data)) + data)  # one write: one record
        except (OSError, pickle.PicklingError, TypeError, AttributeError, struct.error):
            data = None  # not kept: if the process dies before it sends it, it is counted lost
        if seq > self._last:  # (events built on two threads may come out of order)
            self._last = seq
            self._mark(seq)
        return data

    def sent(self) -> None:
        """A batch was sent (the forwarder's thread): cut the journal back if it is big."""
        try:
            if os.fstat(self._fd).st_size > JOURNAL_BYTES:
                os.ftruncate(self._fd, _SIZE)
        except OSError:
            pass
