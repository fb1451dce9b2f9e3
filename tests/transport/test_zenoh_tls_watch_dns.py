"""The link watch does not look a `connect` endpoint's host name up at every tick (review
of issue 23): while the endpoint is linked it needs no lookup at all, and a lookup may
block the watch for seconds when the name server cannot be reached (a robot offline)."""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pki
import pytest
import zenoh
from waiting import wait_for

import rr_actors as rr
from rr_actors._transport.zenoh_config import session_config
from rr_actors._transport.zenoh_watch import TICK, LinkWatch

MEMBERS = ["robot", "operator"]


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def _tls(directory: Path, ca: tuple[Path, Path], name: str, addresses: tuple[str, ...]) -> Any:
    cert, key = pki.issue(directory / name, name, addresses, ca=ca)
    return rr.ZenohTLS(ca=ca[0], cert=cert, key=key, members=MEMBERS)


@contextlib.contextmanager
def _session(tls: Any, listen: list[str], connect: list[str]) -> Iterator[zenoh.Session]:
    session = zenoh.open(session_config("router", listen, connect, 1.0, system="lab", tls=tls))
    try:
        yield session
    finally:
        session.close()  # type: ignore[no-untyped-call]


def test_a_linked_endpoint_named_by_a_host_name_is_not_looked_up_at_every_tick(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    ca = pki.make_ca(tmp_path / "lab", "lab")
    robot = _tls(tmp_path, ca, "robot", ("localhost", "127.0.0.1"))
    operator = _tls(tmp_path, ca, "operator", ("127.0.0.1",))
    port = _free_port()
    endpoint = f"tls/localhost:{port}"
    lookups: list[str] = []
    real = socket.getaddrinfo

    def counted(host: Any, *args: Any, **kwargs: Any) -> Any:
        if threading.current_thread().name == "rr-zenoh-watch":
            lookups.append(host)
        return real(host, *args, **kwargs)

    monkeypatch.setattr(socket, "getaddrinfo", counted)
    with (
        _session(robot, [f"tls/127.0.0.1:{port}"], []),
        _session(operator, [], [endpoint]) as session,
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
