"""What the one-host TLS tests share: a free port, a member's `ZenohTLS`, a TLS router.

`tests/transport/zenoh/ops/test_*.py` make raw Zenoh routers with the very config
`ZenohNetwork` makes (`session_config`), in the test process; the certificates come from
`tests/support/pki.py`.
"""

from __future__ import annotations

import contextlib
import socket
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import zenoh

import rr_actors as rr
from rr_actors._transport.zenoh.ops.config import session_config
from tests.support import pki

MEMBERS = ("robot", "operator")


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nobody listened on a moment ago."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def member_tls(
    directory: Path,
    ca: tuple[Path, Path],
    name: str,
    addresses: tuple[str, ...] = ("127.0.0.1",),
    members: Iterable[str] = MEMBERS,
) -> Any:
    """`rr.ZenohTLS` of member `name`: a certificate of `ca` naming `addresses`."""
    cert, key = pki.issue(directory / name, name, addresses, ca=ca)
    return rr.ZenohTLS(ca=ca[0], cert=cert, key=key, members=list(members))


@contextlib.contextmanager
def router(
    tls: Any, listen: list[str], connect: list[str], system: str = "lab"
) -> Iterator[zenoh.Session]:
    """A raw Zenoh router with `ZenohNetwork`'s TLS config; closed on exit."""
    session = zenoh.open(session_config("router", listen, connect, 1.0, system=system, tls=tls))
    try:
        yield session
    finally:
        session.close()  # type: ignore[no-untyped-call]
