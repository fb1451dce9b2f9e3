"""The inbound side of the AF_UNIX carrier: a registrar's listener and its connections.

The listener holds the name's lock file for as long as it listens, so the socket path is
its own. Each accepted connection passes the authkey handshake on a thread of its own
(all of it within `HANDSHAKE_TIMEOUT` seconds of the accept) before anything it sends is
unpickled; then every message is told to the local registrar with a stand-in reply that
answers over the same connection. The accept thread survives running out of file
descriptors: it backs off and tries again, and reports how long it has been unable to
accept (`Listener.trouble`) for the manager's heartbeat answer.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import os
import socket
import threading
import time
from multiprocessing import AuthenticationError

from rr_actors._transport.base import Endpoint
from rr_actors._transport.codec import Oversized, frames, unframe
from rr_actors._transport.messenger import Lost, Messenger
from rr_actors._transport.unix.rendezvous import Member
from rr_actors._transport.unix.sockets import (
    HANDSHAKE_TIMEOUT,
    handshake,
    publish_limit,
    split,
    take_name_lock,
)
from rr_actors._transport.unix.writer import Writer
from rr_actors.errors import ConfigError, DuplicateNameError

__all__ = ["Listener"]

logger = logging.getLogger("rr_actors")


class _Link:
    """One accepted connection on the provider side; its reader runs on its own thread.

    Raises:
        OSError: no file descriptor is left for its reading side (`EMFILE`, ...).
    """

    def __init__(self, listener: Listener, sock: socket.socket, deadline: float) -> None:
        self.listener = listener
        self.deadline = deadline  # for the whole handshake
        self.sock, self.conn = split(sock)
        self.writer = Writer(self.sock, self._failed, f"rr-answer-{listener.name}")

    def send(self, frame: bytes, on_lost: Lost | None = None) -> bool:
        """Send or queue an answer; False (it is dropped) if the connection is gone."""
        if self.writer.send(frame, on_lost):
            return True
        logger.debug("answer of %s dropped: the caller's connection is gone", self.listener.name)
        return False

    def close(self) -> None:
        """End the connection (any thread); the reader thread then cleans up."""
        self.writer.close()

    def forget_in_child(self) -> None:
        """In a forked child: close this process's copies of the descriptors (not shut
        down: the connection is the parent's)."""
        self.writer.forget_in_child()
        self.conn.close()

    def _failed(self, exc: BaseException) -> None:
        logger.debug("connection to a caller of %s lost: %s", self.listener.name, exc)

    def serve(self) -> None:
        """Handshake, then deliver every message to the local registrar (its own thread).

        The whole handshake must be done within `HANDSHAKE_TIMEOUT` seconds of the accept:
        a peer that trickles it byte by byte is cut off at that deadline.
        """
        listener = self.listener
        conn = self.conn
        try:
            try:
                handshake(self.sock, listener.authkey, self.deadline, server=True)
            except (AuthenticationError, EOFError, OSError) as exc:
                logger.warning("registrar %s refused a connection: %s", listener.name, exc)
                return
            messenger, endpoint = listener.messenger, listener.endpoint
            for data in frames(conn, listener.max_message_bytes):
                try:
                    if isinstance(data, Oversized):
                        messenger.oversized(endpoint, self, data.token, data.size)
                    else:
                        messenger.message(endpoint, self, *unframe(data))
                except Exception:
                    logger.exception("registrar %s dropped a malformed message", listener.name)
        finally:
            self.writer.close()
            conn.close()
            listener.forget(self)


class _OnTheConnection:
    """The AF_UNIX carrier's `Link`: an answer goes back on the connection its message
    came on (the `process` a listener names with each message is its `_Link`)."""

    def answer_to(self, process: _Link, data: bytes, on_lost: Lost | None) -> bool:
        return process.send(data, on_lost)


_MESSENGER = Messenger(_OnTheConnection())


LOCK_RETRY = 0.2
"""Seconds a listener keeps trying to take a name lock that is held: another process may
be probing it for a few microseconds (`unix._lock_held`, rule 19), which is no owner."""


def _take_lock(path: str, name: str) -> int:
    """`take_name_lock`, retried for `LOCK_RETRY` seconds while it is held."""
    deadline = time.monotonic() + LOCK_RETRY
    pause = 0.002
    while True:
        try:
            return take_name_lock(path, name)
        except DuplicateNameError:
            if time.monotonic() >= deadline:
                raise
        time.sleep(pause)  # (a probe is over in microseconds; an owner stays)
        pause = min(2 * pause, 0.05)


def _publish(path: str, text: str) -> None:
    """Write `text` to `path` atomically (a temporary file renamed over it)."""
    folder, name = os.path.split(path)
    temporary = os.path.join(folder, f".{name}")
    fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.write(fd, text.encode("ascii"))
    finally:
        os.close(fd)
    os.replace(temporary, path)


_SHORTAGE = frozenset({errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM})
"""`accept` errors that mean "out of resources for now": back off and try again."""

_BACKOFF_FIRST = 0.01
_BACKOFF_MAX = 0.5
"""Seconds the listener waits before it retries an `accept` that failed (doubling).

Well below `HANDSHAKE_TIMEOUT`: a peer waiting in the backlog meanwhile still gets
through once descriptors are free again."""


class Listener:
    """Accepts connections for one registrar served by this process.

    It holds the name's lock file for as long as it listens, so the socket path is its own:
    a socket left there by a process that died can be unlinked without asking anyone.

    Its accept thread outlives failures: when `accept` fails for lack of resources (the
    process is out of file descriptors: `EMFILE`), it logs once, waits (exponential
    backoff, cut short when one of its connections ends) and tries again, while peers
    wait in the backlog. [`trouble`][rr_actors._transport.unix.inbound.Listener.trouble] says
    for how long it has been unable to accept, so a manager process can report it with
    its heartbeat answer and its supervisor restart a manager that stays unable to.
    """

    def __init__(self, system: Member, endpoint: Endpoint) -> None:
        self.name = endpoint.name
        self.endpoint = endpoint
        self.messenger = _MESSENGER
        self.max_message_bytes = endpoint.max_message_bytes
        self.authkey = system.address.authkey
        self.path = system.address.socket_path(self.name)
        self.tombstone = system.address.tombstone_path(self.name)
        self._lock = threading.Lock()
        self._closing = threading.Lock()  # a second close waits for the first to finish
        self._links: set[_Link] = set()
        self._closed = False
        self._wake = threading.Event()  # a connection ended, or the listener closes
        self._failing_since: float | None = None  # monotonic time of the first failed accept
        self._failure = ""
        self._lock_fd = _take_lock(system.address.lock_path(self.name), self.name)
        self.limit_path = system.address.limit_path(self.name)
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            publish_limit(self.limit_path, self.max_message_bytes)  # before anyone connects
            # who speaks for it if this process dies (rule 19), kept after it ends
            _publish(system.address.restart_path(self.name), system.supervisor(self.name))
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

    def trouble(self) -> tuple[float, str] | None:
        """For how long (seconds) and why it has been unable to accept; `None` if it can.

        Infinite seconds if its accept thread died (it never comes back by itself).
        """
        since = self._failing_since
        if since is None:
            return None
        return time.monotonic() - since, self._failure

    def _accept(self) -> None:
        try:
            self._accept_until_closed()
        except BaseException as exc:  # a bug: say so, and let the heartbeat report it
            self._failing_since = -math.inf
            self._failure = f"its accept thread died: {exc!r}"
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
                self._cannot_accept(exc, backoff)
                backoff = min(2 * backoff, _BACKOFF_MAX)
                continue
            deadline = time.monotonic() + HANDSHAKE_TIMEOUT
            try:
                link = _Link(self, sock, deadline)
            except OSError as exc:  # no descriptor for its reading side
                sock.close()
                self._cannot_accept(exc, backoff)
                backoff = min(2 * backoff, _BACKOFF_MAX)
                continue
            if self._failing_since is not None:
                self._accepting_again()
            backoff = _BACKOFF_FIRST
            with self._lock:
                if self._closed:
                    link.close()
                    link.conn.close()
                    return
                self._links.add(link)
            try:
                threading.Thread(
                    target=link.serve, name=f"rr-link-{self.name}", daemon=True
                ).start()
            except RuntimeError as exc:  # no thread for it (a limit on threads): as EMFILE
                self.forget(link)
                link.close()
                link.conn.close()
                self._cannot_accept(OSError(errno.EAGAIN, f"no thread: {exc}"), backoff)
                backoff = min(2 * backoff, _BACKOFF_MAX)

    def _cannot_accept(self, exc: OSError, backoff: float) -> None:
        """Note a failed accept (log the first of a run), then wait before the next."""
        if self._failing_since is None:
            self._failing_since = time.monotonic()
            self._failure = f"{type(exc).__name__}: {exc}"
            with self._lock:
                open_links = len(self._links)
            logger.warning(
                "registrar %s cannot accept connections (%s; %d open): retrying",
                self.name,
                exc,
                open_links,
            )
        if exc.errno not in _SHORTAGE:
            logger.debug("registrar %s: accept failed: %s", self.name, exc)
        self._wake.clear()
        self._wake.wait(backoff)  # cut short when a connection ends or the listener closes

    def _accepting_again(self) -> None:
        trouble = self.trouble()
        self._failing_since = None
        if trouble is not None:
            logger.info(
                "registrar %s accepts connections again after %.3f s", self.name, trouble[0]
            )

    def forget(self, link: _Link) -> None:
        with self._lock:
            self._links.discard(link)
        self._wake.set()  # its descriptors are free: a listener backing off tries again

    def forget_in_child(self) -> None:
        """In a forked child: let go of the parent's listener without touching it.

        Closes this process's copies of the listening socket, of the name lock's
        descriptor (a lock shared with a child would outlive the parent: its peers would
        think the name still served) and of every connection. Unlike `close`, nothing is
        shut down, unlinked or written: the socket, the lock and the files are the
        parent's, which still serves the name. Takes no lock.
        """
        self._closed = True
        links = list(self._links)
        self._links.clear()
        self._lock = threading.Lock()
        self._closing = threading.Lock()
        self._sock.close()
        with contextlib.suppress(OSError):
            os.close(self._lock_fd)
        for link in links:
            link.forget_in_child()

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
        for link in links:
            link.close()
