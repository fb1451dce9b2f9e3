"""The trigger: a tiny single-threaded process that sends a run's signals at their due times.

    run process (injector thread)                      trigger process (this file)
      due - PREPARE_AHEAD: look up the target,
      open a pidfd ──── (seq, due, signum) + pidfd ───► heap of due signals
                                                        wait (epoll), spin the last 0.2 ms
                                                        pidfd_send_signal ── time.monotonic()
      record the fault ◄──── (seq, sent_at, errno) ─── reply

A process because a thread of the busy run process would wait for the interpreter lock;
this one does nothing else (real-time priority when it may: `prioritise`) and imports only
the standard library. CLOCK_MONOTONIC is system-wide, so due times mean the same in both.
It exits when the run process closes its end; `Trigger` is that end.
"""

from __future__ import annotations

import contextlib
import errno
import heapq
import itertools
import logging
import os
import selectors
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable

__all__ = ["Trigger"]

logger = logging.getLogger("rr_actors.experiments")

REQUEST = struct.Struct("<Qdi")
"""seq (u64), due (monotonic seconds, f64), signal number (i32); one pidfd rides along."""

REPLY = struct.Struct("<Qdi")
"""seq, sent_at (monotonic seconds; 0 if not sent), errno (0: sent)."""

NO_REALTIME = "RR_ACTORS_NO_REALTIME"
"""Set to `1` to keep the trigger at normal scheduling priority."""

SPIN = 0.0002
"""The last seconds before a due signal are spun, not slept (a sleep can wake late)."""


def serve(sock: socket.socket) -> None:
    """Send each requested signal at its due time and reply; return when `sock` closes."""
    due: list[tuple[float, int, int, int]] = []  # (due, seq, signum, pidfd)
    with selectors.DefaultSelector() as selector:  # (not select(): fds of 1024 and up)
        selector.register(sock, selectors.EVENT_READ)
        while True:
            timeout = None if not due else max(0.0, due[0][0] - time.monotonic() - SPIN)
            if selector.select(timeout):
                message, fds, _, _ = socket.recv_fds(sock, REQUEST.size, 1)
                if not message:
                    return
                seq, at, signum = REQUEST.unpack(message)
                heapq.heappush(due, (at, seq, signum, fds[0]))
                continue
            if due[0][0] - time.monotonic() > SPIN:
                continue  # woke early: never spin longer than SPIN (this may run real-time)
            at, seq, signum, pidfd = heapq.heappop(due)
            while time.monotonic() < at:
                pass  # the last fraction of a millisecond
            try:
                signal.pidfd_send_signal(pidfd, signum)
                sent, code = time.monotonic(), 0
            except OSError as exc:
                sent, code = 0.0, exc.errno or errno.EIO
            finally:
                os.close(pidfd)
            sock.sendall(REPLY.pack(seq, sent, code))


def prioritise() -> bool:
    """Run at real-time priority if allowed (root or CAP_SYS_NICE); whether it could.

    This process sleeps, then spins at most `SPIN` seconds per signal, so a real-time
    policy costs the machine next to nothing and keeps the signals on time when every
    CPU is busy (the rest of an experiment, other programs). `RR_ACTORS_NO_REALTIME=1`
    in the environment keeps the normal policy.
    """
    if os.environ.get(NO_REALTIME) == "1":
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except (PermissionError, OSError, AttributeError):
        return False
    return True


def main() -> None:
    """`python _trigger.py FD`: serve the socket inherited as file descriptor FD."""
    prioritise()
    sock = socket.socket(fileno=int(sys.argv[1]))
    try:
        serve(sock)
    finally:
        sock.close()


class Trigger:
    """The run process's end of the trigger process: `send` hands it a pidfd, a signal and a due
    time; `on_sent(sent_at, errno)` is called on this object's reader thread."""

    def __init__(self) -> None:
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            self._process = subprocess.Popen(  # noqa: S603 - this interpreter, our own script
                [sys.executable, "-I", __file__, str(theirs.fileno())],
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
        message = REQUEST.pack(seq, due, int(signum))
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
                data = self._sock.recv(REPLY.size)
            except OSError:
                data = b""
            if len(data) < REPLY.size:
                break
            seq, sent_at, code = REPLY.unpack(data)
            with self._lock:
                on_sent = self._pending.get(seq)
            if on_sent is not None:
                try:
                    on_sent(sent_at, code)  # (may `send` again: pending until it returns)
                except Exception:
                    logger.exception("recording a fault failed")
            with self._idle:
                self._pending.pop(seq, None)
                self._idle.notify_all()
        with self._idle:  # the trigger is gone: what it did not answer was not sent
            pending, self._pending = self._pending, {}
            self._idle.notify_all()
        for on_sent in pending.values():
            on_sent(0.0, errno.ECANCELED)  # (ESRCH is the target's: it had exited)


if __name__ == "__main__":
    main()
