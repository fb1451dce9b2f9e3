"""How messages cross processes: authenticated channels between the registrars of a system.

A *system* is a private runtime directory (mode 0700) plus a random authkey. Every process
that takes part [`attach`][rr_actors._transport.attach]es it; each registrar it
[`serve`][rr_actors._transport.AttachedSystem.serve]s listens on
`<runtime_dir>/<registrar>.sock` (AF_UNIX). Another process reaches that registrar through a
[`RemotePeer`][rr_actors._transport.RemotePeer], which the directory resolver hands out
for names that are not registered locally, so the registrar code sends a `Load` the same
way whether its target lives in this process or another one.

Wire format: one frame per message, `8-byte token (little endian) + cloudpickle payload`.
A message's `reply` never crosses: the sender keeps it in a table under the token (0: no
answer wanted) and the receiver substitutes a reply that sends `token + pickle((value,
error))` back over the same connection. Nothing is unpickled from a connection before it
passed the authkey handshake (`multiprocessing.connection.deliver_challenge` /
`answer_challenge`, run per connection on its own thread, bounded by a timeout).

Failure: when a connection ends (the peer process died or its registrar stopped), every
answer still outstanding on it fails at once with `RegistrarUnavailableError` (or
`RegistrarStoppedError` if the registrar was stopped cleanly); the next message connects
again, so a restarted registrar that binds the same path is reached. Low-level errors
(`EOFError`, `BrokenPipeError`, `ConnectionResetError`, `OSError`, pickling errors) are
translated into rr_actors errors with `raise ... from exc` and never reach a caller.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import itertools
import logging
import os
import pickle
import shutil
import socket
import struct
import tempfile
import threading
from collections.abc import Callable
from multiprocessing import AuthenticationError
from multiprocessing.connection import Connection, answer_challenge, deliver_challenge
from typing import TYPE_CHECKING, Any

import cloudpickle

from rr_actors import _messages
from rr_actors._directory import DIRECTORY, Peer, Reply
from rr_actors._replies import FutureReply, wait
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
"""Seconds a connecting peer gets to pass the authkey handshake (both sides)."""

_MAX_SOCKET_PATH = 107  # sun_path is 108 bytes with the terminating NUL (Linux)
_NO_REPLY = 0
_TOKEN = struct.Struct("<Q")


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


def _frame(token: int, obj: Any) -> bytes:
    """`token` + cloudpickle of `obj`; pickling errors propagate."""
    buffer = io.BytesIO()
    buffer.write(_TOKEN.pack(token))
    _Pickler(buffer, protocol=pickle.HIGHEST_PROTOCOL).dump(obj)
    return buffer.getvalue()


def _unframe(data: bytes) -> tuple[int, memoryview]:
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


def _shutdown(conn: Connection) -> None:
    """Wake a thread blocked reading `conn` (close alone does not, on Linux), then close."""
    with contextlib.suppress(OSError), socket.socket(fileno=os.dup(conn.fileno())) as sock:
        sock.shutdown(socket.SHUT_RDWR)
    with contextlib.suppress(OSError):
        conn.close()


def _connect(path: str, authkey: bytes) -> Connection:
    """Connect to `path` and pass the handshake; raises OSError / AuthenticationError."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.setblocking(True)
        sock.connect(path)
        conn = Connection(sock.detach())
    finally:
        sock.close()
    try:
        _set_io_timeout(conn, HANDSHAKE_TIMEOUT)
        answer_challenge(conn, authkey)
        deliver_challenge(conn, authkey)
        _set_io_timeout(conn, 0)
    except BaseException:
        conn.close()
        raise
    return conn


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


@dataclasses.dataclass(frozen=True)
class _Run:
    """Control request: run `fn(registrar)` in the registrar's process, answer its result."""

    fn: Callable[[ResourceRegistrar], Any]
    reply: Reply | None


_BY_REFERENCE = _BY_REFERENCE | {_Run}


class _Channel:
    """One connection from this process to a remote registrar and its outstanding answers."""

    __slots__ = ("closed", "conn", "pending")

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        self.pending: dict[int, tuple[Reply, Any]] = {}
        self.closed = False


class RemotePeer:
    """A registrar in another process of the system, reached through its socket.

    `tell` is what the registrar code calls for every message; it connects lazily (one
    connection per target per process) and is safe from any thread. Answers are read by
    one daemon thread per connection, which resolves the kept replies.
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

        Raises:
            ConfigError: the message (say, the request of a call) cannot be pickled.
            RegistrarUnavailableError: the registrar's process is not reachable (it died).
            RegistrarStoppedError: it was stopped, or this process closed the system.
        """
        reply: Reply | None = getattr(message, "reply", None)
        if reply is not None:
            message = dataclasses.replace(message, reply=None)
        with self._lock:
            token = next(self._tokens) if reply is not None else _NO_REPLY
        try:
            frame = _frame(token, message)
        except Exception as exc:
            raise ConfigError(f"{_what(message, self.name)} is not picklable: {exc}") from exc
        for attempt in (1, 2):
            with self._lock:
                channel = self._channel
                if channel is None or channel.closed:
                    channel = self._open()
                if reply is not None:
                    channel.pending[token] = (reply, message)
                try:
                    channel.conn.send_bytes(frame)
                except OSError as exc:  # the peer went away before the reader noticed it
                    channel.pending.pop(token, None)
                    failed = self._detach(channel)
                    error: BaseException = exc
                else:
                    return
            self._fail(failed)
            if attempt == 2:
                raise self._gone("lost its connection", error) from error
            # nothing was delivered: send once more on a fresh connection

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
        with self._lock:
            channel = self._channel
            failed = [] if channel is None else self._detach(channel)
        self._fail(failed, error)

    # -- plumbing (the lock is held where noted) ----------------------------------------

    def _open(self) -> _Channel:
        """Connect (lock held)."""
        if self._system.closed:
            raise RegistrarStoppedError(f"the system of registrar {self.name!r} was closed")
        try:
            conn = _connect(self._path, self._system.address.authkey)
        except AuthenticationError as exc:
            raise RegistrarUnavailableError(
                f"registrar {self.name!r} refused this process's authkey"
            ) from exc
        except (OSError, EOFError) as exc:
            raise self._gone("cannot be reached", exc) from exc
        channel = _Channel(conn)
        self._channel = channel
        threading.Thread(
            target=self._read, args=(channel,), name=f"rr-to-{self.name}", daemon=True
        ).start()
        return channel

    def _gone(self, how: str, cause: BaseException | None = None) -> RrError:
        if os.path.exists(self._system.address.tombstone_path(self.name)):
            return RegistrarStoppedError(f"registrar {self.name!r} was stopped")
        detail = f" ({type(cause).__name__}: {cause})" if cause is not None else ""
        return RegistrarUnavailableError(f"registrar {self.name!r} {how}{detail}")

    def _detach(self, channel: _Channel) -> list[Reply]:
        """Mark `channel` dead, close it, return the replies waiting on it (lock held)."""
        if channel.closed:
            return []
        channel.closed = True
        if self._channel is channel:
            self._channel = None
        _shutdown(channel.conn)
        failed = [reply for reply, _ in channel.pending.values()]
        channel.pending.clear()
        return failed

    def _fail(self, failed: list[Reply], error: RrError | None = None) -> None:
        """Fail the replies of a lost connection (lock not held)."""
        if not failed:
            return
        error = error or self._gone("died while answers were outstanding")
        for reply in failed:
            reply.set_error(error)

    def _read(self, channel: _Channel) -> None:
        """The reader thread of one connection: resolve answers until it ends."""
        conn = channel.conn
        while True:
            try:
                data = conn.recv_bytes()
            except (EOFError, OSError):
                break
            token, payload = _unframe(data)
            entry = channel.pending.pop(token, None)
            if entry is None:
                continue
            reply, message = entry
            try:
                value, error = pickle.loads(payload)
            except Exception as exc:  # noqa: BLE001 - any unpickling failure fails this answer
                failure = RrError(
                    f"the answer to the {_what(message, self.name)} cannot be unpickled here: {exc}"
                )
                failure.__cause__ = exc
                reply.set_error(failure)
                continue
            if error is None:
                reply.set_result(value)
            else:
                reply.set_error(error)
        with self._lock:
            failed = self._detach(channel)
        self._fail(failed)


class _AnswerReply:
    """The provider side's stand-in for a sender's reply: answers over the connection.

    An answer that does not pickle becomes an error answer (the caller never hangs); for
    a `Load`, the consumer id it created is released again, since its caller got an error.
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
        self._link.send(frame)

    def _unpicklable(self, value: Any, error: BaseException | None, exc: Exception) -> RrError:
        message = self._message
        registrar = self._link.listener.name
        if error is not None:
            return RrError(f"{type(error).__qualname__}: {error} (the error itself did not pickle)")
        if isinstance(message, _messages.Load):
            with contextlib.suppress(RrError):  # release the consumer id its caller lost
                DIRECTORY.lookup(registrar).tell(
                    _messages.Abandon(message.query_id, message.origin_rr)
                )
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
    """One accepted connection on the provider side (its reader runs on its own thread)."""

    def __init__(self, listener: _Listener, conn: Connection) -> None:
        self.listener = listener
        self.conn = conn
        self.lock = threading.Lock()

    def send(self, frame: bytes) -> None:
        try:
            with self.lock:
                self.conn.send_bytes(frame)
        except OSError:
            logger.debug(
                "answer of %s dropped: the caller's connection is gone", self.listener.name
            )

    def serve(self) -> None:
        """Handshake, then deliver every message to the local registrar (its own thread)."""
        listener = self.listener
        conn = self.conn
        try:
            _set_io_timeout(conn, HANDSHAKE_TIMEOUT)
            deliver_challenge(conn, listener.authkey)
            answer_challenge(conn, listener.authkey)
            _set_io_timeout(conn, 0)
        except (AuthenticationError, EOFError, OSError) as exc:
            logger.warning("registrar %s refused a connection: %s", listener.name, exc)
            listener.forget(self)
            _shutdown(conn)
            return
        name = listener.name
        while True:
            try:
                data = conn.recv_bytes()
            except (EOFError, OSError):
                break
            token, payload = _unframe(data)
            try:
                message = pickle.loads(payload)
            except Exception as exc:  # noqa: BLE001 - answered as an error, never raised here
                if token != _NO_REPLY:
                    error = RrError(f"a message for registrar {name!r} cannot be unpickled: {exc}")
                    self.send(_frame(token, (None, error)))
                continue
            reply = None
            if token != _NO_REPLY:
                reply = _AnswerReply(self, token, message)
                object.__setattr__(message, "reply", reply)  # a fresh copy, ours to fill in
            if type(message) is _Run:
                listener.run(message)
                continue
            try:
                DIRECTORY.lookup(name).tell(message)
            except RrError as exc:
                if reply is not None:
                    reply.set_error(exc)
        listener.forget(self)
        _shutdown(conn)


class _Listener:
    """Accepts connections for one registrar served by this process."""

    def __init__(self, system: AttachedSystem, registrar: ResourceRegistrar) -> None:
        self.name = registrar.name
        self.registrar = registrar
        self.authkey = system.address.authkey
        self.path = system.address.socket_path(self.name)
        self.tombstone = system.address.tombstone_path(self.name)
        self._lock = threading.Lock()
        self._links: set[_Link] = set()
        self._closed = False
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            self._sock.bind(self.path)
            self._sock.listen(64)
        except OSError as exc:
            self._sock.close()
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
            link = _Link(self, Connection(sock.detach()))
            with self._lock:
                if self._closed:
                    _shutdown(link.conn)
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
        """Stop listening; with `stopped`, leave a tombstone so peers say "stopped"."""
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
        for link in links:
            _shutdown(link.conn)


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
            DuplicateNameError: a living process of the system already serves that name.
            ConfigError: the socket path is too long or cannot be bound.
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
        if os.path.exists(path):
            if _accepts(path):
                raise DuplicateNameError(f"registrar {name!r} is already served on this system")
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)  # left behind by a process that died
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
        stopped = _stopped_cleanly(registrar)
        with self._lock:
            if self._listeners.get(listener.name) is listener:
                del self._listeners[listener.name]
        listener.close(stopped=stopped)


def _stopped_cleanly(registrar: ResourceRegistrar) -> bool:
    """Whether `registrar` was stopped by its owner (not crashed, not still running)."""
    if registrar.is_alive():
        return False
    return isinstance(DIRECTORY.gone_error(registrar.name), RegistrarStoppedError)


def _accepts(path: str) -> bool:
    """Whether something listens on the AF_UNIX socket `path`."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        try:
            probe.connect(path)
        except OSError:
            return False
        return True


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

    It is an `AttachedSystem` of the creating process; `close()` also removes the runtime
    directory. Hand `address` to the processes that should join.
    """

    @classmethod
    def create(cls, runtime_dir: str | None = None) -> System:
        """Create the private runtime directory and a random authkey, and attach.

        Args:
            runtime_dir: directory to use (created with mode 0700 if missing; an existing
                one must belong to this user and is made 0700); default: a fresh
                temporary directory.

        Raises:
            ConfigError: `runtime_dir` cannot be used.
        """
        if runtime_dir is None:
            runtime_dir = tempfile.mkdtemp(prefix="rr-")  # mode 0700
        else:
            try:
                os.makedirs(runtime_dir, mode=0o700, exist_ok=True)
                if os.stat(runtime_dir).st_uid != os.getuid():
                    raise ConfigError(f"runtime_dir {runtime_dir!r} belongs to another user")
                os.chmod(runtime_dir, 0o700)
            except OSError as exc:
                raise ConfigError(f"runtime_dir {runtime_dir!r} cannot be used: {exc}") from exc
        address = SystemAddress(os.path.abspath(runtime_dir), os.urandom(32))
        with _ATTACHED_LOCK:
            system = cls(address)
            _ATTACHED[address.runtime_dir] = system
        return system

    def close(self) -> None:
        """Leave the system and remove its runtime directory (idempotent)."""
        super().close()
        shutil.rmtree(self.address.runtime_dir, ignore_errors=True)
