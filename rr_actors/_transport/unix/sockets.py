"""AF_UNIX sockets with `multiprocessing.connection`'s authkey handshake, bounded in time.

Both sides of a connection get one deadline, `HANDSHAKE_TIMEOUT` seconds, for everything
before the first message: the connect (which waits for room in a full accept backlog) and
every read and write of the handshake. A peer that trickles its handshake a byte at a time
is cut off at the deadline, not kept alive by each byte.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import socket
import struct
import time
from multiprocessing import AuthenticationError
from multiprocessing.connection import Connection, answer_challenge, deliver_challenge

from rr_actors.config import DEFAULT_MAX_MESSAGE_BYTES
from rr_actors.errors import ConfigError, DuplicateNameError

__all__ = [
    "HANDSHAKE_TIMEOUT",
    "connect",
    "handshake",
    "publish_limit",
    "read_limit",
    "shutdown",
    "split",
    "take_name_lock",
]

HANDSHAKE_TIMEOUT = 5.0
"""Seconds a connection gets to connect and pass the authkey handshake (both sides)."""

_HEADER = struct.Struct("!i")  # multiprocessing.connection's frame header
_LONG = struct.Struct("!Q")  # ... after a header of -1


class _Timed:
    """`send_bytes` and `recv_bytes` of `multiprocessing.connection` over `sock`, by `deadline`.

    `deliver_challenge` and `answer_challenge` need only these two methods. Every read
    and write waits at most until `deadline` (`time.monotonic()` seconds), so the whole
    handshake, not each step of it, is bounded.
    """

    __slots__ = ("deadline", "sock")

    def __init__(self, sock: socket.socket, deadline: float) -> None:
        self.sock = sock
        self.deadline = deadline

    def _left(self) -> float:
        left = self.deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("the handshake did not finish in time")
        return left

    def send_bytes(self, data: bytes) -> None:
        self.sock.settimeout(self._left())
        self.sock.sendall(_HEADER.pack(len(data)) + data)  # (one bound for the whole send)

    def recv_bytes(self, maxlength: int | None = None) -> bytes:
        (size,) = _HEADER.unpack(self._recv(_HEADER.size))
        if size == -1:
            (size,) = _LONG.unpack(self._recv(_LONG.size))
        if size < 0 or (maxlength is not None and size > maxlength):
            raise OSError(f"bad message length in the handshake: {size}")
        return self._recv(size)

    def _recv(self, size: int) -> bytes:
        data = b""
        while len(data) < size:
            self.sock.settimeout(self._left())
            chunk = self.sock.recv(size - len(data))
            if not chunk:
                raise EOFError("the connection ended during the handshake")
            data += chunk
        return data


def handshake(sock: socket.socket, authkey: bytes, deadline: float, *, server: bool) -> None:
    """Pass the mutual authkey handshake on `sock`, all of it before `deadline`.

    The listening side delivers its challenge first, the connecting side answers it and
    then delivers its own. `sock` is left blocking (no timeout) afterwards.

    Args:
        sock: a connected stream socket.
        authkey: the system's secret.
        deadline: `time.monotonic()` seconds by which the handshake must be done.
        server: whether this is the listening side.

    Raises:
        AuthenticationError: the other side does not know `authkey`, or sent a malformed
            challenge.
        TimeoutError: it was not done by `deadline`.
        OSError, EOFError: the connection broke or the other side sent garbage.
    """
    timed = _Timed(sock, deadline)
    try:
        if server:
            deliver_challenge(timed, authkey)  # type: ignore[arg-type]
            answer_challenge(timed, authkey)  # type: ignore[arg-type]
        else:
            answer_challenge(timed, authkey)  # type: ignore[arg-type]
            deliver_challenge(timed, authkey)  # type: ignore[arg-type]
    except (AuthenticationError, OSError, EOFError):
        raise
    except Exception as exc:  # a malformed challenge: multiprocessing asserts, or indexes
        raise AuthenticationError(f"malformed handshake: {type(exc).__name__}: {exc}") from exc
    sock.settimeout(None)


def shutdown(sock: socket.socket) -> None:
    """Wake every thread blocked reading or writing `sock` (close alone does not, on Linux)."""
    with contextlib.suppress(OSError):
        sock.shutdown(socket.SHUT_RDWR)


def split(sock: socket.socket) -> tuple[socket.socket, Connection]:
    """`sock` for writing plus a `Connection` on a duplicate descriptor for reading.

    Raises:
        OSError: no descriptor is left for the duplicate (`EMFILE`, `ENFILE`).
    """
    return sock, Connection(os.dup(sock.fileno()))


def _send_timeout(sock: socket.socket, seconds: float) -> None:
    """Bound (or with 0, unbound) blocking sends on `sock`, and so a blocking `connect`."""
    sock.setsockopt(
        socket.SOL_SOCKET,
        socket.SO_SNDTIMEO,
        struct.pack("ll", int(seconds), int((seconds % 1) * 1_000_000)),
    )


def connect(path: str, authkey: bytes) -> tuple[socket.socket, Connection]:
    """Connect to `path` and pass the handshake, both within `HANDSHAKE_TIMEOUT` seconds.

    When the listener's accept backlog is full (many peers connecting at once, or a
    listener that is briefly out of file descriptors), the connect waits in the kernel
    for room until the deadline, rather than failing at once: a blocking AF_UNIX
    `connect` sleeps on the listener's queue, bounded by the socket's send timeout.

    Raises:
        OSError, EOFError: nothing listens there, the backlog stayed full until the
            deadline (`BlockingIOError`), or the connection broke.
        TimeoutError: the handshake did not finish by the deadline.
        AuthenticationError: the listener does not know the system's authkey.
    """
    deadline = time.monotonic() + HANDSHAKE_TIMEOUT
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        _send_timeout(sock, HANDSHAKE_TIMEOUT)
        sock.connect(path)
        _send_timeout(sock, 0)
        handshake(sock, authkey, deadline, server=False)
        return split(sock)
    except BaseException:
        sock.close()
        raise


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


def publish_limit(path: str, limit: int) -> None:
    """Write `limit` (a registrar's `max_message_bytes`) to `path`, atomically.

    Written to a temporary file, then renamed over `path`: a reader sees the old file or
    the new one, never half of one. Called by the listener while it holds the name's
    lock, so no other process writes the same file meanwhile.

    Raises:
        OSError: the file cannot be written.
    """
    folder, name = os.path.split(path)
    temporary = os.path.join(folder, f".{name}")
    fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.write(fd, str(limit).encode("ascii"))
    finally:
        os.close(fd)
    os.replace(temporary, path)


def read_limit(path: str) -> int:
    """The limit published at `path`; `DEFAULT_MAX_MESSAGE_BYTES` if there is none.

    A missing or unreadable file means the registrar is not listening (the connect then
    fails) or was started by an older version: the default is the best guess.
    """
    try:
        with open(path, "rb") as published:
            value = int(published.read(32))
    except (OSError, ValueError):
        return DEFAULT_MAX_MESSAGE_BYTES
    return value if value > 0 else DEFAULT_MAX_MESSAGE_BYTES
