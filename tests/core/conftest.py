"""The core tests' shared fixtures."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator

import pytest


@pytest.fixture
def gates() -> Iterator[Callable[[], threading.Event]]:
    """Make events that block callbacks; all are set at teardown so no thread stays stuck."""
    made: list[threading.Event] = []

    def make() -> threading.Event:
        made.append(threading.Event())
        return made[-1]

    yield make
    for gate in made:
        gate.set()
