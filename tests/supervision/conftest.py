"""Fixtures of the supervision tests (the shared ones are in tests/conftest.py)."""

from __future__ import annotations

import asyncio
from typing import Any, Protocol

import pytest

import rr_actors as rr


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
