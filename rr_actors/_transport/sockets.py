"""AF_UNIX sockets with `multiprocessing.connection`'s authkey handshake, bounded in time."""

from __future__ import annotations

import contextlib
import fcntl
import os
import socket
import struct
from multiprocessing.connection import Connection, answer_challenge, deliver_challenge

from rr_actors.errors import ConfigError, DuplicateNameError

__all__ = [
    "HANDSHAKE_TIMEOUT",
    "connect",
    "set_io_timeout",
    "shutdown",
    "split",
    "take_name_lock",
]

HANDSHAKE_TIMEOUT = 5.0
"""Seconds a connecting peer gets to connect and pass the authkey handshake (both sides)."""


def set_io_timeout(conn: Connection, seconds: float) -> None:
    """Bound (or with 0, unbound) blocking reads and writes on `conn`'s socket."""
    value = struct.pack("ll", int(seconds), int((seconds % 1) * 1_000_000))
    with socket.socket(fileno=os.dup(conn.fileno())) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, value)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, value)


def shutdown(sock: socket.socket) -> None:
    """Wake every thread blocked reading or writing `sock` (close alone does not, on Linux)."""
    with contextlib.suppress(OSError):
        sock.shutdown(socket.SHUT_RDWR)


def split(sock: socket.socket) -> tuple[socket.socket, Connection]:
    """`sock` for writing plus a `Connection` on a duplicate descriptor for reading."""
    return sock, Connection(os.dup(sock.fileno()))


def connect(path: str, authkey: bytes) -> tuple[socket.socket, Connection]:
    """Connect to `path` and pass the handshake, within `HANDSHAKE_TIMEOUT` seconds each.

    Raises:
        OSError, EOFError: nothing listens there, or the connection broke.
        AuthenticationError: the listener does not know the system's authkey.
    """
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.settimeout(HANDSHAKE_TIMEOUT)
        sock.connect(path)
        sock.settimeout(None)
        sock, conn = split(sock)
    except BaseException:
        sock.close()
        raise
    try:
        set_io_timeout(conn, HANDSHAKE_TIMEOUT)
        answer_challenge(conn, authkey)
        deliver_challenge(conn, authkey)
        set_io_timeout(conn, 0)
    except BaseException:
        conn.close()
        sock.close()
        raise
    return sock, conn


def take_name_lock(path: str, name: str) -> int:
    """Open and `flock` the lock file of registrar `name`; the descriptor holds the lock.

    Raises:
        DuplicateNameError: another process (or listener) holds it.
        ConfigError: the file cannot be opened.
    """
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    except OSError as exc:
        raise ConfigError(f"cannot open the lock file {path!r}: {exc}") from exc
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        os.close(fd)
        raise DuplicateNameError(f"registrar {name!r} is already served on this system") from exc
    return fd
