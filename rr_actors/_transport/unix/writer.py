"""The send side of one connection: frames leave in order, and a sender never blocks.

A sender writes a frame itself when nothing is queued and the socket takes all of it at
once (`MSG_DONTWAIT`); otherwise the frame is queued for the connection's writer thread,
the only thread that may block on a peer that does not read. A frozen peer therefore
stalls only its own writer thread; callers still time out on their own timeouts.
"""

from __future__ import annotations

import collections
import logging
import socket
import threading
from collections.abc import Callable

from rr_actors._transport.messenger import Lost, run_lost
from rr_actors._transport.unix.sockets import shutdown

__all__ = ["Lost", "Writer", "run_lost"]

logger = logging.getLogger("rr_actors")


class Writer:
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
            run_lost([on_lost])
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
            shutdown(sock)
            if close_here:
                sock.close()
        run_lost(lost)
        return True

    def forget_in_child(self) -> None:
        """In a forked child: close this process's copy of the socket, send nothing more.

        Never `shutdown`: the socket is the parent's too, and a shutdown would end it for
        the parent. Takes no lock (a thread of the parent may have held it at the fork).
        """
        self.closed = True
        self._cond = threading.Condition(threading.Lock())
        self._queue.clear()
        if self._sock is not None:
            self._sock.close()

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
                        run_lost([on_lost for _, on_lost in batch[index:] if on_lost])
                        self.fail(exc)
                        return
                with self._cond:
                    self._busy = False
        finally:
            with self._cond:
                while self._busy:  # a sender still writes inline: let it finish first
                    self._cond.wait()
            sock.close()
