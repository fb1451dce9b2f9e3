"""The send side of one connection: frames leave in order, and a sender never blocks.

A sender writes a frame itself when nothing is queued and the socket takes all of it at
once (`MSG_DONTWAIT`); otherwise the frame is queued for the connection's writer thread,
the only thread that may block on a peer that does not read. A frozen peer therefore
stalls only its own writer thread; callers still time out on their own timeouts.
"""

from __future__ import annotations

import logging
import socket
import threading
from collections.abc import Callable

from rr_actors._core.serial import SerialExecutor
from rr_actors._transport.messenger import Lost, run_lost
from rr_actors._transport.unix.sockets import shutdown

__all__ = ["Lost", "Writer", "run_lost"]

logger = logging.getLogger("rr_actors")


class Writer:
    """The send side of one connection: frames leave in the order they were sent.

    A sender writes a frame itself when nothing is queued or being written and the
    socket takes all of it without blocking (`MSG_DONTWAIT`); otherwise the frame (or the
    part the socket did not take) is queued for the connection's writer thread (a
    `SerialExecutor`, started when a frame first waits), the only thread that may block
    on a peer that does not read. A failed connect or a failed write of the writer
    thread closes the writer and calls `on_failure(exc)` once; a sender whose own write
    fails gets False from `send` and cleans up itself. The socket is closed after the
    last write (`shutdown` at `close` ends a blocked one).
    """

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
        self._executor = SerialExecutor(name, on_drop=_lost, on_end=self._close_socket)

    @property
    def closed(self) -> bool:
        """Whether the writer was closed (nothing more is sent)."""
        return self._closed

    def send(self, frame: bytes, on_lost: Lost | None = None) -> bool:
        """Send `frame` or queue it (never blocks on the peer).

        Returns:
            True if the frame was sent or queued (if the connection ends before it is
            sent, `on_lost` runs); False if the writer was closed or the connection broke
            just now (the writer is then closed): nothing of the frame was sent.
        """
        if self._closed:
            return False
        task = _Frame(self, frame, on_lost)
        try:
            return self._executor.submit(task, inline=task.now if self._sock else None)
        except OSError as exc:
            logger.debug("a send failed, the connection is closed: %s", exc)
            self.close()  # the caller cleans up: it knows what it was sending
            return False

    def connect_with(self, connect: Callable[[], object]) -> None:
        """Run `connect` first on the writer thread of a writer made without a socket; it
        gives the socket with `attach` (or fails the writer)."""
        self._executor.submit(connect)

    def attach(self, sock: socket.socket) -> bool:
        """Give a writer made without a socket its connected socket; False if closed."""
        with self._lock:
            if self._closed:
                return False
            self._sock = sock
            return True

    def close(self) -> bool:
        """Stop sending and end the connection; queued frames are lost (their `on_lost`
        runs). False if it was closed already.

        The socket is shut down (here, and after the last write before it is closed,
        whichever comes first), so a thread reading a duplicate of its descriptor wakes
        and the peer reads the end at once.
        """
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
        """In a forked child: close this process's copy of the socket, send nothing more.

        Never `shutdown`: the socket is the parent's too, and a shutdown would end it for
        the parent. Takes no lock (a thread of the parent may have held it at the fork).
        """
        self._closed = True
        self._lock = threading.Lock()
        self._executor = SerialExecutor(self._executor.name)
        self._executor.finish()
        if self._sock is not None:
            self._sock.close()

    def fail(self, exc: BaseException) -> None:
        """Close because of `exc` (a failed connect or write) and report it once."""
        if self.close():
            self._on_failure(exc)

    def _close_socket(self) -> None:  # (after the last write: the executor's `on_end`)
        if self._sock is not None:
            # shut down before closing, here too: were it closed first, a shutdown after
            # would fail (EBADF) and the reader's duplicate descriptor would keep the
            # connection open: the peer would never see its end
            shutdown(self._sock)
            self._sock.close()


class _Frame:
    """One frame to send (or the part of it the socket did not take at once)."""

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

    def __call__(self) -> None:
        """Send it all (the writer thread: may block on the peer)."""
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


def _lost(task: object) -> None:
    if isinstance(task, _Frame) and task.on_lost is not None:
        run_lost([task.on_lost])
