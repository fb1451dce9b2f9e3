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

from rr_actors._transport.codec import Oversized, frames, unframe
from rr_actors._transport.messenger import Remote, Replies
from rr_actors._transport.unix.rendezvous import Member
from rr_actors._transport.unix.sockets import connect, read_limit
from rr_actors._transport.unix.writer import Writer
from rr_actors.config import DEFAULT_MAX_MESSAGE_BYTES
from rr_actors.errors import RegistrarStoppedError, RegistrarUnavailableError, RrError

__all__ = ["RemotePeer"]

logger = logging.getLogger("rr_actors")


class _Channel:
    """One connection from this process to a remote registrar: the peer's `Route`.

    `pending` holds the replies pending for an answer on it (the messenger's `Replies`:
    each is answered, or failed when the channel is lost, exactly once). `limit` is the
    target's `max_message_bytes`, both ways.
    """

    __slots__ = ("limit", "peer", "pending", "reading", "writer")

    def __init__(
        self,
        writer: Writer,
        limit: int = DEFAULT_MAX_MESSAGE_BYTES,
        peer: RemotePeer | None = None,
    ) -> None:
        self.writer = writer
        self.limit = limit
        self.peer = peer
        self.pending = Replies()
        self.reading: Connection | None = None  # the reader thread's (a duplicate descriptor)

    def send(self, data: bytes) -> bool:
        """Write or queue a frame (`Writer.send`); False if the connection is gone."""
        return self.writer.send(data)

    def broken(self) -> bool:
        """Nothing of a frame left: close the channel (what waits fails); a fresh one may
        take the frame."""
        if self.peer is not None:
            self.peer._lose(self, None)
        return True


class RemotePeer(Remote):
    """A registrar in another process of the system, reached through its socket (`tell`,
    `run`: `Remote`; its route is one connection).

    It connects lazily (one connection per target per process, made on the
    connection's writer thread) and is safe from any thread: a frame is written only if
    the socket takes it at once, otherwise it is queued for the connection's writer
    thread, which also connects (the handshake is bounded by `HANDSHAKE_TIMEOUT`).
    Answers are read by one daemon thread per connection, which resolves the kept
    replies.
    """

    def __init__(self, system: Member, name: str) -> None:
        self.name = name
        self._system = system
        self._path = system.address.socket_path(name)
        self._lock = threading.Lock()
        self._channel: _Channel | None = None

    def route(self) -> _Channel:
        """The connection, or a new one whose writer thread connects."""
        channel = self._channel
        if channel is None or channel.writer.closed:
            channel = self._open()
        return channel

    def gone(self) -> RrError:
        return self._gone("lost its connection")

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
            writer = Writer(None, lambda exc: self._failed(fresh, exc), f"rr-write-{self.name}")
            fresh = _Channel(writer, limit, self)
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
        """Close `channel` and fail every reply still pending on it (any thread)."""
        channel.writer.close()
        with self._lock:
            if self._channel is channel:
                self._channel = None
        channel.pending.fail(
            None, error or (lambda: self._gone("died while answers were outstanding"))
        )

    def _read(self, channel: _Channel, conn: Connection) -> None:
        """The reader thread of one connection: resolve answers until it ends.

        An answer that cannot be unpickled here fails its reply; the message's
        `compensation()` (a `Load`'s: an `Abandon` of its consumer id) goes back to the
        peer, since the caller gets an error instead of what it asked for (`Replies`).
        """
        pending = channel.pending
        try:
            for data in frames(conn, channel.limit):
                try:
                    if isinstance(data, Oversized):
                        pending.too_large(data.token, data.size)
                    else:
                        pending.answered(*unframe(data))
                except Exception:
                    logger.exception("dropped a malformed answer from registrar %s", self.name)
        finally:
            self._lose(channel, None)
            conn.close()
            if not self._system.closed:
                self._system.peer_ended(self.name)  # (is it lost? rule 19)
