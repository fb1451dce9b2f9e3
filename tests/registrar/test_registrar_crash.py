"""A registrar that crashes fails the requests it had accepted at once (rule 17)."""

from __future__ import annotations

import threading
import time
import uuid
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.testing import crash


def _name(prefix: str) -> str:
    return f"{prefix}-{uuid.uuid4().hex[:8]}"


def test_an_unload_waiting_on_its_provider_fails_at_once_when_the_consumer_crashes() -> None:
    unloading = threading.Event()
    release = threading.Event()

    def unload(request: Any, response: Any) -> None:
        unloading.set()
        assert release.wait(10)

    provider = rr.ResourceRegistrar.start(_name("erm"))
    consumer = rr.ResourceRegistrar.start(_name("app"))
    outcome: list[BaseException] = []
    try:
        provider.register_server("camera", load=lambda r: r, unload=unload)
        query = consumer.call(provider.name, "camera", 1, timeout=5)
        waiting = threading.Thread(
            target=lambda: _record(outcome, lambda: consumer.unload(query.id, timeout=30))
        )
        waiting.start()
        assert unloading.wait(5)
        started = time.monotonic()
        crash(consumer)
        waiting.join(5)
        elapsed = time.monotonic() - started

        assert [rr.RegistrarUnavailableError] == [type(e) for e in outcome]
        assert elapsed < 5.0  # at once, not after the 30 s timeout
    finally:
        release.set()
        provider.stop()


def _record(outcome: list[BaseException], fn: Any) -> None:
    try:
        fn()
    except BaseException as exc:  # the test inspects what was raised
        outcome.append(exc)


def test_a_request_to_a_crashed_registrar_names_it_unavailable() -> None:
    registrar = rr.ResourceRegistrar.start(_name("erm"))
    crash(registrar)

    with pytest.raises(rr.RegistrarUnavailableError, match=registrar.name):
        registrar.server_queries("camera")
