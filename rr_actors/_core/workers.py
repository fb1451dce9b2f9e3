"""An elastic pool of daemon threads that runs user callbacks off the actors' mailboxes.

A task never waits for a busy worker: when no worker is idle a new one starts, so a
callback that blocks (on a nested `call`, a `send_status`, or forever) cannot starve
another. Idle workers exit after `idle_timeout` seconds.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable

__all__ = ["Workers"]

logger = logging.getLogger("rr_actors")


class Workers:
    """Run zero-argument callables on reused or fresh daemon threads."""

    def __init__(self, name: str, *, idle_timeout: float = 10.0) -> None:
        self._name = name
        self._idle_timeout = idle_timeout
        self._lock = threading.Lock()
        self._tasks: queue.SimpleQueue[Callable[[], None]] = queue.SimpleQueue()
        self._idle = 0  # workers waiting for a task, minus tasks queued for them
        self._count = 0

    def submit(self, task: Callable[[], None]) -> None:
        """Run `task` soon on a worker thread; its exceptions are logged, never raised."""
        with self._lock:
            if self._idle > 0:
                self._idle -= 1
                self._tasks.put(task)
                return
            self._count += 1
            number = self._count
        threading.Thread(
            target=self._run, args=(task,), name=f"rr-{self._name}-worker-{number}", daemon=True
        ).start()

    def _run(self, task: Callable[[], None]) -> None:
        while True:
            try:
                task()
            except BaseException:  # a worker must survive anything a task does
                logger.exception("uncaught exception in an rr_actors worker task")
            with self._lock:
                self._idle += 1
            while True:
                try:
                    task = self._tasks.get(timeout=self._idle_timeout)
                    break
                except queue.Empty:
                    with self._lock:
                        if self._idle > 0:  # nobody counts on this worker: leave
                            self._idle -= 1
                            return
