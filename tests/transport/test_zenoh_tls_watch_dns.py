"""The link watch does not look a `connect` endpoint's host name up at every tick (review
of issue 23): while the endpoint is linked it needs no lookup at all, and a lookup may
block the watch for seconds when the name server cannot be reached (a robot offline)."""

from __future__ import annotations

import socket
import threading
from pathlib import Path
from typing import Any

import pki
import pytest
from tls_lab import free_port, member_tls, router
from waiting import wait_for

from rr_actors._transport.zenoh.watch import TICK, LinkWatch


def test_a_linked_endpoint_named_by_a_host_name_is_not_looked_up_at_every_tick(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    ca = pki.make_ca(tmp_path / "lab", "lab")
    robot = member_tls(tmp_path, ca, "robot", ("localhost", "127.0.0.1"))
    operator = member_tls(tmp_path, ca, "operator", ("127.0.0.1",))
    port = free_port()
    endpoint = f"tls/localhost:{port}"
    lookups: list[str] = []
    real = socket.getaddrinfo

    def counted(host: Any, *args: Any, **kwargs: Any) -> Any:
        if threading.current_thread().name == "rr-zenoh-watch":
            lookups.append(host)
        return real(host, *args, **kwargs)

    monkeypatch.setattr(socket, "getaddrinfo", counted)
    with (
        router(robot, [f"tls/127.0.0.1:{port}"], []),
        router(operator, [], [endpoint]) as session,
    ):
        watch = LinkWatch("lab", session, operator, (endpoint,))
        try:
            assert wait_for(lambda: len(session.info.links()) == 1, timeout=10)
            assert wait_for(lambda: "localhost" in lookups, timeout=10)
            before = len(lookups)
            threading.Event().wait(8 * TICK)  # eight looks at the linked endpoint
            assert 0 == len(lookups) - before
        finally:
            watch.close()
