"""Fixtures of the supervision tests (the suite's own are in `tests/conftest.py`)."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from typing import Any, Protocol

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


class CallWithRetry(Protocol):
    def __call__(self, sup: rr.Supervisor, *args: Any, **kwargs: Any) -> rr.Query: ...


def _blocking(sup: rr.Supervisor, *args: Any, **kwargs: Any) -> rr.Query:
    return sup.call_with_retry(*args, **kwargs)


def _awaited(sup: rr.Supervisor, *args: Any, **kwargs: Any) -> rr.Query:
    return asyncio.run(sup.acall_with_retry(*args, **kwargs))


@pytest.fixture(params=[_blocking, _awaited], ids=["blocking", "awaited"])
def call_with_retry(request: pytest.FixtureRequest) -> CallWithRetry:
    """`call_with_retry(sup, consumer, target_rr, server, request, **kwargs)`: the
    supervisor's `call_with_retry`, or its twin awaited on an event loop of the calling
    thread (`asyncio.run(sup.acall_with_retry(...))`): the retry's tests, the same
    bodies, run against both (ids "blocking" and "awaited")."""
    call: CallWithRetry = request.param
    return call
