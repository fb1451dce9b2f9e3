"""A manager process's events that outlive a SIGKILL: its journal, and what the parent
received of them and lost.

```
 supervisor's process                         manager process
   Tally.create() ── a file ──────────────►   Journal(path): each event published
                                              appended (pickled, one write); one it could
                                              not keep raises the doubt mark
   Received.deliver ◄── Events(batch) over the control pipe
   ... the process exits (or is killed) ...
   Received.drain: what is still in the pipe
   Received.count_lost: the journal's records not received (above the last number
     received, or a hole below it), then the backup's outbox (`_store/outbox.py`: events
     committed, then killed before their publishing); of the numbers still missing,
     those at or below the doubt mark ──► one EventsDropped(cause="killed"),
     the others (never published) ──► one EventsUnpublished(seqs)
```

Why: "What a SIGKILL can and cannot lose of the event stream", failure-semantics.md. The
journal's write publishes an event for good: a kill before it is a kill before the event,
whose number no event takes. Past `JOURNAL_BYTES` the journal is cut back after a sent
batch; the doubt mark rises to the last number written then (an event published meanwhile
and never sent counts lost), as for an event not written. Layout: the 8-byte doubt mark,
then per event a `_RECORD` head (seq, pickle length) and the pickle.
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
from multiprocessing.connection import Connection
from typing import Any

from rr_actors._core import runtime
from rr_actors._process.control import Events
from rr_actors._store.outbox import read_told
from rr_actors.events import EventsDropped, EventsUnpublished

logger = logging.getLogger("rr_actors")

_SIZE = 8  # the doubt mark: one unsigned 64-bit number, in the machine's byte order

_RECORD = struct.Struct("=QI")  # a record's head: the event's seq, its pickle's length

JOURNAL_BYTES = 1 << 20
"""Past this size (bytes) the journal is cut back after a sent batch (about 5 000 events)."""


class Tally:
    """The journal of one manager process's events (one incarnation each), read back."""

    def __init__(self, path: str, fd: int, mapped: mmap.mmap) -> None:
        self.path = path
        self._fd = fd
        self._map: mmap.mmap | None = mapped
        self._view = memoryview(mapped).cast("Q")

    @classmethod
    def create(cls) -> Tally | None:
        """A new journal (supervisor's side); `None` if no file could be made (a loss at a
        kill is then not counted)."""
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

    def doubted(self) -> int:
        """The highest number of an event the journal may lack though it was published (cut
        from it, or not written); 0: none, or not read."""
        if self._map is None:
            return 0
        return int(self._view[0])

    def kept(self, arrived: int, holes: set[int] | frozenset[int] = frozenset()) -> list[Any]:
        """The journal's events numbered above `arrived` or in `holes`, in order (a record
        cut short, or one that does not unpickle, ends the reading)."""
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
            if number > arrived or number in holes:
                try:
                    found.append(pickle.loads(memoryview(data)[at : at + length]))
                except Exception:  # noqa: BLE001 - not ours to judge: the reading ends
                    break
            at += length
        found.sort(key=_seq)
        return found

    def close(self) -> None:
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
    """The child's side: each event published, appended."""

    def __init__(self, path: str, doubt: Callable[[int], object], fd: int) -> None:
        self.path, self._fd, self._doubt = path, fd, doubt
        self._last = self._doubted = 0  # the highest number written; the doubt mark
        self._lock = runtime.Lock()  # a write and its number, or a cut: one at a time
        self._dumps = functools.partial(pickle.dumps, protocol=pickle.HIGHEST_PROTOCOL)
        self._write = os.write

    @classmethod
    def open(cls, path: str) -> Journal | None:
        """Open the file the supervisor's process made; `None` if it cannot be used."""
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
        return cls(path, functools.partial(view.__setitem__, 0), fd)

    def __call__(self, event: Any) -> bytes | None:
        """Append `event` (the publishing thread); its pickle, or `None` if not kept (then
        lost if it is never sent: the doubt mark rises to its number)."""
        seq = getattr(event, "seq", 0)
        try:  # per event: a try costs nothing, `suppress` a context manager
            data: bytes = self._dumps(event)
            with self._lock:  # (a cut between the write and `_last` would go uncounted)
                self._write(self._fd, _RECORD.pack(seq, len(data)) + data)  # one record
                self._last = max(self._last, seq)  # (two threads' events: out of order)
        except (OSError, pickle.PicklingError, TypeError, AttributeError, struct.error):
            with self._lock:
                self._doubt_up_to(seq)
            return None
        return data

    def _doubt_up_to(self, seq: int) -> None:
        if seq > self._doubted:
            self._doubted = seq
            self._doubt(seq)

    def sent(self) -> None:
        """A batch was sent (the forwarder's thread): past `JOURNAL_BYTES`, cut the journal
        back; what it held and was not sent yet is then in doubt."""
        try:
            if os.fstat(self._fd).st_size <= JOURNAL_BYTES:
                return
            with self._lock:
                self._doubt_up_to(self._last)  # (before the cut: a kill between is counted)
                os.ftruncate(self._fd, _SIZE)
        except OSError:
            pass


HOLES = 4096
"""Missing numbers below the last one that arrived, kept at most (events built on two
threads may be sent out of order)."""


class Received:
    """The events one manager process forwarded, to `on_events`; and those it lost.

    `tally`: its journal (`None`: none); `backup`: its registrar's backup file, absolute.
    """

    def __init__(
        self,
        on_events: Callable[[list[Any]], None] | None,
        tally: Tally | None,
        backup: str | None = None,
    ) -> None:
        self.on_events = on_events
        self.tally = tally
        self.backup = backup
        self.last_seq = 0
        self.holes: set[int] = set()

    def deliver(self, name: str, batch: list[Any]) -> None:
        if self.on_events is None:
            return
        last, holes = self.last_seq, self.holes
        for event in batch:
            seq = _seq(event)
            if seq > last:
                if seq > last + 1 and len(holes) < HOLES:
                    holes.update(range(last + 1, min(seq, last + 1 + HOLES - len(holes))))
                last = seq
            elif seq:
                holes.discard(seq)
        self.last_seq = last
        try:
            self.on_events(batch)
        except Exception:
            logger.exception("events of manager %s could not be delivered", name)

    def drain(self, name: str, conn: Connection) -> None:
        """Read what the process sent before it ended (still in the pipe)."""
        for _ in range(10_000):  # bounded: the pipe holds what a dead process wrote
            try:
                if not conn.poll(0):
                    return
                message = conn.recv()
            except (EOFError, OSError, ValueError):
                return
            if isinstance(message, Events):
                self.deliver(name, message.batch)

    def close(self) -> None:
        tally, self.tally = self.tally, None
        if tally is not None:
            tally.close()

    def count_lost(self, name: str, pid: int, *, listened: bool = True) -> None:
        """After the exit: deliver what its journal and outbox kept but it never sent, then
        tell the numbers still missing (before a restart empties the outbox); nothing is
        read if nobody `listened` (a later subscriber hears nothing older than itself)."""
        tally = self.tally
        if tally is None or self.on_events is None or not listened:
            self.close()
            return
        self.tally = None
        arrived, holes = self.last_seq, self.holes
        try:
            kept = tally.kept(arrived, holes)
            doubt = tally.doubted()
        finally:
            tally.close()
        seen = {_seq(e) for e in kept}
        told = [
            event
            for event in (read_told(self.backup, pid) if self.backup is not None else ())
            if (_seq(event) > arrived or _seq(event) in holes) and _seq(event) not in seen
        ]
        if told:  # committed, then killed before their publishing: the journal lacks them
            kept = sorted([*kept, *told], key=_seq)
            seen.update(_seq(e) for e in told)
        if kept:
            self.deliver(name, kept)
        top = max(arrived, doubt, *seen)
        missing = {*range(arrived + 1, top + 1), *holes} - seen
        lost = sum(1 for seq in missing if seq <= doubt)
        if lost:
            logger.warning("manager %s (pid %d) died with %d events unsent", name, pid, lost)
            self.deliver(name, [EventsDropped(lost, pid=pid, cause="killed")])
        if len(missing) > lost:  # (numbers taken by events a kill came before)
            unused = tuple(sorted(seq for seq in missing if seq > doubt))
            self.deliver(name, [EventsUnpublished(unused, pid=pid)])


def _seq(event: Any) -> int:
    seq: int = getattr(event, "seq", 0)
    return seq
