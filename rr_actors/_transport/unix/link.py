"""The AF_UNIX link: one connection per pair of processes and registrar, both ways.

Frames are `codec`'s, after an authkey handshake; a sender never blocks on the other
process. How and why: docs/explanation/inside.md ("The AF_UNIX link").
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import functools
import logging
import math
import os
import socket
import struct
import threading
import time
from collections.abc import Callable
from multiprocessing import AuthenticationError
from multiprocessing.connection import Connection, answer_challenge, deliver_challenge
from typing import Protocol

from rr_actors._core.serial import SerialExecutor, Task
from rr_actors._platform.base import bound_reached, no_thread
from rr_actors._transport.codec import Oversized, frames, unframe
from rr_actors._transport.messenger import (
    Endpoint,
    Listening,
    Lost,
    Messenger,
    Route,
    run_lost,
)
from rr_actors.config import DEFAULT_MAX_MESSAGE_BYTES
from rr_actors.errors import (
    ConfigError,
    DuplicateNameError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    RrError,
)

logger = logging.getLogger("rr_actors")

HANDSHAKE_TIMEOUT = 5.0
"""Seconds a connection gets to connect and pass the authkey handshake (both sides)."""

LOCK_RETRY = 0.2
"""Seconds a listener retries a held name lock: a probe (`lock_held`) holds it briefly."""


class Paths(Protocol):
    """Where a registrar's files are (`system.SystemAddress`), and the system's secret."""

    @property
    def authkey(self) -> bytes: ...
    def socket_path(self, name: str) -> str: ...
    def tombstone_path(self, name: str) -> str: ...
    def lock_path(self, name: str) -> str: ...
    def limit_path(self, name: str) -> str: ...
    def restart_path(self, name: str) -> str: ...


class Rendezvous(Protocol):
    """What the link needs of its system (`system.UnixCarrier`)."""

    @property
    def address(self) -> Paths: ...
    @property
    def closed(self) -> bool: ...  # this process left the system: no new channel
    @property
    def messenger(self) -> Messenger: ...
    def speaker(self, name: str) -> str: ...  # what `name`'s `.restart` file says (rule 19)

    def ended(self, name: str) -> None:
        """A connection to `name` ended or failed: is it lost (rule 19)? Returns at once."""


# -- a connection: made, authenticated, written ---------------------------------------------

_HEADER = struct.Struct("!i")  # multiprocessing.connection's frame header
_LONG = struct.Struct("!Q")  # ... after a header of -1


class _Timed:
    """`send_bytes` and `recv_bytes` over `sock`, bounded by `deadline`."""

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
        self.sock.sendall(_HEADER.pack(len(data)) + data)

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
    """Pass the mutual authkey handshake on `sock` before `deadline` (monotonic).

    Raises `AuthenticationError`, `TimeoutError`, `OSError` or `EOFError`.
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
    """`sock` for writing, a `Connection` on a duplicate for reading (OSError: `EMFILE`)."""
    return sock, Connection(os.dup(sock.fileno()))


def _send_timeout(sock: socket.socket, seconds: float) -> None:
    """Bound (0: unbound) blocking sends on `sock`, and so a blocking `connect`."""
    sock.setsockopt(
        socket.SOL_SOCKET,
        socket.SO_SNDTIMEO,
        struct.pack("ll", int(seconds), int((seconds % 1) * 1_000_000)),
    )


def connect(
    path: str, authkey: bytes, *, coming: Callable[[], bool] | None = None
) -> tuple[socket.socket, Connection]:
    """Connect to `path` and pass the handshake within `HANDSHAKE_TIMEOUT` seconds,
    retried while `coming()` says a listener is on its way (a restart).

    Raises `OSError`/`EOFError` (nobody listens), `TimeoutError`, `AuthenticationError`.
    """
    deadline = time.monotonic() + HANDSHAKE_TIMEOUT
    pause = CONNECT_RETRY / 64
    while True:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            _send_timeout(sock, HANDSHAKE_TIMEOUT)
            sock.connect(path)
        except (ConnectionRefusedError, FileNotFoundError):
            sock.close()
            if coming is None or time.monotonic() + pause > deadline or not coming():
                raise
            time.sleep(pause)  # (the listener binds within milliseconds of its lock)
            pause = min(2 * pause, CONNECT_RETRY)
            continue
        except BaseException:
            sock.close()
            raise
        try:
            _send_timeout(sock, 0)
            handshake(sock, authkey, deadline, server=False)
            return split(sock)
        except BaseException:
            sock.close()
            raise


CONNECT_RETRY = 0.05
"""The longest pause, in seconds, between two connects to a listener that is coming."""


def lock_held(path: str) -> bool:
    """Whether a process holds the name lock at `path`; unsure: held (no false loss)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return False
    except OSError:
        return True
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)  # (closing releases the probe's lock)
    return False


class Writer:
    """The send side of one connection, in order; a failure calls `on_failure(exc)` once."""

    __slots__ = ("_closed", "_executor", "_lock", "_on_failure", "_sock")

    def __init__(
        self,
        sock: socket.socket | None,
        on_failure: Callable[[BaseException], None],
        name: str = "rr-write",
    ) -> None:
        self._lock = threading.Lock()  # `_sock` and `_closed`
        self._sock = sock
        self._closed = False
        self._on_failure = on_failure
        # (transient: no thread while idle, as a sender writes inline what the socket takes)
        self._executor = SerialExecutor(
            name, on_drop=_lost, on_end=self._close_socket, transient=True
        )

    @property
    def closed(self) -> bool:
        return self._closed

    def send(self, frame: bytes, on_lost: Lost | None = None) -> bool:
        """Send `frame` or queue it (never blocks); False if nothing of it was sent."""
        if self._closed:
            return False
        task = _Frame(self, frame, on_lost)
        try:
            return self._executor.submit(task, inline=task.now if self._sock else None)
        except OSError as exc:
            logger.debug("a send failed, the connection is closed: %s", exc)
            self.close()  # the caller cleans up: it knows what it was sending
            return False
        except RuntimeError as exc:  # no thread for what the socket did not take
            self.fail(exc)
            return False

    def connect_with(self, connect: Callable[[], object]) -> None:
        """Run `connect` first on the writer thread; it gives the socket (`attach`)."""
        self._executor.submit(connect)

    def attach(self, sock: socket.socket) -> bool:
        """Give a writer made without a socket its connected socket; False if closed."""
        with self._lock:
            if self._closed:
                return False
            self._sock = sock
            return True

    def close(self) -> bool:
        """Shut the connection down; queued frames are lost. False if closed already."""
        with self._lock:
            if self._closed:
                return False
            self._closed = True
            sock = self._sock
        if sock is not None:
            shutdown(sock)
        self._executor.close(timeout=0)
        return True

    def forget_in_child(self) -> None:
        """In a forked child: close this process's copy of the socket, never shut it down."""
        self._closed = True
        self._lock = threading.Lock()
        self._executor = SerialExecutor(self._executor.name)
        self._executor.finish()
        if self._sock is not None:
            self._sock.close()

    def fail(self, exc: BaseException) -> None:
        """Close because of a failed connect or write; report it once."""
        if self.close():
            self._on_failure(exc)

    def _close_socket(self) -> None:  # (after the last write: the executor's `on_end`)
        if self._sock is not None:
            # shut down first: closed, the reader's duplicate would keep the connection open
            shutdown(self._sock)
            self._sock.close()


class _Frame:
    """One frame to send (or what the socket did not take at once)."""

    __slots__ = ("data", "on_lost", "writer")

    def __init__(self, writer: Writer, data: bytes | memoryview, on_lost: Lost | None) -> None:
        self.writer = writer
        self.data = data
        self.on_lost = on_lost

    def now(self) -> _Frame | None:
        """Send what the socket takes at once (the sender's thread); the rest, if any."""
        sock = self.writer._sock
        assert sock is not None
        try:
            sent = sock.send(self.data, socket.MSG_DONTWAIT)
        except BlockingIOError:
            sent = 0
        if sent >= len(self.data):
            return None
        self.data = memoryview(self.data)[sent:]
        return self

    def __call__(self) -> None:  # (the writer thread: may block on the peer)
        sock = self.writer._sock
        try:
            if sock is not None:
                sock.sendall(self.data)
                return
            error = OSError("not connected")  # (its connect task failed)
        except OSError as exc:
            error = exc
        _lost(self)
        self.writer.fail(error)


def _lost(task: Task) -> None:
    if isinstance(task, _Frame) and task.on_lost is not None:
        run_lost([task.on_lost])


def _read(
    conn: Connection,
    limit: int,
    whole: Callable[[int, memoryview], object],
    oversized: Callable[[int, int], object],
    kind: str,
    name: str,
) -> None:
    """Hand each frame read from `conn` to `whole`, or `oversized` over `limit`, until EOF."""
    for data in frames(conn, limit):
        try:
            if isinstance(data, Oversized):
                oversized(data.token, data.size)
            else:
                whole(*unframe(data))
        except Exception:
            logger.exception("dropped a malformed %s of registrar %s", kind, name)


# -- the files of a served name ----------------------------------------------------------------


def _take_lock(path: str, name: str) -> int:
    """The descriptor holding `name`'s lock (retried `LOCK_RETRY` s).

    Raises `DuplicateNameError` (held elsewhere) or `ConfigError` (cannot open).
    """
    deadline = time.monotonic() + LOCK_RETRY
    pause = 0.002
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
        except OSError as exc:
            raise ConfigError(f"cannot open the lock file {path!r}: {exc}") from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if time.monotonic() >= deadline:
                raise DuplicateNameError(
                    f"registrar {name!r} is already served on this system"
                ) from exc
        else:
            return fd
        time.sleep(pause)  # (a probe is over in microseconds; an owner stays)
        pause = min(2 * pause, 0.05)


def publish(path: str, text: str) -> None:
    """Write `text` to `path` atomically (OSError if it cannot)."""
    folder, name = os.path.split(path)
    temporary = os.path.join(folder, f".{name}")
    fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.write(fd, text.encode("ascii"))
    finally:
        os.close(fd)
    os.replace(temporary, path)


def read_limit(path: str) -> int:
    """The limit published at `path`, else `DEFAULT_MAX_MESSAGE_BYTES`."""
    try:
        with open(path, "rb") as published:
            value = int(published.read(32))
    except (OSError, ValueError):
        return DEFAULT_MAX_MESSAGE_BYTES
    return value if value > 0 else DEFAULT_MAX_MESSAGE_BYTES


# -- the outbound side: a channel to a registrar of another process ---------------------------


class _Channel(Route):
    """One connection from this process to a remote registrar (a fresh one may take a
    frame this one could not: `again`)."""

    __slots__ = ("dial", "reading", "writer")

    def __init__(
        self, writer: Writer, limit: int = DEFAULT_MAX_MESSAGE_BYTES, dial: Dial | None = None
    ) -> None:
        super().__init__(limit, again=True)
        self.writer = writer
        self.dial = dial
        self.reading: Connection | None = None  # the reader thread's (a duplicate descriptor)


class Dial:
    """This process's way to registrar `name` of another process: one connection, made
    lazily, again once it went (`route`)."""

    def __init__(self, system: Rendezvous, name: str) -> None:
        self.name = name
        self._system = system
        self._path = system.address.socket_path(name)
        self._lock = threading.Lock()
        self._channel: _Channel | None = None

    def route(self) -> _Channel:
        channel = self._channel
        if channel is None or channel.writer.closed:
            if channel is not None:  # (a frame could not leave it: what waits on it fails)
                self._lose(channel, None)
            channel = self._open()
        return channel

    def send(self, channel: _Channel, data: bytes) -> None:
        if not channel.writer.send(data):
            raise self._gone("lost its connection")

    def close(self, error: RrError) -> None:
        channel = self._channel
        if channel is not None:
            self._lose(channel, error)

    def forget_in_child(self) -> None:
        """In a forked child: drop the parent's connection and replies, never shut down."""
        self._lock = threading.Lock()
        channel, self._channel = self._channel, None
        if channel is None:
            return
        channel.pending.clear()
        channel.writer.forget_in_child()
        if channel.reading is not None:
            channel.reading.close()

    def _open(self) -> _Channel:
        """The current channel, or a new one whose writer thread connects."""
        with self._lock:
            channel = self._channel
            if channel is not None and not channel.writer.closed:
                return channel
            if self._system.closed:
                raise RegistrarStoppedError(f"the system of registrar {self.name!r} was closed")
            if not os.path.exists(self._path) and not lock_held(
                self._system.address.lock_path(self.name)
            ):  # (a listener that holds the lock binds soon: its connect waits for it)
                self._system.ended(self.name)  # (is it lost? rule 19)
                raise self._gone("cannot be reached (it does not listen)")
            limit = read_limit(self._system.address.limit_path(self.name))
            writer = Writer(None, lambda exc: self._failed(fresh, exc), f"rr-write-{self.name}")
            fresh = _Channel(writer, limit, self)
            try:
                writer.connect_with(functools.partial(self._connect, fresh))  # (its first task)
            except RuntimeError as exc:  # no thread to connect on: the machine's bound, named
                writer.close()
                raise no_thread(self.name, exc, "its connection") from exc
            self._channel = channel = fresh
        return channel

    def _connect(self, channel: _Channel) -> None:
        """`channel`'s writer thread, first: connect, start its reader."""
        try:
            coming = functools.partial(lock_held, self._system.address.lock_path(self.name))
            sock, conn = connect(self._path, self._system.address.authkey, coming=coming)
        except AuthenticationError as exc:
            error: RrError = RegistrarUnavailableError(
                f"registrar {self.name!r} refused this process's authkey"
            )
            error.__cause__ = exc
            channel.writer.fail(error)
            return
        except Exception as exc:  # noqa: BLE001 - OSError, EOFError, ...: not reachable
            error = self._gone("cannot be reached", exc)
            error.__cause__ = exc
            channel.writer.fail(error)
            return
        if not channel.writer.attach(sock):  # closed while connecting
            conn.close()
            sock.close()
            return
        channel.reading = conn
        try:
            threading.Thread(
                target=self._read, args=(channel, conn), name=f"rr-read-{self.name}", daemon=True
            ).start()
        except RuntimeError as exc:  # no reader: what waits on it fails, naming the bound
            channel.reading = None
            conn.close()
            channel.writer.fail(no_thread(self.name, exc, "its connection"))

    def _failed(self, channel: _Channel, exc: BaseException) -> None:
        if isinstance(exc, RuntimeError):
            exc = no_thread(self.name, exc, "its connection")
        if isinstance(exc, RrError):
            self._lose(channel, exc)
        else:
            self._lose(channel, self._gone("lost its connection", exc))
        if not self._system.closed:
            self._system.ended(self.name)  # (is it lost? rule 19)

    def _gone(self, how: str, cause: BaseException | None = None) -> RrError:
        if os.path.exists(self._system.address.tombstone_path(self.name)):
            return RegistrarStoppedError(f"registrar {self.name!r} was stopped", self.name)
        detail = f" ({type(cause).__name__}: {cause})" if cause is not None else ""
        bound = None if cause is None else bound_reached(cause)  # (here, or the other side's)
        if bound is not None:
            detail += f": this machine's limit of {bound} was reached"
        return RegistrarUnavailableError(f"registrar {self.name!r} {how}{detail}")

    def _lose(self, channel: _Channel, error: RrError | None) -> None:
        """Fail the replies pending on `channel` (first: `error` is what they hear, not its
        reader's end), close it, fail those sent meanwhile (any thread)."""
        fail = error or (lambda: self._gone("died while answers were outstanding"))
        channel.pending.fail(None, fail)
        channel.writer.close()
        with self._lock:
            if self._channel is channel:
                self._channel = None
        channel.pending.fail(None, fail)

    def _read(self, channel: _Channel, conn: Connection) -> None:
        """The reader thread of one connection: resolve answers until it ends."""
        pending = channel.pending
        try:
            _read(conn, channel.limit, pending.answered, pending.too_large, "answer", self.name)
        finally:
            self._lose(channel, None)
            conn.close()
            if not self._system.closed:
                self._system.ended(self.name)  # (is it lost? rule 19)


# -- the inbound side: a registrar's listener and its connections -----------------------------


class _Accepted:
    """One accepted connection of a listener, read on its own thread (OSError: `EMFILE`)."""

    def __init__(self, listener: Listener, sock: socket.socket, deadline: float) -> None:
        self.listener = listener
        self.deadline = deadline  # for the whole handshake
        self.sock, self.conn = split(sock)
        self.writer = Writer(self.sock, self._failed, f"rr-answer-{listener.name}")

    def send(self, frame: bytes, on_lost: Lost | None = None) -> bool:
        if self.writer.send(frame, on_lost):
            return True
        logger.debug("answer of %s dropped: the caller's connection is gone", self.listener.name)
        return False

    def close(self) -> None:  # (any thread; the reader thread then cleans up)
        self.writer.close()

    def forget_in_child(self) -> None:  # (closed, not shut down: the parent's)
        self.writer.forget_in_child()
        self.conn.close()

    def _failed(self, exc: BaseException) -> None:
        logger.debug("connection to a caller of %s lost: %s", self.listener.name, exc)

    def serve(self) -> None:
        """Handshake, then deliver every message to the registrar (its own thread)."""
        listener = self.listener
        conn = self.conn
        try:
            try:
                handshake(self.sock, listener.authkey, self.deadline, server=True)
            except (AuthenticationError, EOFError, OSError) as exc:
                if self.writer.closed:  # the listener stopped and closed it: no refusal
                    logger.debug("registrar %s stopped during a handshake: %s", listener.name, exc)
                else:
                    logger.warning("registrar %s refused a connection: %s", listener.name, exc)
                return
            messenger, endpoint = listener.messenger, listener.endpoint
            _read(
                conn,
                listener.max_message_bytes,
                functools.partial(messenger.message, endpoint, self),
                functools.partial(messenger.oversized, endpoint, self),
                "message",
                listener.name,
            )
        finally:
            self.writer.close()
            conn.close()
            listener.forget(self)


_SHORTAGE = frozenset({errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM})  # back off

# seconds before a failed `accept` is retried (doubling), well below HANDSHAKE_TIMEOUT
_BACKOFF_FIRST = 0.01
_BACKOFF_MAX = 0.5


class Listener(Listening):
    """Accepts connections for a registrar served here, holding the name's lock.

    Raises `DuplicateNameError` or `ConfigError` (lock file or socket unusable).
    """

    def __init__(self, system: Rendezvous, endpoint: Endpoint) -> None:
        super().__init__(endpoint)
        self.messenger = system.messenger
        self.max_message_bytes = endpoint.max_message_bytes
        self.authkey = system.address.authkey
        self.path = system.address.socket_path(self.name)
        self.tombstone = system.address.tombstone_path(self.name)
        self._lock = threading.Lock()
        self._connections: set[_Accepted] = set()
        self._closed = False
        self._wake = threading.Event()  # a connection ended, or the listener closes
        self._lock_fd = _take_lock(system.address.lock_path(self.name), self.name)
        self.limit_path = system.address.limit_path(self.name)
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            publish(self.limit_path, str(self.max_message_bytes))  # before anyone connects
            # who speaks for it if this process dies (rule 19), kept after it ends
            publish(system.address.restart_path(self.name), system.speaker(self.name))
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.path)  # left behind by a process that died
            self._sock.bind(self.path)
            self._sock.listen(socket.SOMAXCONN)  # (connecting peers also wait for room)
        except OSError as exc:
            self._sock.close()
            os.close(self._lock_fd)
            raise ConfigError(f"cannot listen on {self.path!r}: {exc}") from exc
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.tombstone)
        threading.Thread(target=self._accept, name=f"rr-listen-{self.name}", daemon=True).start()

    def _accept(self) -> None:
        try:
            self._accept_until_closed()
        except BaseException as exc:  # a bug: say so, and let the heartbeat report it
            self.failing_since = -math.inf  # (in trouble for ever)
            self.failure = f"its accept thread died: {exc!r}"
            logger.exception("registrar %s stopped accepting connections", self.name)

    def _accept_until_closed(self) -> None:
        backoff = _BACKOFF_FIRST
        while True:
            try:
                sock, _ = self._sock.accept()
                sock.setblocking(True)
            except OSError as exc:
                if self._closed:
                    return
                if exc.errno == errno.ECONNABORTED:  # the peer gave up before the accept
                    continue
                backoff = self._cannot_accept(exc, backoff)
                continue
            deadline = time.monotonic() + HANDSHAKE_TIMEOUT
            try:
                accepted = _Accepted(self, sock, deadline)
            except OSError as exc:  # no descriptor for its reading side
                sock.close()
                backoff = self._cannot_accept(exc, backoff)
                continue
            if self.failing_since is not None:
                self._accepting_again()
            backoff = _BACKOFF_FIRST
            with self._lock:
                if self._closed:
                    accepted.close()
                    accepted.conn.close()
                    return
                self._connections.add(accepted)
            try:
                threading.Thread(
                    target=accepted.serve, name=f"rr-link-{self.name}", daemon=True
                ).start()
            except RuntimeError as exc:  # no thread for it (a limit on threads): as EMFILE
                self.forget(accepted)
                accepted.close()
                accepted.conn.close()
                backoff = self._cannot_accept(OSError(errno.EAGAIN, f"no thread: {exc}"), backoff)

    def _cannot_accept(self, exc: OSError, backoff: float) -> float:
        """Note a failed accept (log the first of a run), wait `backoff`; the next one."""
        if self.failing_since is None:
            self.failing_since = time.monotonic()
            self.failure = f"{type(exc).__name__}: {exc}"
            with self._lock:
                open_connections = len(self._connections)
            logger.warning(
                "registrar %s cannot accept connections (%s; %d open): retrying",
                self.name,
                exc,
                open_connections,
            )
        if exc.errno not in _SHORTAGE:
            logger.debug("registrar %s: accept failed: %s", self.name, exc)
        self._wake.clear()
        self._wake.wait(backoff)  # cut short when a connection ends or the listener closes
        return min(2 * backoff, _BACKOFF_MAX)

    def _accepting_again(self) -> None:
        since, self.failing_since = self.failing_since, None
        if since is not None:
            logger.info(
                "registrar %s accepts connections again after %.3f s",
                self.name,
                time.monotonic() - since,
            )

    def forget(self, accepted: _Accepted) -> None:
        with self._lock:
            self._connections.discard(accepted)
        self._wake.set()  # its descriptors are free: a listener backing off tries again

    def forget_in_child(self) -> None:
        """In a forked child: close its copies of the socket, the lock and connections."""
        self._closed = True
        connections = list(self._connections)
        self._connections.clear()
        self._lock = threading.Lock()
        self._sock.close()
        with contextlib.suppress(OSError):
            os.close(self._lock_fd)
        for accepted in connections:
            accepted.forget_in_child()

    def stop(self, *, stopped: bool) -> None:
        """Stop listening; `stopped` leaves a tombstone (peers then say "stopped")."""
        with self._lock:
            self._closed = True
            connections = list(self._connections)
            self._connections.clear()
        self._wake.set()
        if stopped:
            with contextlib.suppress(OSError), open(self.tombstone, "w"):
                pass
        with contextlib.suppress(OSError):
            os.unlink(self.path)
        with contextlib.suppress(OSError):
            os.unlink(self.limit_path)
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_RDWR)
        self._sock.close()
        os.close(self._lock_fd)  # last: the path is free for the next owner only now
        for accepted in connections:
            accepted.close()
