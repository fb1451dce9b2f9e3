"""How processes are forked from this one: what a forked child lets go of, and a forkserver
of rr_actors' own.

Each layer with process-wide state says at its import how a forked child lets go of it
(`after_fork_in_child`: one `os.register_at_fork` hook, lowest layer first); a child that
cannot go on is refused (`refuse`, `check_usable`), never left to time out
(docs/explanation/failure-semantics.md, "A forked child starts afresh"). Manager processes
are forked by a second instance of CPython's `ForkServer`, so its preload holds even when
the program started CPython's first, and within a bound (`start_within`):

```
 caller (ManagerProcess.start, Spare.start)      rr_actors' server           child
   start_within(process, s) ─► _launch:
     connect, send the pipes' fds ──────────────►  accept, fork ───────────►  (forked)
     poll(sentinel, s) ◄───── pid ──────────────   write pid
     write(pickled process, s) ─────────────────────────────────────────►  read, run
   s ran out: TimeoutError; no pid yet: write _Unwanted ────────────────►  (later) exit 0
              the pid, the write unfinished: SIGKILL ───────────────────►  killed
```

CPython's private forkserver names are used in this file only, checked on 3.11 to 3.13
(`SUPPORTED`); elsewhere `context` returns `None` (CPython's forkserver, unbounded).
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
from collections.abc import Callable, Sequence
from multiprocessing.process import BaseProcess
from typing import Any

from rr_actors.errors import ConfigError

_resets: list[tuple[str, Callable[[], None]]] = []
_refusals: list[str] = []
_parent: int | None = None  # the pid of the process this one was forked from
_forking: int | None = None  # this process's pid, noted just before it forks


def after_fork_in_child(what: str, reset: Callable[[], None]) -> None:
    """Have `reset()` run in every child forked from this process, on its only thread, before its
    own code. Call it once per piece of state, at import; `what` names it in a refusal. A reset
    replaces locks, closes (never shuts down) sockets, joins nothing; what it raises refuses
    the child.
    """
    _resets.append((what, reset))


def refuse(reason: str) -> None:
    """Say that this forked child cannot run rr_actors (`reason` ends "the process it was forked
    from ...")."""
    _refusals.append(reason)


def forked_from() -> int | None:
    """The pid of the process this one was forked from (after it ran rr_actors), else `None`."""
    return _parent


def check_usable(what: str) -> None:
    """`ConfigError` (naming `spawn` and `forkserver`) if this process was forked from one whose
    state it cannot use; `what` is what is being started.
    """
    if _refusals:
        raise ConfigError(
            f"cannot start {what}: this process was forked from process {_parent}, which "
            f"{'; and '.join(_refusals)}; a forked child cannot use that. Start the process "
            f"with the 'spawn' or 'forkserver' method instead "
            f"(multiprocessing.get_context('spawn') or get_context('forkserver'))"
        )


def _before() -> None:
    global _forking  # (one process-wide hook)
    _forking = os.getpid()


def _after_in_child() -> None:
    global _parent  # (one process-wide hook)
    _parent = _forking if _forking is not None else os.getppid()
    for what, reset in _resets:
        try:
            reset()
        except Exception as exc:  # noqa: BLE001 - the child is refused, not half reset
            refuse(f"left {what} in a state the child could not reset ({exc!r})")


os.register_at_fork(before=_before, after_in_child=_after_in_child)


# -- rr_actors' own forkserver --------------------------------------------------------------


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

        def poll(self, flag: int = os.WNOHANG) -> int | None:
            if self.returncode is None and self._reading.acquire(blocking=flag != os.WNOHANG):
                try:  # one reader (a join, `_cleanup` at a start): a second's EOF read 255
                    return super().poll(flag)
                finally:
                    self._reading.release()
            return self.returncode

        def _launch(self, process_obj: Any) -> None:
            # CPython 3.11-3.13's `Popen._launch`: this server, within `start_within`'s bound
            self._reading = threading.Lock()  # (held by the thread that reads its exit)
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
            self.finalizer = _util.Finalize(self, _util.close_fds, (parent_w, self.sentinel))  # type: ignore[attr-defined]
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
    """`process.start()` through this file's server within `seconds`, else `TimeoutError` (nothing
    is left running); with another context, unbounded.
    """
    _bound.deadline = time.monotonic() + seconds
    try:
        process.start()
    finally:
        _bound.deadline = None


def context(preload: Sequence[str]) -> Any:
    """The forkserver context of rr_actors' own, its server preloading `preload` (read when the
    server starts), or `None` where not `SUPPORTED`.
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


def forget_server(server: Any) -> None:
    """In a forked child: make `server` (a CPython `ForkServer`) new; the parent's is not the
    child's child. Its copy of the "alive" pipe is closed: the server ends with the parent."""
    server._lock = threading.Lock()  # a thread of the parent may have held it at the fork
    if server._forkserver_pid is None:
        return  # none was started (or a forkserver's child: it let go already)
    fd = getattr(server, "_forkserver_alive_fd", None)
    if isinstance(fd, int):
        with contextlib.suppress(OSError):
            os.close(fd)
    server._forkserver_alive_fd = None
    server._forkserver_pid = None
    server._forkserver_address = None
    server._inherited_fds = None


def forget_in_child() -> None:
    """In a forked child: this process's server is the parent's; the next manager starts one."""
    global _LOCK  # a thread of the parent may have held it at the fork
    _LOCK = threading.Lock()
    if _context is not None:
        forget_server(_context.server)
