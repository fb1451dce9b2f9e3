"""One thread per ordered stream of items: the Zenoh carrier's writers and decoders.

```
 put(item) ─► deque ─► its thread (started at the first item) ─► handle(item)
```

Zenoh's callbacks never block and never handle an item themselves: they queue (`put`).
"""

from __future__ import annotations

import collections
import logging
import threading
from collections.abc import Callable
from typing import Any

__all__ = ["Queue"]

logger = logging.getLogger("rr_actors")


class Queue:
    """Items handled one at a time in order, by its thread (started at the first item)."""

    def __init__(self, name: str, handle: Callable[[Any], None]) -> None:
        self._name = name
        self._handle = handle
        self._cond = threading.Condition(threading.Lock())
        self._items: collections.deque[Any] = collections.deque()
        self._started = False
        self.closed = False

    def put(self, item: Any) -> bool:
        """Queue `item` for the thread; False if the queue is closed."""
        with self._cond:
            if self.closed:
                return False
            self._items.append(item)
            if not self._started:
                self._started = True
                threading.Thread(target=self._run, name=self._name, daemon=True).start()
            else:
                self._cond.notify()
            return True

    def finish(self) -> None:
        """Take no more items; the thread handles those queued, then ends."""
        with self._cond:
            self.closed = True
            self._cond.notify_all()

    def close(self) -> list[Any]:
        """Stop; the items not yet handled are returned."""
        with self._cond:
            self.closed = True
            left = list(self._items)
            self._items.clear()
            self._cond.notify_all()
            return left

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._items and not self.closed:
                    self._cond.wait()
                if not self._items:
                    return
                item = self._items.popleft()
            try:
                self._handle(item)
            except Exception:
                logger.exception("%s: handling an item failed", self._name)
