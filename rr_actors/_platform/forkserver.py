"""A forkserver of rr_actors' own, so that its preload holds whoever started CPython's.

What it buys: manager processes are forked from a server that has imported rr_actors
even when the program used `multiprocessing`'s forkserver first (a `forkserver` pool or
Process made before its `Supervisor`). CPython keeps one forkserver per process
(`multiprocessing.forkserver._forkserver`) and reads its preload list once, when it
starts: once the program had started it, rr_actors' `set_forkserver_preload` changed
nothing, and every manager (re)start imported rr_actors after its fork (a restart took
86-1,067 ms to serve again instead of 49-169 ms). Here a second instance of CPython's
`ForkServer` class serves manager processes only; the program's forkserver, if any, is
left alone (and never gets rr_actors' preload).

A fork through this server is bounded (`start_within`): CPython's `_launch` writes the
pickled process to the new child's pipe and then reads the child's pid from the server,
both with no bound, so a stopped server (SIGSTOP: a debugger, a hang) held the thread
that started a manager for ever. Within a bound, the pid is awaited first (one `poll`),
then the pickled process is written (a payload over the pipe's 64 KiB blocks until the
child reads it: that write is bounded too). When the bound runs out, `TimeoutError` is
raised and the pipes are closed: a child forked but not given all of its process is
killed; one the server forks later (once it runs again) is given `_Unwanted` instead
of its process and exits 0, so no late manager runs unseen.

```
 caller (ManagerProcess.start, Spare.start)      rr_actors' server           child
   start_within(process, s) ─► _launch:
     connect, send the pipes' fds ──────────────►  accept, fork ───────────►  (forked)
     poll(sentinel, s) ◄───── pid ──────────────   write pid
     write(pickled process, s) ─────────────────────────────────────────►  read, run
   s ran out: TimeoutError; no pid yet: write _Unwanted ────────────────►  (later) exit 0
              the pid, the write unfinished: SIGKILL ───────────────────►  killed
```

CPython-internal names, used in this file only: the `ForkServer` class, the forkserver
`Popen` (whose `_launch` is copied below with two changes: it asks this instance, not
the module's, and within a bound it reads the pid before it writes, each with one
`poll`), `read_signed`, `ForkServerProcess` and `ForkServerContext`, and the instance's
`_forkserver_pid`, `_forkserver_alive_fd`, `_forkserver_address`, `_inherited_fds` and
`_lock`. They are the same in CPython 3.11, 3.12 and 3.13 (`SUPPORTED`); elsewhere
`context` returns `None` and the caller uses CPython's forkserver as before (plain:
`start_within` is then `process.start()`, with no bound).
"""

from __future__ import annotations

import contextlib
import io
import os
import select
import signal
import sys
import threading
import time
from collections.abc import Sequence
from multiprocessing.process import BaseProcess
from typing import Any

__all__ = ["SUPPORTED", "context", "forget_in_child", "server_pid", "start_within"]

SUPPORTED = sys.implementation.name == "cpython" and (3, 11) <= sys.version_info[:2] <= (3, 13)
"""Whether this Python's forkserver internals are the ones this file was checked against."""

_LOCK = threading.Lock()
_context: Any = None  # the one context (and server) of this process, made at first use
_bound = threading.local()  # `deadline`: this thread's fork's (monotonic), set by `start_within`

try:
    from multiprocessing import context as _mp_context
    from multiprocessing import forkserver as _forkserver
    from multiprocessing import popen_forkserver as _popen_forkserver
    from multiprocessing import reduction as _reduction
    from multiprocessing import spawn as _spawn
    from multiprocessing import util as _util
except ImportError:  # no forkserver here (it needs fds passed over AF_UNIX)
    SUPPORTED = False
else:

    class _OwnPopen(_popen_forkserver.Popen):
        """CPython's forkserver `Popen`, asking rr_actors' server to fork."""

        def _launch(self, process_obj: Any) -> None:
            # CPython 3.11-3.13's `popen_forkserver.Popen._launch`, with rr_actors'
            # server instead of the module's, and within `start_within`'s bound
            prep_data = _spawn.get_preparation_data(process_obj._name)
            buf = io.BytesIO()
            _mp_context.set_spawning_popen(self)
            try:
                _reduction.dump(prep_data, buf)
                _reduction.dump(process_obj, buf)
            finally:
                _mp_context.set_spawning_popen(None)
            self.sentinel, w = _context.server.connect_to_new_process(self._fds)  # type: ignore[attr-defined]
            parent_w = os.dup(w)
            self.finalizer = _util.Finalize(
                self,
                _util.close_fds,  # type: ignore[attr-defined]
                (parent_w, self.sentinel),
            )
            deadline: float | None = getattr(_bound, "deadline", None)
            if deadline is None:  # CPython's order, no bound
                with open(w, "wb", closefd=True) as f:
                    f.write(buf.getbuffer())
                self.pid = _forkserver.read_signed(self.sentinel)
                return
            pid = None
            try:  # the pid first: a child forked after the bound gets EOF, not the process
                _wait(self.sentinel, select.POLLIN, deadline)
                pid = _forkserver.read_signed(self.sentinel)
                _write(w, buf.getbuffer(), deadline)
            except BaseException:
                with contextlib.suppress(OSError):
                    if pid is not None:  # forked, its process not (all) written: never to run
                        os.kill(pid, signal.SIGKILL)  # (the server reaps it)
                    else:  # the pipe is empty: if the server forks it later, it exits 0
                        os.set_blocking(w, False)
                        os.write(w, _UNWANTED)
                os.close(w)
                self.finalizer()  # the pid's pipe and the payload pipe's copy
                raise
            os.close(w)
            self.pid = pid

    class _Unwanted:
        """What a child forked after its fork's bound runs instead of its process."""

        def _bootstrap(self, parent_sentinel: Any = None) -> int:
            return 0  # (an EOF instead would print an `EOFError` traceback on its stderr)

    _UNWANTED = bytes(_reduction.ForkingPickler.dumps({})) + bytes(
        _reduction.ForkingPickler.dumps(_Unwanted())
    )
    """A child's preparation data (nothing to prepare) and `_Unwanted`: under `PIPE_BUF`."""

    class _OwnProcess(_mp_context.ForkServerProcess):
        """A process forked by rr_actors' server (pickled by reference into the child)."""

        @staticmethod
        def _Popen(process_obj: Any) -> Any:  # noqa: N802 - CPython's name
            return _OwnPopen(process_obj)

    class _OwnContext(_mp_context.ForkServerContext):
        """The forkserver context, with rr_actors' server (`server`)."""

        Process = _OwnProcess

        def __init__(self) -> None:
            super().__init__()
            self.server = _forkserver.ForkServer()

        def set_forkserver_preload(self, module_names: Sequence[str]) -> None:
            self.server.set_forkserver_preload(list(module_names))


def _wait(fd: int, event: int, deadline: float) -> None:
    """Wait until `fd` is ready for `event` (or closed at its other end), or raise."""
    poller = select.poll()
    poller.register(fd, event)
    if not poller.poll(max(0, round((deadline - time.monotonic()) * 1000))):
        raise TimeoutError("a fork through rr_actors' forkserver did not finish in time")


def _write(fd: int, data: memoryview, deadline: float) -> None:
    """Write all of `data` to the pipe `fd` by `deadline` (one `write` when it fits)."""
    os.set_blocking(fd, False)
    while data:
        try:
            data = data[os.write(fd, data) :]
        except BlockingIOError:
            _wait(fd, select.POLLOUT, deadline)


def start_within(process: BaseProcess, seconds: float) -> None:
    """`process.start()`, the fork through this file's server bounded by `seconds`.

    Raises:
        TimeoutError: the server did not fork it, or the child did not take its
            pickled process, within `seconds` (nothing is left running). Only with
            this file's context; with another, `process.start()` has no bound.
    """
    _bound.deadline = time.monotonic() + seconds
    try:
        process.start()
    finally:
        _bound.deadline = None


def context(preload: Sequence[str]) -> Any:
    """The forkserver context of rr_actors' own, its server preloading `preload`.

    The preload is read when the server starts (at its first process, or at
    `server_pid`); a later change applies only after it was restarted.

    Returns:
        The context (a `multiprocessing` forkserver context), or `None` on a Python
        whose internals were not checked (`SUPPORTED`) or without a forkserver.
    """
    global _context  # one per process, like CPython's
    if not SUPPORTED:
        return None
    with _LOCK:
        if _context is None:
            _context = _OwnContext()
        if _context.server._forkserver_pid is None:
            _context.set_forkserver_preload(preload)
        return _context


def server_pid(ctx: Any) -> int | None:
    """Start `ctx`'s server if it does not run; its pid (`None`: not this file's context)."""
    server = getattr(ctx, "server", None)
    if server is None or ctx is not _context:
        return None
    server.ensure_running()  # cheap when it runs: one waitpid(WNOHANG)
    pid = server._forkserver_pid
    return pid if isinstance(pid, int) else None


def forget_in_child() -> None:
    """In a child forked (plain `os.fork`) from this process: the server is the parent's.

    The child cannot use it (`ensure_running` waits for it with `waitpid`, and it is not
    the child's child): it is made as new (its pid, address, lock, and its copy of the
    "alive" pipe, closed); the child's next manager process starts one of its own.
    """
    global _LOCK  # a thread of the parent may have held it at the fork
    _LOCK = threading.Lock()
    if _context is None:
        return
    server = _context.server
    server._lock = threading.Lock()
    if server._forkserver_pid is None:
        return
    fd = server._forkserver_alive_fd
    if isinstance(fd, int):
        with contextlib.suppress(OSError):
            os.close(fd)  # the parent's server ends with the parent, not with the child
    server._forkserver_alive_fd = None
    server._forkserver_pid = None
    server._forkserver_address = None
    server._inherited_fds = None
