"""The run process's end of the trigger process (`_trigger.py`), which sends a run's signals.

`_trigger.py` is the trigger process itself (standard library only, so that it starts in
tens of milliseconds); this is the handle the injector uses: it starts that process,
hands it pidfds with their due times, and reads its replies on a thread of its own.
"""

from __future__ import annotations

import contextlib
import errno
import itertools
import logging
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable

from rr_actors.experiments import _trigger

__all__ = ["Trigger"]

logger = logging.getLogger("rr_actors.experiments")


class Trigger:
    """The run process's end of the trigger process (`_trigger.py`), which sends signals.

    `send` hands it a pidfd, a signal and a due time; `on_sent(sent_at, errno)` is called
    on this object's reader thread when the signal went out (or could not: `errno`).
    """

    def __init__(self) -> None:
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            self._process = subprocess.Popen(  # noqa: S603 - this interpreter, our own script
                [sys.executable, "-I", _trigger.__file__, str(theirs.fileno())],
                pass_fds=(theirs.fileno(),),
                stdin=subprocess.DEVNULL,
            )
        finally:
            theirs.close()
        self._sock = ours
        self._seq = itertools.count(1)
        self._lock = threading.Lock()
        self._idle = threading.Condition(self._lock)
        self._pending: dict[int, Callable[[float, int], None]] = {}
        self._reader = threading.Thread(target=self._read, name="rr-trigger", daemon=True)
        self._reader.start()

    def send(
        self, due: float, signum: int, pidfd: int, on_sent: Callable[[float, int], None]
    ) -> None:
        """Send `signum` through (a copy of) `pidfd` at monotonic time `due`."""
        seq = next(self._seq)
        with self._lock:
            self._pending[seq] = on_sent
        message = _trigger.REQUEST.pack(seq, due, int(signum))
        try:
            socket.send_fds(self._sock, [message], [pidfd])
        except OSError as exc:
            with self._lock:
                self._pending.pop(seq, None)
            on_sent(0.0, exc.errno or errno.EIO)

    def close(self, *, timeout: float) -> None:
        """Wait (bounded) for the replies still due, then end the trigger process."""
        deadline = time.monotonic() + timeout
        with self._idle:
            while self._pending and time.monotonic() < deadline:
                self._idle.wait(max(0.0, deadline - time.monotonic()))
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_RDWR)
        self._reader.join(timeout)
        self._sock.close()
        try:
            self._process.wait(timeout)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()

    def _read(self) -> None:
        while True:
            try:
                data = self._sock.recv(_trigger.REPLY.size)
            except OSError:
                data = b""
            if len(data) < _trigger.REPLY.size:
                break
            seq, sent_at, code = _trigger.REPLY.unpack(data)
            with self._lock:
                on_sent = self._pending.pop(seq, None)
            if on_sent is not None:
                try:
                    on_sent(sent_at, code)
                except Exception:
                    logger.exception("recording a fault failed")
            with self._idle:
                self._idle.notify_all()
        with self._idle:  # the trigger is gone: what it did not answer was not sent
            pending, self._pending = self._pending, {}
            self._idle.notify_all()
        for on_sent in pending.values():
            on_sent(0.0, errno.ESRCH)
