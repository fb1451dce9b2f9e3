"""How many events a manager process built: a counter that outlives a SIGKILL.

```
 supervisor's process                         manager process
   Tally.create() ── a file of 8 bytes ──►    Tally.open(path).mark  (each event's seq,
                                              written as it is built: `number_events`)
   ... the process exits (or is killed) ...
   tally.built() - the last seq it received ──► EventsDropped(lost, cause="killed")
```

A manager process numbers its events (`seq`) and forwards them in batches from a thread
of its own; a SIGKILL (a fault, or the heartbeat killing a hung manager) loses the
events still in its buffer, and nothing comes after them to show a gap. The child
writes the number of each event it builds into a small shared file (one store into a
memory map: no system call per event); the supervisor's side reads it after the exit,
so the events lost at the kill are counted, and published as one `EventsDropped` with
the dead process's pid. The file is removed once it was read.
"""

from __future__ import annotations

import contextlib
import functools
import mmap
import os
import tempfile
from collections.abc import Callable

__all__ = ["Tally"]

_SIZE = 8  # one unsigned 64-bit counter, in the machine's byte order


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

    @classmethod
    def open(cls, path: str) -> Callable[[int], object] | None:
        """The child's side: `mark(seq)` stores the number of the last event built.

        Returns:
            The marker for `number_events`, or `None` if the file cannot be mapped (the
            events are numbered all the same: a loss then shows only as a gap).
        """
        try:
            fd = os.open(path, os.O_RDWR)
        except OSError:
            return None
        try:
            mapped = mmap.mmap(fd, _SIZE)
        except (OSError, ValueError):
            return None
        finally:
            os.close(fd)  # the map keeps the file
        view = memoryview(mapped).cast("Q")
        return functools.partial(view.__setitem__, 0)  # one C call per event

    def built(self) -> int:
        """The number of the last event the child built (0: none, or not read)."""
        if self._map is None:
            return 0
        return int(self._view[0])

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
