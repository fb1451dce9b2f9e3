"""What the one-host TLS tests share: a free port, a member's `ZenohTLS`, a TLS router.

`tests/transport/zenoh/ops/test_*.py` make raw Zenoh routers with the very config
`ZenohNetwork` makes (`session_config`), in the test process; the certificates come from
`tests/support/pki.py`.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import zenoh

import rr_actors as rr
from rr_actors._transport.zenoh.ops.config import session_config
from tests.support import pki

MEMBERS = ("robot", "operator")


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


def listener(tls: Any, port: int, system: str = "lab") -> contextlib.AbstractContextManager[Any]:
    """A raw Zenoh router listening on `tls/127.0.0.1:<port>` (`router`); closed on exit."""
    return router(tls, [f"tls/127.0.0.1:{port}"], [], system)


def open_router(tls: Any, connect: list[str], system: str = "lab") -> zenoh.Session:
    """A raw Zenoh router connecting to `connect`, left open (the caller closes it)."""
    return zenoh.open(session_config("router", [], connect, 1.0, system=system, tls=tls))


class Lab:
    """A CA "lab" in a temporary directory, and `ZenohTLS`es of its members on loopback."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.ca = pki.make_ca(directory / "lab", "lab")

    def tls(self, name: str, addresses: tuple[str, ...] = ("127.0.0.1",), **issue: Any) -> Any:
        """`rr.ZenohTLS` of member `name` (one of `MEMBERS`, or added to them); `issue`:
        `pki.issue`'s options (`ca=` another CA's)."""
        ca = issue.pop("ca", self.ca)
        where = self.directory / uuid.uuid4().hex[:8]
        cert, key = pki.issue(where, name, addresses, ca=ca, **issue)
        members = [*MEMBERS, name] if name not in MEMBERS else list(MEMBERS)
        return rr.ZenohTLS(ca=ca[0], cert=cert, key=key, members=members)


class Logged(logging.Handler):
    """The `rr_actors` log lines, and a wait for one containing a text (`caught_log`)."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.lines: list[tuple[str, str]] = []
        self.changed = threading.Condition()

    def emit(self, record: logging.LogRecord) -> None:
        with self.changed:
            self.lines.append((record.levelname, record.getMessage()))
            self.changed.notify_all()

    def wait(self, level: str, text: str, timeout: float) -> str:
        """The first line at `level` containing `text`, waited for up to `timeout` s."""

        def found() -> str | None:
            return next((m for lv, m in self.lines if lv == level and text in m), None)

        with self.changed:
            self.changed.wait_for(found, timeout=timeout)
            line = found()
        assert line is not None, f"no {level} with {text!r} within {timeout} s: {self.lines}"
        return line


@contextlib.contextmanager
def caught_log() -> Iterator[Logged]:
    """`rr_actors`' log at INFO, caught (`Logged`) for the block."""
    handler = Logged()
    log = logging.getLogger("rr_actors")
    level = log.level
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    try:
        yield handler
    finally:
        log.removeHandler(handler)
        log.setLevel(level)
