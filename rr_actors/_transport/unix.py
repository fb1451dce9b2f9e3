"""How messages cross processes: authenticated channels between the registrars of a system.

A *system* is a private runtime directory (mode 0700) plus a random authkey. Every process
that takes part [`attach`][rr_actors._transport.attach]es it; each registrar it
[`serve`][rr_actors._transport.AttachedSystem.serve]s listens on
`<runtime_dir>/<registrar>.sock` (AF_UNIX) and holds an exclusive `flock` on
`<runtime_dir>/<registrar>.lock` for as long as it listens, so one name has one owner.
Another process reaches that registrar through a
[`RemotePeer`][rr_actors._transport.RemotePeer], which the directory resolver hands out
for names that are not registered locally, so the registrar code sends a `Load` the same
way whether its target lives in this process or another one.

Wire format: one frame per message (`multiprocessing.connection` framing), `8-byte token
(little endian) + cloudpickle payload`. A message's `reply` never crosses: the sender keeps
it in a table under the token (0: no answer wanted) and the receiver substitutes a reply
that sends `token + pickle((value, error))` back over the same connection. Nothing is
unpickled from a connection before it passed the authkey handshake
(`multiprocessing.connection.deliver_challenge` / `answer_challenge`, run on a thread of
the connection, bounded by a timeout).

Sending never blocks on the other process: a sender writes a frame itself only when the
socket takes it at once, otherwise it queues the frame for the connection's writer thread
(frames of one connection leave in the order they were sent). A frozen peer therefore
stalls only its own writer thread; callers still time out on their own timeouts.

Failure: when a connection ends (the peer process died or its registrar stopped), every
answer still outstanding on it fails at once with `RegistrarUnavailableError` (or
`RegistrarStoppedError` if the registrar was stopped cleanly); the next message connects
again, so a restarted registrar that binds the same path is reached. Low-level errors
(`EOFError`, `BrokenPipeError`, `ConnectionResetError`, `OSError`, pickling errors) are
translated into rr_actors errors with `raise ... from exc` and never reach a caller.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import fcntl
import io
import itertools
import logging
import os
import pickle
import socket
import struct
import tempfile
import threading
import traceback
from collections.abc import Callable, Iterator
from multiprocessing import AuthenticationError
from multiprocessing.connection import Connection, answer_challenge, deliver_challenge
from typing import TYPE_CHECKING, Any

import cloudpickle

from rr_actors._core.directory import DIRECTORY, Peer, Reply
from rr_actors._core.replies import FutureReply, wait
from rr_actors._registrar import messages as _messages
from rr_actors._types import Query, Status, StatusUpdate
from rr_actors.errors import (
    CallTimeoutError,
    ConfigError,
    DependencyCycleError,
    DuplicateNameError,
    ErrorFrame,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    ResourceLoadError,
    RrError,
    UnknownQueryError,
    UnknownServerError,
)

if TYPE_CHECKING:
    from rr_actors._registrar import ResourceRegistrar

__all__ = ["AttachedSystem", "RemotePeer", "System", "SystemAddress", "attach"]

logger = logging.getLogger("rr_actors")

HANDSHAKE_TIMEOUT = 5.0
"""Seconds a connecting peer gets to connect and pass the authkey handshake (both sides)."""

_MAX_SOCKET_PATH = 107  # sun_path is 108 bytes with the terminating NUL (Linux)
_NO_REPLY = 0
_TOKEN = struct.Struct("<Q")
_LENGTH = struct.Struct("!i")  # multiprocessing.connection's frame header
_LONG_LENGTH = struct.Struct("!iQ")  # ... for frames over 2 GiB: -1, then the length
_RUNTIME_SUFFIXES = (".sock", ".stopped", ".lock")  # the files a system puts in its directory


@dataclasses.dataclass(frozen=True)
class _Run:
    """Control request: run `fn(registrar)` in the registrar's process, answer its result."""

    fn: Callable[[ResourceRegistrar], Any]
    reply: Reply | None


# -- encoding -----------------------------------------------------------------------------

# Types pickled by reference with the C pickler's own machinery: cloudpickle's
# `reducer_override` (a Python call per object) is skipped for them. Everything else,
# the user's requests and responses included, goes through cloudpickle.
_BY_REFERENCE: frozenset[type] = frozenset(
    {
        _messages.Load,
        _messages.Unload,
        _messages.Abandon,
        _messages.Fetch,
        _messages.StatusNotice,
        _messages.Revoke,
        _messages.ResponseUpdated,
        _messages.ConsumerDown,
        _Run,
        Query,
        Status,
        StatusUpdate,
        ErrorFrame,
        ResourceLoadError,
        DependencyCycleError,
        UnknownServerError,
        UnknownQueryError,
        RegistrarUnavailableError,
        RegistrarStoppedError,
        CallTimeoutError,
        ConfigError,
        RrError,
    }
)


class _Pickler(cloudpickle.Pickler):  # type: ignore[misc]
    """cloudpickle, with a fast path for the wire protocol's own types."""

    def reducer_override(self, obj: Any) -> Any:
        kind = type(obj)
        if kind in _BY_REFERENCE or (kind is type and obj in _BY_REFERENCE):
            return NotImplemented
        return super().reducer_override(obj)


# Small builtin data (exact types: no subclass, nothing defined in `__main__`), the wire
# protocol's records holding only such data, and status codes: the C pickler alone encodes
# them as cloudpickle would, without building a cloudpickle `Pickler` (a third of a dedup
# hit's encoding time). `_plain` looks at no more than `_PLAIN_BUDGET` containers of at
# most `_PLAIN_WIDTH` items each; anything larger or else goes through cloudpickle.
_PLAIN_ATOMS: frozenset[type] = frozenset({str, int, float, bool, type(None), bytes, Status})
_PLAIN_SEQUENCES: frozenset[type] = frozenset({tuple, list, set, frozenset})
_PLAIN_RECORDS: frozenset[type] = frozenset(
    kind for kind in _BY_REFERENCE if dataclasses.is_dataclass(kind) and kind is not ErrorFrame
)
_PLAIN_BUDGET = 64
_PLAIN_WIDTH = 256


def _plain(obj: Any) -> bool:
    """Whether `obj` is small builtin data that plain `pickle` encodes as cloudpickle would."""
    return type(obj) in _PLAIN_ATOMS or _plain_walk(obj, _PLAIN_BUDGET) >= 0


def _plain_walk(item: Any, budget: int) -> int:
    """The budget left after walking the container `item`, or -1 if it is not plain."""
    kind = type(item)
    budget -= 1
    if budget < 0:
        return -1
    items: Any
    if kind in _PLAIN_SEQUENCES or kind is dict:
        if len(item) > _PLAIN_WIDTH:
            return -1
        items = item if kind is not dict else (*item.keys(), *item.values())
    elif kind in _PLAIN_RECORDS:  # a few fields each
        items = item.__dict__.values()
    else:
        return -1
    for value in items:
        if type(value) not in _PLAIN_ATOMS:
            budget = _plain_walk(value, budget)
            if budget < 0:
                return -1
    return budget


def _without_reply(message: Any) -> Any:
    """`message` as it crosses to another process: its `reply` stays with the sender."""
    if type(message) is _messages.Load:  # the hot path: a fifth of `dataclasses.replace`
        return _messages.Load(
            message.query_id,
            message.server,
            message.request,
            message.origin_rr,
            message.chain,
            None,  # type: ignore[arg-type]
        )
    return dataclasses.replace(message, reply=None)


def _frame(token: int, obj: Any) -> bytes:
    """The bytes on the wire for `obj`: header, `token`, pickle; pickling errors propagate.

    The header is `multiprocessing.connection`'s, so the receiver reads frames with
    `Connection.recv_bytes`. Small builtin data (`_plain`) is pickled by the C pickler
    alone; everything else by cloudpickle.
    """
    if _plain(obj):
        payload = pickle.dumps(obj, pickle.HIGHEST_PROTOCOL)
        size = len(payload) + _TOKEN.size
        if size <= 0x7FFFFFFF:
            return b"".join((_LENGTH.pack(size), _TOKEN.pack(token), payload))
        return b"".join((_LONG_LENGTH.pack(-1, size), _TOKEN.pack(token), payload))
    buffer = io.BytesIO()
    buffer.write(_LENGTH.pack(0))
    buffer.write(_TOKEN.pack(token))
    _Pickler(buffer, protocol=pickle.HIGHEST_PROTOCOL).dump(obj)
    size = buffer.tell() - _LENGTH.size
    if size > 0x7FFFFFFF:
        return _LONG_LENGTH.pack(-1, size) + buffer.getbuffer()[_LENGTH.size :]
    buffer.seek(0)
    buffer.write(_LENGTH.pack(size))
    return buffer.getvalue()


def _frames(conn: Connection) -> Iterator[bytes]:
    """The frames received on `conn`, until it ends (EOF or a socket error)."""
    while True:
        try:
            yield conn.recv_bytes()
        except (EOFError, OSError):
            return


def _unframe(data: bytes) -> tuple[int, memoryview]:
    """Split a received frame into token and payload; raises ValueError if it is too short."""
    if len(data) < _TOKEN.size:
        raise ValueError(f"a frame of {len(data)} bytes is too short to hold a token")
    (token,) = _TOKEN.unpack_from(data)
    return token, memoryview(data)[_TOKEN.size :]


def _what(message: Any, target: str) -> str:
    """A few words naming a message, for error texts."""
    if isinstance(message, _messages.Load):
        return f"request of call to '{target}/{message.server}'"
    if isinstance(message, _Run):
        return f"function run on registrar {target!r}"
    return f"{type(message).__name__} message to registrar {target!r}"


# -- sockets --------------------------------------------------------------------------------


def _set_io_timeout(conn: Connection, seconds: float) -> None:
    """Bound (or with 0, unbound) blocking reads and writes on `conn`'s socket."""
    value = struct.pack("ll", int(seconds), int((seconds % 1) * 1_000_000))
    with socket.socket(fileno=os.dup(conn.fileno())) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, value)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, value)


def _shutdown(sock: socket.socket) -> None:
    """Wake every thread blocked reading or writing `sock` (close alone does not, on Linux)."""
    with contextlib.suppress(OSError):
        sock.shutdown(socket.SHUT_RDWR)


def _split(sock: socket.socket) -> tuple[socket.socket, Connection]:
    """`sock` for writing plus a `Connection` on a duplicate descriptor for reading."""
    return sock, Connection(os.dup(sock.fileno()))


def _connect(path: str, authkey: bytes) -> tuple[socket.socket, Connection]:
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
        sock, conn = _split(sock)
    except BaseException:
        sock.close()
        raise
    try:
        _set_io_timeout(conn, HANDSHAKE_TIMEOUT)
        answer_challenge(conn, authkey)
        deliver_challenge(conn, authkey)
        _set_io_timeout(conn, 0)
    except BaseException:
        conn.close()
        sock.close()
        raise
    return sock, conn


Lost = Callable[[], None]
"""Called (on any thread) when a queued frame could not be sent: the connection ended."""


class _Writer:
    """The send side of one connection: frames leave in the order they were sent.

    A sender writes a frame itself when nothing is queued or being written and the
    socket takes all of it without blocking (`MSG_DONTWAIT`); otherwise the frame (or the
    part the socket did not take) is queued for the connection's writer thread, the only
    thread that may block on a peer that does not read. A failed connect or a failed
    write of the writer thread closes the writer and calls `on_failure(exc)` once; a
    sender whose own write fails gets False from `send` and cleans up itself.
    """

    __slots__ = ("_busy", "_cond", "_on_failure", "_queue", "_sock", "_started", "closed")

    def __init__(
        self, sock: socket.socket | None, on_failure: Callable[[BaseException], None]
    ) -> None:
        self._cond = threading.Condition(threading.Lock())
        self._queue: collections.deque[tuple[bytes | memoryview, Lost | None]] = collections.deque()
        self._sock = sock
        self._busy = sock is None  # nobody writes before the socket is there
        self._started = False
        self._on_failure = on_failure
        self.closed = False

    def send(self, frame: bytes, on_lost: Lost | None = None) -> bool:
        """Send `frame` or queue it (never blocks on the peer).

        Returns:
            True if the frame was sent or queued (if the connection ends before it is
            sent, `on_lost` runs); False if the writer was closed or the connection broke
            just now (the writer is then closed): nothing of the frame was sent.
        """
        with self._cond:
            if self.closed:
                return False
            if self._busy or self._queue:
                self._queue.append((frame, on_lost))
                self._cond.notify()
                return True
            self._busy = True
            sock = self._sock
        assert sock is not None
        try:
            sent = sock.send(frame, socket.MSG_DONTWAIT)
        except BlockingIOError:
            sent = 0
        except OSError as exc:
            logger.debug("a send failed, the connection is closed: %s", exc)
            with self._cond:
                self._busy = False
                self._cond.notify_all()
            self.close()  # the caller cleans up: it knows what it was sending
            return False
        lost = False
        with self._cond:
            if sent < len(frame):
                if self.closed:
                    lost = True
                else:
                    self._queue.appendleft((memoryview(frame)[sent:], on_lost))
            self._busy = False
            if self._queue or self.closed:  # else the writer thread would wake to nothing
                self._cond.notify_all()  # (once closed, it waits for `_busy` to clear)
        if lost and on_lost is not None:
            _run_lost([on_lost])
        return True

    def attach(self, sock: socket.socket) -> bool:
        """Give a writer made without a socket its connected socket; False if closed.

        The calling thread then becomes the writer thread: it must call `run()`.
        """
        with self._cond:
            if self.closed:
                return False
            self._sock = sock
            self._started = True
            self._busy = False
            self._cond.notify_all()
            return True

    def start(self, name: str) -> None:
        """Start the writer thread of a writer made with its socket."""
        with self._cond:
            self._started = True
        threading.Thread(target=self.run, name=name, daemon=True).start()

    def close(self) -> bool:
        """Stop sending; queued frames are lost (their `on_lost` runs). False if closed."""
        with self._cond:
            if self.closed:
                return False
            self.closed = True
            lost = [on_lost for _, on_lost in self._queue if on_lost is not None]
            self._queue.clear()
            sock = self._sock
            self._cond.notify_all()
            close_here = not self._started
        if sock is not None:
            _shutdown(sock)
            if close_here:
                sock.close()
        _run_lost(lost)
        return True

    def fail(self, exc: BaseException) -> None:
        """Close because of `exc` (a failed connect or write) and report it once."""
        if self.close():
            self._on_failure(exc)

    def run(self) -> None:
        """The writer thread: send what was queued until the writer closes; owns the socket."""
        sock = self._sock
        assert sock is not None
        try:
            while True:
                with self._cond:
                    while not self.closed and (self._busy or not self._queue):
                        self._cond.wait()
                    if self.closed:
                        return
                    batch = list(self._queue)
                    self._queue.clear()
                    self._busy = True
                for index, (data, _) in enumerate(batch):
                    try:
                        sock.sendall(data)
                    except OSError as exc:
                        with self._cond:
                            self._busy = False
                        _run_lost([on_lost for _, on_lost in batch[index:] if on_lost])
                        self.fail(exc)
                        return
                with self._cond:
                    self._busy = False
        finally:
            with self._cond:
                while self._busy:  # a sender still writes inline: let it finish first
                    self._cond.wait()
            sock.close()


def _run_lost(callbacks: list[Lost]) -> None:
    for on_lost in callbacks:
        try:
            on_lost()
        except Exception:
            logger.exception("cleaning up after a lost frame failed")


# -- the system -------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class SystemAddress:
    """How a process joins a system: pass it (it pickles) to the processes you start.

    Attributes:
        runtime_dir: the private directory that holds the registrars' sockets.
        authkey: the system's secret; a connection that cannot prove it is refused.
    """

    runtime_dir: str
    authkey: bytes = dataclasses.field(repr=False)

    def socket_path(self, name: str) -> str:
        """The path registrar `name` listens on."""
        return os.path.join(self.runtime_dir, f"{name}.sock")

    def tombstone_path(self, name: str) -> str:
        """A file that says registrar `name` was stopped cleanly (not crashed)."""
        return os.path.join(self.runtime_dir, f"{name}.stopped")

    def lock_path(self, name: str) -> str:
        """The file whose `flock` the process serving registrar `name` holds."""
        return os.path.join(self.runtime_dir, f"{name}.lock")


class _Channel:
    """One connection from this process to a remote registrar and its outstanding answers.

    `pending` maps a token to the reply (and the message, for error texts) waiting for its
    answer. Entries leave it only through atomic dict operations (`pop` by the reader,
    `popitem` when the channel is lost), so each reply is answered exactly once.
    """

    __slots__ = ("pending", "writer")

    def __init__(self, writer: _Writer) -> None:
        self.writer = writer
        self.pending: dict[int, tuple[Reply, Any]] = {}


class RemotePeer:
    """A registrar in another process of the system, reached through its socket.

    `tell` is what the registrar code calls for every message; it connects lazily (one
    connection per target per process, made on the connection's writer thread) and is
    safe from any thread. Answers are read by one daemon thread per connection, which
    resolves the kept replies.
    """

    def __init__(self, system: AttachedSystem, name: str) -> None:
        self.name = name
        self._system = system
        self._path = system.address.socket_path(name)
        self._lock = threading.Lock()
        self._channel: _Channel | None = None
        self._tokens = itertools.count(1)

    def tell(self, message: Any) -> None:
        """Send `message` to the remote registrar; its reply (if any) is answered later.

        Called from any thread of this process: a caller's thread (`call` sends its `Load`
        from there), registrar and client actor threads, worker threads, and this
        transport's reader threads. It never blocks on the peer: the frame is written
        only if the socket takes it at once, otherwise it is queued for the connection's
        writer thread, which also connects (the handshake is bounded by
        `HANDSHAKE_TIMEOUT`). Messages told to one peer from one process arrive in the
        order they were told. A peer that is unreachable, frozen or dies later fails the
        reply (`RegistrarUnavailableError`, or `RegistrarStoppedError` if it was stopped);
        a caller waiting on it with a timeout gets its `CallTimeoutError` in time.

        Raises:
            ConfigError: the message (say, the request of a call) cannot be pickled.
            RegistrarUnavailableError: the registrar's process is known to be unreachable.
            RegistrarStoppedError: it was stopped, or this process closed the system.
        """
        reply: Reply | None = getattr(message, "reply", None)
        if reply is not None:
            message = _without_reply(message)
        token = next(self._tokens) if reply is not None else _NO_REPLY  # atomic in CPython
        try:
            frame = _frame(token, message)
        except Exception as exc:
            raise ConfigError(f"{_what(message, self.name)} is not picklable: {exc}") from exc
        for _attempt in (1, 2):
            channel = self._channel
            if channel is None or channel.writer.closed:
                channel = self._open()
            if reply is not None:
                channel.pending[token] = (reply, message)
            if channel.writer.send(frame):
                return
            # The connection was lost before anything of the frame left: unless its loss
            # already failed the reply, send once more on a fresh connection.
            ours = reply is None or channel.pending.pop(token, None) is not None
            self._lose(channel, None)
            if not ours:
                return
        raise self._gone("lost its connection")

    def run(self, fn: Callable[[ResourceRegistrar], Any], *, timeout: float) -> Any:
        """Run `fn(registrar)` in the remote registrar's process and return its result.

        `fn` is cloudpickled (closures work) and runs on a fresh thread there, so it may
        block, e.g. on `registrar.send_status(...)`.

        Args:
            fn: called with the remote `ResourceRegistrar`; its result must pickle.
            timeout: seconds to wait for the result.

        Returns:
            What `fn` returned.

        Raises:
            CallTimeoutError: no result within `timeout` seconds.
            RegistrarUnavailableError: the registrar's process died or is unreachable.
            RegistrarStoppedError: the registrar was stopped.
            ConfigError: `fn` does not pickle.
            RrError: its result does not pickle (the message says so).
            Exception: whatever `fn` raised, re-raised here.
        """
        reply = FutureReply()
        try:
            self.tell(_Run(fn, reply))
        except RrError as exc:
            reply.set_error(exc)
        return wait(reply.future, timeout, f"run() on registrar {self.name!r}")

    def close(self, error: RrError) -> None:
        """Close the connection; outstanding answers fail with `error`."""
        channel = self._channel
        if channel is not None:
            self._lose(channel, error)

    # -- plumbing --------------------------------------------------------------------------

    def _open(self) -> _Channel:
        """The current channel, or a new one whose writer thread connects."""
        with self._lock:
            channel = self._channel
            if channel is not None and not channel.writer.closed:
                return channel
            if self._system.closed:
                raise RegistrarStoppedError(f"the system of registrar {self.name!r} was closed")
            if not os.path.exists(self._path):
                raise self._gone("cannot be reached (it does not listen)")
            fresh = _Channel(_Writer(None, lambda exc: self._failed(fresh, exc)))
            self._channel = channel = fresh
        threading.Thread(
            target=self._connect, args=(channel,), name=f"rr-write-{self.name}", daemon=True
        ).start()
        return channel

    def _connect(self, channel: _Channel) -> None:
        """The writer thread of `channel`: connect, start its reader, then write."""
        try:
            sock, conn = _connect(self._path, self._system.address.authkey)
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
        threading.Thread(
            target=self._read, args=(channel, conn), name=f"rr-read-{self.name}", daemon=True
        ).start()
        channel.writer.run()

    def _failed(self, channel: _Channel, exc: BaseException) -> None:
        """`channel`'s writer failed (connect or write): fail what waits on it."""
        if isinstance(exc, RrError):
            self._lose(channel, exc)
        else:
            self._lose(channel, self._gone("lost its connection", exc))

    def _gone(self, how: str, cause: BaseException | None = None) -> RrError:
        if os.path.exists(self._system.address.tombstone_path(self.name)):
            return RegistrarStoppedError(f"registrar {self.name!r} was stopped")
        detail = f" ({type(cause).__name__}: {cause})" if cause is not None else ""
        return RegistrarUnavailableError(f"registrar {self.name!r} {how}{detail}")

    def _lose(self, channel: _Channel, error: RrError | None) -> None:
        """Close `channel` and fail every reply still waiting on it (any thread)."""
        channel.writer.close()
        with self._lock:
            if self._channel is channel:
                self._channel = None
        pending = channel.pending
        failed: list[Reply] = []
        while True:
            try:
                _, (reply, _message) = pending.popitem()  # atomic: the reader pops too
            except KeyError:
                break
            failed.append(reply)
        if not failed:
            return
        error = error or self._gone("died while answers were outstanding")
        for reply in failed:
            reply.set_error(error)

    def _read(self, channel: _Channel, conn: Connection) -> None:
        """The reader thread of one connection: resolve answers until it ends."""
        try:
            for data in _frames(conn):
                try:
                    self._answer(channel, data)
                except Exception:
                    logger.exception("dropped a malformed answer from registrar %s", self.name)
        finally:
            self._lose(channel, None)
            conn.close()

    def _answer(self, channel: _Channel, data: bytes) -> None:
        token, payload = _unframe(data)
        entry = channel.pending.pop(token, None)
        if entry is None:
            return
        reply, message = entry
        try:
            value, error = pickle.loads(payload)
        except Exception as exc:  # noqa: BLE001 - any unpickling failure fails this answer
            reply.set_error(self._unreadable(message, exc))
            return
        if error is None:
            reply.set_result(value)
        elif isinstance(error, BaseException):
            reply.set_error(error)
        else:
            reply.set_error(RrError(f"a malformed answer from registrar {self.name!r}"))

    def _unreadable(self, message: Any, exc: Exception) -> RrError:
        """The error for an answer that cannot be unpickled here (a Load's id is released)."""
        failure: RrError
        if isinstance(message, _messages.Load):
            with contextlib.suppress(RrError):  # the caller gets an error: release its id
                self.tell(_messages.Abandon(message.query_id, message.origin_rr))
            failure = ResourceLoadError(
                (
                    ErrorFrame(
                        registrar=self.name,
                        server=message.server,
                        exc_type=type(exc).__qualname__,
                        message=f"the response cannot be unpickled in the process of "
                        f"registrar {message.origin_rr!r}: {exc}",
                        traceback="".join(traceback.format_exception(exc)),
                    ),
                )
            )
        else:
            failure = RrError(
                f"the answer to the {_what(message, self.name)} cannot be unpickled here: {exc}"
            )
        failure.__cause__ = exc
        return failure


class _AnswerReply:
    """The provider side's stand-in for a sender's reply: answers over the connection.

    An answer that does not pickle becomes an error answer (the caller never hangs). For a
    `Load` whose answer does not reach its caller (it does not pickle, or the caller's
    connection ends first), the consumer id it created is released again.
    """

    __slots__ = ("_done", "_link", "_message", "_token")

    def __init__(self, link: _Link, token: int, message: Any) -> None:
        self._link = link
        self._token = token
        self._message = message
        self._done = False

    def set_result(self, value: Any) -> None:
        self._answer(value, None)

    def set_error(self, error: BaseException) -> None:
        self._answer(None, error)

    def _answer(self, value: Any, error: BaseException | None) -> None:
        if self._done:
            return
        self._done = True
        try:
            frame = _frame(self._token, (value, error))
        except Exception as exc:  # noqa: BLE001 - any pickling failure becomes an error answer
            frame = _frame(self._token, (None, self._unpicklable(value, error, exc)))
            error = exc
        on_lost = None
        if error is None and isinstance(self._message, _messages.Load):
            on_lost = self._release
        if not self._link.send(frame, on_lost) and on_lost is not None:
            on_lost()

    def _release(self) -> None:
        """The answer to a Load did not reach its caller: release the consumer id."""
        message = self._message
        with contextlib.suppress(RrError):
            DIRECTORY.lookup(self._link.listener.name).tell(
                _messages.Abandon(message.query_id, message.origin_rr)
            )

    def _unpicklable(self, value: Any, error: BaseException | None, exc: Exception) -> RrError:
        message = self._message
        registrar = self._link.listener.name
        if error is not None:
            return RrError(f"{type(error).__qualname__}: {error} (the error itself did not pickle)")
        if isinstance(message, _messages.Load):
            self._release()  # its caller gets an error
            return ResourceLoadError(
                (
                    ErrorFrame(
                        registrar=registrar,
                        server=message.server,
                        exc_type=type(exc).__qualname__,
                        message=f"the response is not picklable, so it cannot reach "
                        f"registrar {message.origin_rr!r}: {exc} (value: {value!r:.200})",
                        traceback="",
                    ),
                )
            )
        kind = type(message).__name__
        return RrError(
            f"the answer of registrar {registrar!r} to a {kind} message is not picklable: {exc}"
        )


class _Link:
    """One accepted connection on the provider side; its reader runs on its own thread."""

    def __init__(self, listener: _Listener, sock: socket.socket) -> None:
        self.listener = listener
        self.sock, self.conn = _split(sock)
        self.writer = _Writer(self.sock, self._failed)

    def send(self, frame: bytes, on_lost: Lost | None = None) -> bool:
        """Send or queue an answer; False (it is dropped) if the connection is gone."""
        if self.writer.send(frame, on_lost):
            return True
        logger.debug("answer of %s dropped: the caller's connection is gone", self.listener.name)
        return False

    def close(self) -> None:
        """End the connection (any thread); the reader thread then cleans up."""
        self.writer.close()

    def _failed(self, exc: BaseException) -> None:
        logger.debug("connection to a caller of %s lost: %s", self.listener.name, exc)

    def serve(self) -> None:
        """Handshake, then deliver every message to the local registrar (its own thread)."""
        listener = self.listener
        conn = self.conn
        try:
            try:
                _set_io_timeout(conn, HANDSHAKE_TIMEOUT)
                deliver_challenge(conn, listener.authkey)
                answer_challenge(conn, listener.authkey)
                _set_io_timeout(conn, 0)
            except (AuthenticationError, EOFError, OSError) as exc:
                logger.warning("registrar %s refused a connection: %s", listener.name, exc)
                return
            self.writer.start(f"rr-answer-{listener.name}")
            for data in _frames(conn):
                try:
                    self._deliver(data)
                except Exception:
                    logger.exception("registrar %s dropped a malformed message", listener.name)
        finally:
            listener.forget(self)
            self.writer.close()
            conn.close()

    def _deliver(self, data: bytes) -> None:
        """Unpickle one frame and hand the message to the local registrar."""
        name = self.listener.name
        token, payload = _unframe(data)
        try:
            message = pickle.loads(payload)
        except Exception as exc:  # noqa: BLE001 - answered as an error, never raised here
            if token != _NO_REPLY:
                error = RrError(f"a message for registrar {name!r} cannot be unpickled: {exc}")
                self.send(_frame(token, (None, error)))
            return
        reply = None
        if token != _NO_REPLY:
            if not hasattr(message, "reply"):
                error = RrError(
                    f"a {type(message).__name__} message for registrar {name!r} cannot be answered"
                )
                self.send(_frame(token, (None, error)))
                return
            reply = _AnswerReply(self, token, message)
            object.__setattr__(message, "reply", reply)  # a fresh copy, ours to fill in
        if type(message) is _Run:
            self.listener.run(message)
            return
        try:
            DIRECTORY.lookup(name).tell(message)
        except Exception as exc:
            if reply is None:
                raise
            reply.set_error(exc if isinstance(exc, RrError) else RrError(f"{exc!r}"))


def _take_name_lock(path: str, name: str) -> int:
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


class _Listener:
    """Accepts connections for one registrar served by this process.

    It holds the name's lock file for as long as it listens, so the socket path is its own:
    a socket left there by a process that died can be unlinked without asking anyone.
    """

    def __init__(self, system: AttachedSystem, registrar: ResourceRegistrar) -> None:
        self.name = registrar.name
        self.registrar = registrar
        self.authkey = system.address.authkey
        self.path = system.address.socket_path(self.name)
        self.tombstone = system.address.tombstone_path(self.name)
        self._lock = threading.Lock()
        self._closing = threading.Lock()  # a second close waits for the first to finish
        self._links: set[_Link] = set()
        self._closed = False
        self._lock_fd = _take_name_lock(system.address.lock_path(self.name), self.name)
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.path)  # left behind by a process that died
            self._sock.bind(self.path)
            self._sock.listen(64)
        except OSError as exc:
            self._sock.close()
            os.close(self._lock_fd)
            raise ConfigError(f"cannot listen on {self.path!r}: {exc}") from exc
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.tombstone)
        threading.Thread(target=self._accept, name=f"rr-listen-{self.name}", daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                sock, _ = self._sock.accept()
            except OSError:
                return  # closed
            sock.setblocking(True)
            link = _Link(self, sock)
            with self._lock:
                if self._closed:
                    link.close()
                    link.conn.close()
                    return
                self._links.add(link)
            threading.Thread(target=link.serve, name=f"rr-link-{self.name}", daemon=True).start()

    def forget(self, link: _Link) -> None:
        with self._lock:
            self._links.discard(link)

    def run(self, message: _Run) -> None:
        """Run a control function on a fresh thread (it may block; it is rare)."""
        reply = message.reply
        assert reply is not None

        def task() -> None:
            try:
                result = message.fn(self.registrar)
            except BaseException as exc:  # noqa: BLE001 - the caller gets it
                reply.set_error(exc)
            else:
                reply.set_result(result)

        threading.Thread(target=task, name=f"rr-run-{self.name}", daemon=True).start()

    def close(self, *, stopped: bool) -> None:
        """Stop listening; with `stopped`, leave a tombstone so peers say "stopped".

        Two threads may close it at once (the registrar's watcher and the system's
        `close`): the second returns only once the first has finished, so a process that
        exits right after its own `close` never leaves the socket without its tombstone
        (the watcher is a daemon thread, cut short by the exit).
        """
        with self._closing:
            self._close(stopped=stopped)

    def _close(self, *, stopped: bool) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            links = list(self._links)
            self._links.clear()
        if stopped:
            with contextlib.suppress(OSError), open(self.tombstone, "w"):
                pass
        with contextlib.suppress(OSError):
            os.unlink(self.path)
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_RDWR)
        self._sock.close()
        os.close(self._lock_fd)  # last: the path is free for the next owner only now
        for link in links:
            link.close()


class AttachedSystem:
    """This process's membership of a system: the resolver, the peers and the listeners.

    Get one with [`attach`][rr_actors._transport.attach] (or `System.create`, which
    attaches the creating process).
    """

    def __init__(self, address: SystemAddress) -> None:
        self.address = address
        self.closed = False
        self._lock = threading.Lock()
        self._peers: dict[str, RemotePeer] = {}
        self._listeners: dict[str, _Listener] = {}
        DIRECTORY.add_resolver(self._resolve)

    def serve(self, registrar: ResourceRegistrar) -> None:
        """Make a registrar of this process reachable from the other processes of the system.

        Listening stops by itself when the registrar stops or dies. Serving a name again
        (a registrar restarted in this process) replaces the old listener.

        Args:
            registrar: a running registrar of this process.

        Raises:
            DuplicateNameError: a living process of the system already serves that name
                (it holds the `flock` on `<runtime_dir>/<name>.lock`).
            ConfigError: the socket path is too long or cannot be bound, or the lock
                file cannot be opened.
            RegistrarStoppedError: the system was closed.
        """
        name = registrar.name
        path = self.address.socket_path(name)
        if len(os.fsencode(path)) > _MAX_SOCKET_PATH:
            raise ConfigError(
                f"socket path {path!r} for registrar {name!r} is longer than "
                f"{_MAX_SOCKET_PATH} bytes; use a shorter runtime_dir or name"
            )
        with self._lock:
            if self.closed:
                raise RegistrarStoppedError("the system was closed")
            old = self._listeners.pop(name, None)
            peer = self._peers.pop(name, None)
        if old is not None:
            old.close(stopped=False)
        if peer is not None:
            peer.close(RegistrarUnavailableError(f"registrar {name!r} moved into this process"))
        listener = _Listener(self, registrar)
        with self._lock:
            self._listeners[name] = listener
        threading.Thread(
            target=self._watch, args=(registrar, listener), name=f"rr-watch-{name}", daemon=True
        ).start()

    def run(
        self, registrar_name: str, fn: Callable[[ResourceRegistrar], Any], *, timeout: float
    ) -> Any:
        """Run `fn(registrar)` where registrar `registrar_name` lives and return the result.

        For a registrar served by this process, `fn` runs in the calling thread;
        otherwise see [`RemotePeer.run`][rr_actors._transport.RemotePeer.run].

        Raises:
            UnknownServerError: no registrar of that name is served on the system.
            CallTimeoutError: no result within `timeout` seconds.
            RegistrarUnavailableError: its process died or cannot be reached.
            RegistrarStoppedError: it was stopped.
        """
        with self._lock:
            listener = self._listeners.get(registrar_name)
        if listener is not None:
            return fn(listener.registrar)
        peer = self._resolve(registrar_name)
        if peer is None:
            raise UnknownServerError(f"no registrar named {registrar_name!r} on this system")
        assert isinstance(peer, RemotePeer)
        return peer.run(fn, timeout=timeout)

    def close(self) -> None:
        """Leave the system: stop listening, close every connection (idempotent).

        Answers still outstanding fail with `RegistrarStoppedError`. Registrars are not
        stopped; stop them first.
        """
        with self._lock:
            if self.closed:
                return
            self.closed = True
            listeners = list(self._listeners.values())
            peers = list(self._peers.values())
            self._listeners.clear()
            self._peers.clear()
        DIRECTORY.remove_resolver(self._resolve)
        for listener in listeners:
            listener.close(stopped=_stopped_cleanly(listener.registrar))
        for peer in peers:
            peer.close(RegistrarStoppedError("this process closed its system"))
        with _ATTACHED_LOCK:
            if _ATTACHED.get(self.address.runtime_dir) is self:
                del _ATTACHED[self.address.runtime_dir]

    def __enter__(self) -> AttachedSystem:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    # -- plumbing ------------------------------------------------------------------------

    def _resolve(self, name: str) -> Peer | None:
        """The directory resolver: a peer for a registrar of another process, or None."""
        peer = self._peers.get(name)
        if peer is not None:
            return peer
        if self.closed or name in self._listeners:
            return None  # served here: the directory's own record says stopped or died
        if not (
            os.path.exists(self.address.socket_path(name))
            or os.path.exists(self.address.tombstone_path(name))
        ):
            return None
        with self._lock:
            return self._peers.setdefault(name, RemotePeer(self, name))

    def _watch(self, registrar: ResourceRegistrar, listener: _Listener) -> None:
        registrar._ref.actor_stopped.wait()  # the transport watches the registrar's actor
        # Close before letting go: while it is still listed, the system's own close()
        # finds it and waits for this close to finish (a process may exit right after).
        listener.close(stopped=_stopped_cleanly(registrar))
        with self._lock:
            if self._listeners.get(listener.name) is listener:
                del self._listeners[listener.name]


def _stopped_cleanly(registrar: ResourceRegistrar) -> bool:
    """Whether `registrar` was stopped by its owner (not crashed, not still running)."""
    if registrar.is_alive():
        return False
    return isinstance(DIRECTORY.gone_error(registrar.name), RegistrarStoppedError)


_ATTACHED: dict[str, AttachedSystem] = {}
_ATTACHED_LOCK = threading.Lock()


def attach(address: SystemAddress) -> AttachedSystem:
    """Join the system at `address` from this process (idempotent per process).

    Installs the directory resolver, so registrars of this process reach the system's
    registrars in other processes by name.

    Returns:
        This process's `AttachedSystem` for that address (the same one if already attached).
    """
    with _ATTACHED_LOCK:
        attached = _ATTACHED.get(address.runtime_dir)
        if attached is None or attached.closed:
            attached = AttachedSystem(address)
            _ATTACHED[address.runtime_dir] = attached
        return attached


class System(AttachedSystem):
    """A system of registrars across processes, as its owner (the main process) holds it.

    It is an `AttachedSystem` of the creating process; `close()` also removes the files the
    system put in the runtime directory, and the directory itself if `create` made it.
    Hand `address` to the processes that should join.
    """

    _made_dir = False

    @classmethod
    def create(cls, runtime_dir: str | None = None) -> System:
        """Create the private runtime directory and a random authkey, and attach.

        Args:
            runtime_dir: directory to use (created with mode 0700 if missing; an existing
                one must belong to this user and is made 0700, and `close()` leaves it and
                whatever else it holds in place); default: a fresh temporary directory.

        Raises:
            ConfigError: `runtime_dir` cannot be used.
        """
        if runtime_dir is None:
            runtime_dir = tempfile.mkdtemp(prefix="rr-")  # mode 0700
            made = True
        else:
            try:
                made = not os.path.isdir(runtime_dir)
                os.makedirs(runtime_dir, mode=0o700, exist_ok=True)
                if os.stat(runtime_dir).st_uid != os.getuid():
                    raise ConfigError(f"runtime_dir {runtime_dir!r} belongs to another user")
                os.chmod(runtime_dir, 0o700)
            except OSError as exc:
                raise ConfigError(f"runtime_dir {runtime_dir!r} cannot be used: {exc}") from exc
        address = SystemAddress(os.path.abspath(runtime_dir), os.urandom(32))
        with _ATTACHED_LOCK:
            system = cls(address)
            system._made_dir = made
            _ATTACHED[address.runtime_dir] = system
        return system

    def close(self) -> None:
        """Leave the system and remove its files (idempotent).

        Removes the sockets, tombstones and lock files of the runtime directory, then the
        directory itself if `create` made it and nothing else is left in it.
        """
        super().close()
        directory = self.address.runtime_dir
        with contextlib.suppress(OSError):
            for entry in os.listdir(directory):
                if entry.endswith(_RUNTIME_SUFFIXES):
                    with contextlib.suppress(OSError):
                        os.unlink(os.path.join(directory, entry))
        if self._made_dir:
            try:
                os.rmdir(directory)
            except FileNotFoundError:
                pass
            except OSError as exc:
                logger.debug("runtime directory %s kept: %s", directory, exc)
