"""The outbound side of the AF_UNIX carrier: a channel to a registrar of another process.

One connection per target per process, made lazily on the connection's writer thread;
answers are read by one daemon thread per connection, which resolves the kept replies.
Each connection is bounded by the target's `max_message_bytes`, read from the file its
listener publishes when the connection is made: a larger message is refused before
anything of it is sent, a larger answer is skipped unread.
When the connection ends (the peer died or its registrar stopped), every answer still
outstanding on it fails at once: that is how a dead peer is seen, not by a timeout.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import threading
from multiprocessing import AuthenticationError
from multiprocessing.connection import Connection
from typing import Any

from rr_actors._core.directory import Reply
from rr_actors._transport.codec import Oversized, frames, unframe
from rr_actors._transport.messenger import Remote, Replies, check_size, encode
from rr_actors._transport.unix.rendezvous import Member
from rr_actors._transport.unix.sockets import connect, read_limit
from rr_actors._transport.unix.writer import Writer
from rr_actors.config import DEFAULT_MAX_MESSAGE_BYTES
from rr_actors.errors import RegistrarStoppedError, RegistrarUnavailableError, RrError

__all__ = ["RemotePeer"]

logger = logging.getLogger("rr_actors")


class _Channel:
    """One connection from this process to a remote registrar and its outstanding answers.

    `pending` holds the replies waiting for an answer on it (the messenger's `Replies`:
    each is answered, or failed when the channel is lost, exactly once). `limit` is the
    target's `max_message_bytes`, both ways.
    """

    __slots__ = ("limit", "pending", "reading", "writer")

    def __init__(
        self,
        writer: Writer,
        limit: int = DEFAULT_MAX_MESSAGE_BYTES,
        pending: Replies | None = None,
    ) -> None:
        self.writer = writer
        self.limit = limit
        self.pending = pending if pending is not None else Replies(lambda _name, _m: None)
        self.reading: Connection | None = None  # the reader thread's (a duplicate descriptor)


class RemotePeer(Remote):
    """A registrar in another process of the system, reached through its socket (`run`:
    `Remote`).

    `tell` is what the registrar code calls for every message; it connects lazily (one
    connection per target per process, made on the connection's writer thread) and is
    safe from any thread. Answers are read by one daemon thread per connection, which
    resolves the kept replies.
    """

    def __init__(self, system: Member, name: str) -> None:
        self.name = name
        self._system = system
        self._path = system.address.socket_path(name)
        self._lock = threading.Lock()
        self._channel: _Channel | None = None

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
            MessageTooLargeError: pickled, it is larger than the remote registrar's
                `max_message_bytes`; nothing of it was sent.
            RegistrarUnavailableError: the registrar's process is known to be unreachable.
            RegistrarStoppedError: it was stopped, or this process closed the system.
        """
        outgoing = encode(self.name, message)
        reply = outgoing.reply
        for _attempt in (1, 2):
            channel = self._channel
            if channel is None or channel.writer.closed:
                channel = self._open()
            check_size(outgoing, self.name, channel.limit)
            if reply is not None:
                channel.pending.expect(outgoing, self.name, channel.limit)
            if channel.writer.send(outgoing.data):
                return
            # The connection was lost before anything of the frame left: unless its loss
            # already failed the reply, send once more on a fresh connection.
            ours = reply is None or channel.pending.forget(outgoing.token)
            self._lose(channel, None)
            if not ours:
                return
        raise self._gone("lost its connection")

    def close(self, error: RrError) -> None:
        """Close the connection; outstanding answers fail with `error`."""
        channel = self._channel
        if channel is not None:
            self._lose(channel, error)

    def connect(self) -> None:
        """Open a connection now if there is none (its end is then seen: rule 19)."""
        with contextlib.suppress(RrError):
            self._open()

    def forget_in_child(self) -> None:
        """In a forked child: drop the parent's connection (its threads are not here).

        This process's copies of its descriptors are closed, never shut down (that would
        end the parent's connection); its replies are the parent's callers' and are
        dropped. The next `tell` connects anew, from the child. Takes no lock.
        """
        self._lock = threading.Lock()
        channel, self._channel = self._channel, None
        if channel is None:
            return
        channel.pending.clear()
        channel.writer.forget_in_child()
        if channel.reading is not None:
            channel.reading.close()

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
                self._system.peer_ended(self.name)  # (is it lost? rule 19)
                raise self._gone("cannot be reached (it does not listen)")
            limit = read_limit(self._system.address.limit_path(self.name))
            pending = Replies(lambda _name, message: self.tell(message))
            writer = Writer(None, lambda exc: self._failed(fresh, exc), f"rr-write-{self.name}")
            fresh = _Channel(writer, limit, pending)
            writer.connect_with(functools.partial(self._connect, fresh))  # (its first task)
            self._channel = channel = fresh
        return channel

    def _connect(self, channel: _Channel) -> None:
        """The writer thread of `channel`, first: connect, start its reader."""
        try:
            sock, conn = connect(self._path, self._system.address.authkey)
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
        threading.Thread(
            target=self._read, args=(channel, conn), name=f"rr-read-{self.name}", daemon=True
        ).start()

    def _failed(self, channel: _Channel, exc: BaseException) -> None:
        """`channel`'s writer failed (connect or write): fail what waits on it."""
        if isinstance(exc, RrError):
            self._lose(channel, exc)
        else:
            self._lose(channel, self._gone("lost its connection", exc))
        if not self._system.closed:
            self._system.peer_ended(self.name)  # (is it lost? rule 19)

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
        failed: list[Reply] = channel.pending.take()
        if not failed:
            return
        error = error or self._gone("died while answers were outstanding")
        for reply in failed:
            reply.set_error(error)

    def _read(self, channel: _Channel, conn: Connection) -> None:
        """The reader thread of one connection: resolve answers until it ends."""
        try:
            for data in frames(conn, channel.limit):
                try:
                    if isinstance(data, Oversized):
                        self._too_large(channel, data)
                    else:
                        self._answer(channel, data)
                except Exception:
                    logger.exception("dropped a malformed answer from registrar %s", self.name)
        finally:
            self._lose(channel, None)
            conn.close()
            if not self._system.closed:
                self._system.peer_ended(self.name)  # (is it lost? rule 19)

    def _too_large(self, channel: _Channel, oversized: Oversized) -> None:
        """An answer over the limit was skipped unread: fail its reply, undo what it made."""
        channel.pending.too_large(oversized.token, oversized.size)

    def _answer(self, channel: _Channel, data: bytes | bytearray) -> None:
        """Resolve the reply waiting for one answer frame (reader thread).

        An answer that cannot be unpickled here fails it; the message's `compensation()`
        (a `Load`'s: an `Abandon` of its consumer id) goes back to the peer, since the
        caller gets an error instead of what it asked for.
        """
        token, payload = unframe(data)
        channel.pending.answered(token, payload)
