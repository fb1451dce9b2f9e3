"""The inbound side of the AF_UNIX carrier: a registrar's listener and its connections.

The listener holds the name's lock file for as long as it listens, so the socket path is
its own. Each accepted connection passes the authkey handshake on a thread of its own
before anything it sends is unpickled; then every message is told to the local
registrar with a stand-in reply that answers over the same connection.
"""

from __future__ import annotations

import contextlib
import logging
import os
import pickle
import socket
import threading
from multiprocessing import AuthenticationError
from multiprocessing.connection import answer_challenge, deliver_challenge
from typing import TYPE_CHECKING, Any

from rr_actors._core.directory import DIRECTORY
from rr_actors._transport.base import Endpoint
from rr_actors._transport.codec import NO_REPLY, Run, frame, frames, unframe
from rr_actors._transport.sockets import (
    HANDSHAKE_TIMEOUT,
    set_io_timeout,
    split,
    take_name_lock,
)
from rr_actors._transport.writer import Lost, Writer
from rr_actors.errors import ConfigError, RrError

if TYPE_CHECKING:
    from rr_actors._transport.unix import AttachedSystem

__all__ = ["Listener"]

logger = logging.getLogger("rr_actors")


class _AnswerReply:
    """The provider side's stand-in for a sender's reply: answers over the connection.

    An answer that does not pickle becomes an error answer (the caller never hangs). When
    a successful answer does not reach its caller (it does not pickle, or the caller's
    connection ends first), the message's `compensation()` is told to the local
    registrar: for a `Load`, the consumer id it created is released again.
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
            data = frame(self._token, (value, error))
        except BaseException as exc:  # noqa: BLE001 - any pickling failure (SystemExit from a
            # user __reduce__ too) becomes an error answer
            data = frame(self._token, (None, self._unpicklable(value, error, exc)))
            error = exc
        on_lost = self._compensate if error is None else None
        if not self._link.send(data, on_lost) and on_lost is not None:
            on_lost()

    def _compensate(self) -> None:
        """The answer did not reach its caller: undo what handling the message created."""
        compensation = self._message.compensation()
        if compensation is not None:
            with contextlib.suppress(RrError):
                DIRECTORY.lookup(self._link.listener.name).tell(compensation)

    def _unpicklable(self, value: Any, error: BaseException | None, exc: BaseException) -> RrError:
        if error is not None:
            return RrError(f"{type(error).__qualname__}: {error} (the error itself did not pickle)")
        self._compensate()  # its caller gets an error
        failure: RrError = self._message.unsendable_answer(self._link.listener.name, value, exc)
        return failure


class _Link:
    """One accepted connection on the provider side; its reader runs on its own thread."""

    def __init__(self, listener: Listener, sock: socket.socket) -> None:
        self.listener = listener
        self.sock, self.conn = split(sock)
        self.writer = Writer(self.sock, self._failed)

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
                set_io_timeout(conn, HANDSHAKE_TIMEOUT)
                deliver_challenge(conn, listener.authkey)
                answer_challenge(conn, listener.authkey)
                set_io_timeout(conn, 0)
            except (AuthenticationError, EOFError, OSError) as exc:
                logger.warning("registrar %s refused a connection: %s", listener.name, exc)
                return
            self.writer.start(f"rr-answer-{listener.name}")
            for data in frames(conn):
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
        token, payload = unframe(data)
        try:
            message = pickle.loads(payload)
        except BaseException as exc:  # noqa: BLE001 - answered as an error, never raised here
            if token != NO_REPLY:
                error = RrError(f"a message for registrar {name!r} cannot be unpickled: {exc}")
                self.send(frame(token, (None, error)))
            return
        reply = None
        if token != NO_REPLY:
            if not hasattr(message, "reply"):
                error = RrError(
                    f"a {type(message).__name__} message for registrar {name!r} cannot be answered"
                )
                self.send(frame(token, (None, error)))
                return
            reply = _AnswerReply(self, token, message)
            object.__setattr__(message, "reply", reply)  # a fresh copy, ours to fill in
        if type(message) is Run:
            self.listener.run(message)
            return
        try:
            DIRECTORY.lookup(name).tell(message)
        except Exception as exc:
            if reply is None:
                raise
            reply.set_error(exc if isinstance(exc, RrError) else RrError(f"{exc!r}"))


class Listener:
    """Accepts connections for one registrar served by this process.

    It holds the name's lock file for as long as it listens, so the socket path is its own:
    a socket left there by a process that died can be unlinked without asking anyone.
    """

    def __init__(self, system: AttachedSystem, endpoint: Endpoint) -> None:
        self.name = endpoint.name
        self.endpoint = endpoint
        self.authkey = system.address.authkey
        self.path = system.address.socket_path(self.name)
        self.tombstone = system.address.tombstone_path(self.name)
        self._lock = threading.Lock()
        self._closing = threading.Lock()  # a second close waits for the first to finish
        self._links: set[_Link] = set()
        self._closed = False
        self._lock_fd = take_name_lock(system.address.lock_path(self.name), self.name)
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

    def run(self, message: Run) -> None:
        """Run a control function on a fresh thread (it may block; it is rare)."""
        reply = message.reply
        assert reply is not None

        def task() -> None:
            try:
                result = self.endpoint.run(message.fn)
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
