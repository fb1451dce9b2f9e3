"""An asyncio event loop on the simulation: coroutine callbacks in virtual time.

```
 runtime.new_event_loop() ─► SimulatedEventLoop (a process's own loop: `_core.loops`)
 its thread (a simulated one): run_forever ─► _run_once, asyncio's own:
   the ready callbacks, the timers due by loop.time() (the virtual clock)
   _selector.select(timeout) ─► no file to watch: wait on a simulated Event for at most
                                 `timeout` virtual seconds (None: until woken)
 any simulated thread: call_soon_threadsafe ─► _write_to_self ─► that Event is set
 the scheduler, when another task runs: asyncio's running loop is the task's own
 the run's end (`close_all`): its tasks dropped, every loop it made is closed
```

It fills asyncio's private hooks `_selector.select`, `_process_events` and
`_write_to_self` (CPython 3.11 to 3.14; elsewhere `new_event_loop` raises
`SimulationError`). It cannot watch a file or socket (`NotImplementedError`), run a
subprocess, or run on a real thread (`run_in_executor`). The policy's "current" loop
(`asyncio.get_event_loop()` where none runs) is the OS thread's, not each task's.
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
from typing import Any

from rr_actors.simulation import _primitives as sim
from rr_actors.simulation._scheduler import Scheduler, SimulationError, _quiet

__all__ = ["SimulatedEventLoop", "close_all", "new_event_loop"]

_HOOKS = ("_run_once", "_process_events", "_write_to_self")
"""What `BaseEventLoop` must have for a simulated loop (see the module docstring)."""


class _Selector:
    """No file to watch: `select` waits on a simulated event, woken from any simulated
    thread (`SimulatedEventLoop._write_to_self`), for at most `timeout` virtual seconds."""

    __slots__ = ("_woken",)

    def __init__(self, sched: Scheduler) -> None:
        self._woken = sim.Event(sched)

    def select(self, timeout: float | None) -> list[Any]:
        if timeout is None or timeout > 0:
            self._woken.wait(timeout)
        self._woken.clear()
        return []

    def wake(self) -> None:
        self._woken.set()

    def close(self) -> None:
        """(Nothing to close: no file is watched.)"""


class SimulatedEventLoop(asyncio.BaseEventLoop):
    """An asyncio event loop whose clock is the simulation's and whose wait is a
    simulated thread's (see the module docstring). Made by `runtime.new_event_loop()`
    in a simulated run."""

    def __init__(self, sched: Scheduler) -> None:
        super().__init__()
        self._sched = sched
        self._selector = _Selector(sched)

    def time(self) -> float:
        """The loop's clock: the simulation's virtual seconds."""
        return self._sched.now

    def _process_events(self, event_list: list[Any]) -> None:
        """(No file is watched: nothing to process.)"""

    def _write_to_self(self) -> None:
        self._selector.wake()

    def run_in_executor(  # type: ignore[override]  # (typeshed's generic signature)
        self, executor: Any, func: Any, *args: Any
    ) -> Any:
        """Refused: a real thread would leave the simulation (`asyncio.to_thread` too).

        Raises:
            NotImplementedError: always.
        """
        raise NotImplementedError(
            "a simulated event loop runs no callback on a real thread (run_in_executor, "
            "asyncio.to_thread): it would not be simulated"
        )

    def close(self) -> None:
        super().close()
        self._selector.close()


def new_event_loop(sched: Scheduler) -> SimulatedEventLoop:
    """A new simulated event loop (the `runtime.new_event_loop` seam in a simulation).

    Raises:
        SimulationError: this Python's asyncio lacks a hook the loop needs (a CPython
            outside 3.11-3.14): coroutine callbacks cannot be simulated here.
    """
    missing = [hook for hook in _HOOKS if not hasattr(asyncio.BaseEventLoop, hook)]
    if missing:
        raise SimulationError(
            f"coroutine callbacks cannot be simulated on Python "
            f"{sys.version.split()[0]}: its asyncio.BaseEventLoop has no "
            f"{', '.join(missing)} (rr_actors.simulation._loop)"
        )
    loop = SimulatedEventLoop(sched)
    sched.loops.append(loop)
    return loop


def close_all(sched: Scheduler) -> None:
    """Close the loops of a run that is over, pending coroutines first (their `finally`
    unlogged)."""
    for loop in sched.loops:
        if loop.is_closed() or loop.is_running():
            continue
        with _quiet():
            for task in asyncio.all_tasks(loop):
                task._log_destroy_pending = False  # type: ignore[attr-defined]  # (closed here)
                with contextlib.suppress(BaseException):  # (a finally that waits again)
                    task.get_coro().close()
        loop.close()
    sched.loops.clear()
