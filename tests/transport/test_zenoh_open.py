"""How long opening a Zenoh router takes, and what it waits for.

Zenoh's open of a router session waits its scouting `delay` (500 ms) for links to other
routers: the ones it connects to, and the ones that connect to its TCP `listen` endpoints
(a router of another host that retries every 250 ms-1 s gets in meanwhile). With neither
(one host alone, scouting off) nothing can come up, so `ZenohNetwork` sets the delay to 0:
such a router (every test of the zenoh placement opens one) is open at once. With a
`connect` or TCP `listen` endpoint the wait stays: the link to the other router is up when
the open returns, so a name served right away is checked against that host too.
"""

from __future__ import annotations

import socket
import time
import uuid

import zenoh

import rr_actors as rr
from rr_actors._transport.zenoh.ops.config import session_config

SCOUTING_DELAY = 0.5  # seconds: Zenoh's default `scouting/delay`


def test_a_router_without_connect_endpoints_opens_without_the_scouting_wait():
    network = rr.ZenohNetwork(system=f"open-{uuid.uuid4().hex[:8]}", tls=None)
    try:
        began = time.monotonic()
        assert network.address.socket_path  # opens the router session
        assert time.monotonic() - began < SCOUTING_DELAY / 2
    finally:
        network.close()


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def test_a_router_with_a_connect_endpoint_is_linked_when_its_open_returns():
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    listening = zenoh.open(session_config("router", [endpoint], [], 1.0))
    try:
        connecting = zenoh.open(session_config("router", [], [endpoint], 1.0))
        try:
            assert [listening.zid()] == list(connecting.info.routers_zid())
        finally:
            connecting.close()  # type: ignore[no-untyped-call]
    finally:
        listening.close()  # type: ignore[no-untyped-call]
