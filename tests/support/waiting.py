"""The tests' one bounded poll, for conditions that other threads or processes make true."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

__all__ = ["wait_for"]


def wait_for(predicate: Callable[[], bool], timeout: float = 5.0) -> bool:
    """Poll `predicate` every 5 ms until it is true (True) or `timeout` seconds passed (False)."""
    deadline = time.monotonic() + timeout
    pause = threading.Event()
    while not predicate():
        if time.monotonic() > deadline:
            return False
        pause.wait(0.005)
    return True
