"""Fixtures of the supervision tests (the suite's own are in `tests/conftest.py`)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

import rr_actors as rr


@pytest.fixture
def log_provider(uid: str) -> Iterator[tuple[rr.ResourceRegistrar, list[str]]]:
    """An unsupervised provider `log-<uid>` whose server "log" records `unload <name>`."""
    events: list[str] = []
    provider = rr.ResourceRegistrar.start(f"log-{uid}")
    provider.register_server(
        "log", load=lambda r: r, unload=lambda r, _: events.append(f"unload {r}")
    )
    yield provider, events
    provider.stop()
