"""`ZenohNetwork.wait_for` and `subscribe_events` given what they cannot use.

A name no registrar can have (`None`, `5`, a key expression such as `"*"`) is a
`ConfigError` at once, not a wait of the whole timeout that ends saying the registrar was
not served; a callback that is not callable is refused before the session opens, not
logged as a `TypeError` for every event.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator

import pytest

import rr_actors as rr
from tests.support.tls_lab import free_port

pytest.importorskip("zenoh")


@pytest.fixture
def net() -> Iterator[rr.ZenohNetwork]:
    """A plain-TCP network on loopback, not opened yet."""
    system = f"bad-args-{uuid.uuid4().hex[:8]}"
    made = rr.ZenohNetwork(system=system, listen=[f"tcp/127.0.0.1:{free_port()}"], tls=None)
    try:
        yield made
    finally:
        made.close()


@pytest.mark.parametrize("name", [None, 5, "*", "a/**", ""])
def test_wait_for_a_name_no_registrar_can_have_is_a_config_error_naming_it(
    net: rr.ZenohNetwork, name: object
) -> None:
    with pytest.raises(rr.ConfigError, match="not a registrar name"):
        net.wait_for(name, timeout=5)  # type: ignore[arg-type]


def test_subscribe_events_with_a_callback_that_is_not_callable_is_a_config_error(
    net: rr.ZenohNetwork,
) -> None:
    with pytest.raises(rr.ConfigError, match="callback"):
        net.subscribe_events("print")  # type: ignore[arg-type]
