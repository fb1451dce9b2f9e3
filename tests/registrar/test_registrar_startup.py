"""A manager's start-up: `ResourceRegistrar.start(config, setup=...)` serves only after setup."""

from __future__ import annotations

import threading
import time
import uuid
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.testing import pending_work


def _held_loads(name: str) -> int:
    """How many loads the starting registrar `name` holds (asked in its actor thread)."""
    return len(pending_work(name).held_loads)


def _wait_held(name: str, count: int, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:  # each round is a round trip to the actor
        if _held_loads(name) >= count:
            return True
    return False


def _name(prefix: str) -> str:
    return f"{prefix}-{uuid.uuid4().hex[:8]}"


def test_a_load_arriving_during_setup_waits_for_the_server_setup_registers() -> None:
    provider_name = _name("erm")
    setup_started = threading.Event()
    finish_setup = threading.Event()
    answers: list[Any] = []

    def setup(registrar: rr.ResourceRegistrar) -> None:
        setup_started.set()
        assert finish_setup.wait(5)
        registrar.register_server("camera", load=lambda r: f"cam:{r}", unload=lambda r, s: None)

    consumer = rr.ResourceRegistrar.start(_name("app"))
    starter = threading.Thread(
        target=lambda: answers.append(rr.ResourceRegistrar.start(provider_name, setup=setup))
    )
    starter.start()
    try:
        assert setup_started.wait(5)
        calling = threading.Thread(
            target=lambda: answers.append(consumer.call(provider_name, "camera", 1, timeout=5))
        )
        calling.start()
        assert _wait_held(provider_name, 1)  # it arrived before the server exists
        finish_setup.set()
        calling.join(5)
        starter.join(5)

        query = next(a for a in answers if isinstance(a, rr.Query))
        assert "cam:1" == query.response
    finally:
        finish_setup.set()
        starter.join(5)
        consumer.stop()
        for answer in answers:
            if isinstance(answer, rr.ResourceRegistrar):
                answer.stop()


def test_after_setup_a_server_it_did_not_register_is_unknown() -> None:
    provider = rr.ResourceRegistrar.start(_name("erm"), setup=lambda registrar: None)
    consumer = rr.ResourceRegistrar.start(_name("app"))
    try:
        with pytest.raises(rr.UnknownServerError):
            consumer.call(provider.name, "camera", 1, timeout=5)
    finally:
        consumer.stop()
        provider.stop()


def test_a_setup_that_raises_stops_the_registrar_and_frees_its_name() -> None:
    name = _name("erm")

    def setup(registrar: rr.ResourceRegistrar) -> None:
        raise RuntimeError("no camera attached")

    with pytest.raises(RuntimeError, match="no camera attached"):
        rr.ResourceRegistrar.start(name, setup=setup)

    again = rr.ResourceRegistrar.start(name)
    again.stop()
