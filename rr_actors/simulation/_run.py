"""A simulated run: the runtime's seams on one scheduler, in an OS thread of its own.

```
 run(fn, seed=S) ─► a thread "rr-simulation" ─┬─ runtime.use(the simulated seams)
   (the caller waits for it, bounded)         ├─ the main process (pid 1): a fresh state of
                                              │  each runtime.process_state
                                              ├─ Scheduler.run(): fn() as the task
                                              │  "MainThread", and every thread it starts
                                              └─ the states put back, the real seams back
 ◄── Run(seed, hash, steps, elapsed, value, errors, trace): the same for the same seed
```

Once the main task and the non-daemon threads ended, the result is made, every greenlet
left is ended where it waits (`Scheduler.drop`: a suspended greenlet is never freed) and
the files every process still holds are closed: nothing of a run is left but its result.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import gc
import math
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable
from typing import Any, Generic, TypeVar

from rr_actors._core import runtime
from rr_actors._core.actor import SIGNAL_CHECK
from rr_actors.simulation import _loop, _manager
from rr_actors.simulation import _primitives as sim
from rr_actors.simulation._processes import States
from rr_actors.simulation._scheduler import Scheduler, SimulationError
from rr_actors.testing import memory

__all__ = [
    "Run",
    "kill",
    "note",
    "now",
    "pid",
    "run",
    "running_scheduler",
    "sleep",
    "start_process",
]

T = TypeVar("T")

MONOTONIC_START = 1_000.0
"""`runtime.monotonic()` when a run begins."""

WALL_START = 1_767_225_600.0
"""`runtime.wall()` when a run begins (2026-01-01 00:00 UTC)."""

_scheduler: Scheduler | None = None  # the run in progress (one at a time per process)


@dataclasses.dataclass(frozen=True)
class Run(Generic[T]):
    """What a simulated run gave: the same, hash included, for the same seed.

    Attributes:
        seed: the seed it ran with.
        hash: the hash of its trace (each step's task and virtual time, and each `note`).
        steps: how many times the scheduler switched to a task.
        elapsed: the virtual seconds it took.
        value: what `fn` returned.
        errors: the exceptions that ended simulated threads (`name: Type: message`).
        trace: each step, `(virtual seconds, task number, task name or note)`, if asked.
    """

    seed: int
    hash: str
    steps: int
    elapsed: float
    value: T
    errors: tuple[str, ...]
    trace: tuple[tuple[float, int, str], ...] | None


def run(
    fn: Callable[[], T],
    *,
    seed: int,
    preempt: float = 0.05,
    until: float = 3_600.0,
    max_steps: int = 5_000_000,
    trace: bool = False,
    timeout: float | None = 300.0,
) -> Run[T]:
    """Run `fn()` on a simulated world: every thread a greenlet of one OS thread, chosen
    by a scheduler seeded with `seed`, on a virtual clock.

    The run ends when `fn` and every non-daemon thread it started returned; daemon threads
    still waiting then (an actor's loop) are dropped.

    Args:
        fn: the run's main task (the simulated process's main thread).
        seed: the seed of the scheduler's choices and of every random value.
        preempt: the probability that a thread yields at a choice point (an operation
            that would not block): 0 runs each thread until it blocks.
        until: virtual seconds the run may last.
        max_steps: switches the run may take.
        trace: keep each step in `Run.trace`, not only its hash.
        timeout: real seconds the caller waits for the run (`None`: no bound).

    Returns:
        The run's seed, trace hash, steps, virtual time, `fn`'s value and thread errors.

    Raises:
        DeadlockError: nothing could run and nothing was due before `fn` returned.
        LimitError: past `until` or `max_steps`.
        SimulationError: the run did not end within `timeout` real seconds (its thread
            blocks for real; the process should end), or a simulation already runs.
        BaseException: what `fn` raised (with the seed in a note and `simulated_at`); or
            what interrupted the caller's wait (`KeyboardInterrupt`), once the cancelled
            run ended (within `CANCEL_TIMEOUT` seconds).
    """
    if runtime.simulated():
        raise SimulationError("a simulation already runs in this process (one at a time)")

    made: list[Scheduler] = []
    interrupted: list[bool] = []  # (the run's `cancelled`: non-empty once its caller was)

    def make() -> Scheduler:
        made.append(
            Scheduler(
                seed,
                preempt=preempt,
                locals=runtime.thread_locals(),
                states=States(runtime.process_states()),
                max_steps=max_steps,
                until=until,
                trace=trace,
                cancelled=interrupted,
            )
        )
        return made[0]

    outcome: list[Any] = []
    ended = _Ended()  # (not `join`: an interrupted join marks a running thread ended)
    thread = threading.Thread(
        target=_simulate,
        args=(make, fn, outcome, ended),
        name=f"rr-simulation-{seed}",
        daemon=True,
    )
    try:
        thread.start()  # (its run may be interrupted before `start` returns)
        ended.wait(timeout)
    except BaseException:  # a Ctrl-C (or a SIGTERM raised as one): the run ends first
        # a second interrupt pending with the first (a test's timeout with a Ctrl-C) is
        # raised at the next call's end or a Python call's entry: first the cancel, a list's
        # append (done before that end), then the wait, made again if that interrupt cut it
        # (CI, stop 78: it skipped the cancel, and the run went on after its caller for good)
        try:
            interrupted.append(True)
            _wait_ended(thread, ended, CANCEL_TIMEOUT)
        except BaseException:  # noqa: BLE001 - the second: the first is raised after
            _wait_ended(thread, ended, CANCEL_TIMEOUT)
        raise
    if ended.done:
        thread.join()  # (it only returns now)
    else:
        interrupted.append(True)  # (a run only long, not blocked for real, ends)
        frame = sys._current_frames().get(thread.ident or 0)
        stack = "".join(traceback.format_stack(frame)) if frame is not None else ""
        raise SimulationError(
            f"the simulation (seed {seed}) did not end within {timeout:g} real seconds: its "
            f"thread blocks for real (its runtime stays simulated; end the process):\n{stack}"
        )
    gone = sum(not p.alive for p in made[0].processes) if made else 0
    made.clear()  # (the run's last reference: its garbage can go)
    _collect_the_ended(gone)
    ok, done = outcome
    if not ok:
        raise done
    finished: Run[T] = done
    return finished


CANCEL_TIMEOUT = 30.0
"""Real seconds an interrupted caller of `run` waits for the run to end (it is cancelled:
the scheduler's `cancelled`), its greenlets' `finally` blocks and the runtime's seams put
back."""


def _wait_ended(thread: threading.Thread, ended: _Ended, timeout: float) -> None:
    """Wait up to `timeout` seconds for the run's `thread` to end (`ended`, then its
    return), through further interrupts (a second Ctrl-C must not leave the run going
    while its caller removes its folder)."""
    deadline = time.monotonic() + timeout
    while not ended.done and (left := deadline - time.monotonic()) > 0:
        try:
            ended.wait(left)
        except BaseException:  # noqa: BLE001, S112 - the first interrupt is raised after
            continue
    if ended.done:
        with contextlib.suppress(BaseException):  # (it returns at once: `ended`)
            thread.join(max(0.0, deadline - time.monotonic()))


class _Ended:
    """Set once by the run's thread as it ends; waited for by the run's caller, through its
    interrupts. A raw lock, not a `threading.Event`: a signal handler's exception (a Ctrl-C,
    a test's timeout) raised inside `Event.wait` can cut `Condition.wait`'s own `finally`
    in half, and the next wait on it hung (1 run in 4 of an interrupted run, under xdist)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._lock.acquire()  # (released by `set`)
        self.done = False

    def set(self) -> None:
        self.done = True
        self._lock.release()

    def wait(self, timeout: float | None) -> bool:
        """Whether the run's thread ended, within `timeout` seconds (`None`: no bound; 0 or
        less: now, as `Event.wait`), in `SIGNAL_CHECK` slices: a signal that came as the
        caller went to wait is handled at a slice's end (CPython handles it once the call
        returns), not at the wait's (CI, stop 78: a SIGINT then waited for a test's timeout,
        which came with it and cut the cancel)."""
        end = math.inf if timeout is None else time.monotonic() + timeout
        while not self.done:
            left = min(SIGNAL_CHECK, end - time.monotonic())
            if self._lock.acquire(timeout=max(0.0, left)):
                self._lock.release()  # (an interrupt between the two: `done` answers next time)
            elif left < SIGNAL_CHECK:  # (the last slice ran out)
                break
        return self.done


COLLECT_AFTER = 64
"""Ended simulated processes before a full garbage collection (a killed one's memory is left
to the collector; one collection per run would cost more than most runs)."""

_ended = 0


def _collect_the_ended(ended: int) -> None:
    global _ended  # (the count since the last collection, this process's)
    _ended += ended
    if _ended >= COLLECT_AFTER:
        _ended = 0
        gc.collect()


def _simulate(
    make: Callable[[], Scheduler],
    fn: Callable[[], Any],
    outcome: list[Any],
    ended: _Ended,
) -> None:
    """The run's OS thread: seams and states in, the scheduler, then out; `outcome` gets
    `(True, Run)` or `(False, what to raise)` before the tasks left are dropped."""
    try:
        _simulate_in(make, fn, outcome)
    finally:
        ended.set()


def _simulate_in(make: Callable[[], Scheduler], fn: Callable[[], Any], outcome: list[Any]) -> None:
    """`_simulate`'s work."""
    global _scheduler  # (the run in progress: `note`, `now`, `sleep`)
    result: list[Any] = []
    sched = make()
    # a network the run made and left open (a cancelled run's `finally` that never got to
    # its `close`) frees its name as the run ends; those open before are not the run's
    open_before = memory.open_networks()

    def main() -> None:
        try:
            value = fn()
        except BaseException as exc:  # noqa: BLE001 - raised in the caller's thread
            _mark(exc, sched)
            result.append((False, exc))
        else:
            result.append((True, value))

    runtime.use(_seams(sched))
    _scheduler = sched
    try:
        sched.new_process("main")  # (its state made of the simulated seams)
        sim.Thread(sched, target=main, name="MainThread", daemon=False).start()
        sched.run()
        outcome.extend(_finished(sched, *result[0]))
    except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
        outcome.extend(_finished(sched, False, exc))
    finally:
        _scheduler = None
        sched.drop()
        for process in sched.processes:  # (a task that would not end keeps its frames)
            process.close_files()
        _loop.close_all(sched)
        memory.free_names(but=open_before)
        sched.states.close()
        runtime.use(None)


def _mark(exc: BaseException, sched: Scheduler) -> None:
    """Give `exc` the point of the run it was raised at, `(virtual seconds, steps)`, as
    `exc.simulated_at` (unless it has one, or takes no attributes)."""
    if not hasattr(exc, "simulated_at"):
        with contextlib.suppress(AttributeError, TypeError):
            exc.simulated_at = (sched.now, sched.steps)  # type: ignore[attr-defined]


def _finished(sched: Scheduler, ok: bool, value: Any) -> tuple[bool, Any]:
    """`(True, the Run)`, or `(False, what to raise)` with the seed in a note (and the
    point it was raised at: `_mark`)."""
    if not ok:
        _mark(value, sched)
        if not isinstance(value, SimulationError):
            value.add_note(
                f"in the simulation of seed {sched.seed}, at virtual time {sched.now:g} s "
                f"after {sched.steps} steps"
            )
        return False, value
    return True, Run(
        seed=sched.seed,
        hash=sched.hash,
        steps=sched.steps,
        elapsed=sched.now,
        value=value,
        errors=tuple(sched.errors),
        trace=None if sched.trace is None else tuple(sched.trace),
    )


def _seams(sched: Scheduler) -> dict[str, Any]:
    """The simulated seams, for the run's OS thread (the calling one); any other thread
    of the process (a real thread still running from before the run: a status desk's
    watchdog, a test's thread) gets the real ones (`_only_here`)."""
    wall_ns_start = int(WALL_START * 1e9)

    def wall_ns() -> int:
        return wall_ns_start + round(sched.now * 1e9)

    simulated: dict[str, Any] = {
        "Lock": functools.partial(sim.Lock, sched),
        "RLock": functools.partial(sim.RLock, sched),
        "Event": functools.partial(sim.Event, sched),
        "Condition": functools.partial(sim.Condition, sched),
        "SimpleQueue": functools.partial(sim.SimpleQueue, sched),
        "Thread": functools.partial(sim.Thread, sched),
        "Timer": functools.partial(sim.Timer, sched),
        "wall": lambda: wall_ns() / 1e9,  # (as time.time() is time.time_ns(): one clock)
        "wall_ns": wall_ns,
        "sleep": functools.partial(sim.sleep, sched),
        "urandom": sched.data.randbytes,
        "random": sched.data.random,
        "getrandbits": sched.data.getrandbits,
        "get_ident": functools.partial(sim.get_ident, sched),
        "current_thread": functools.partial(sim.current_thread, sched),
        "getpid": lambda: sched.current().process.pid,
        "new_event_loop": functools.partial(_loop.new_event_loop, sched),
        "guards_files": lambda: False,  # (its backups are its own: `runtime.guards_files`)
        "hold": functools.partial(_hold, sched),
        "queue_class": functools.partial(sim.queue_class, sched, {}),
        "manager_process": functools.partial(_manager.start, sched),
    }
    here = threading.get_ident()
    seams = {name: _only_here(here, seam, runtime.REAL[name]) for name, seam in simulated.items()}
    seams["monotonic"] = _monotonic_here(here, sched, runtime.REAL["monotonic"])
    return seams


def _hold(sched: Scheduler, file: T) -> T:
    """`runtime.hold` in a simulation: `file` is the calling task's process's (the run's
    main process's, called from the scheduler itself), closed when that process ends."""
    task = sched.current_or_none()
    (sched.root if task is None else task.process).files.append(file)
    return file


def _only_here(here: int, simulated: Callable[..., Any], real: Callable[..., Any]) -> Any:
    """`simulated` when called on the OS thread `here` (the run's: its greenlets and its
    scheduler), `real` on any other: the seams are the module's globals, seen by every
    thread of the process, and a real thread must keep real clocks, sleeps and locks."""

    ident = threading.get_ident

    def seam(*args: Any, **kwargs: Any) -> Any:
        if ident() == here:
            return simulated(*args, **kwargs)
        return real(*args, **kwargs)

    return seam


def _monotonic_here(here: int, sched: Scheduler, real: Callable[[], float]) -> Callable[[], float]:
    """`_only_here` for the clock, the commonest seam (a heartbeat, each timeout): the
    virtual clock read in the seam itself."""
    ident = threading.get_ident

    def monotonic() -> float:
        if ident() == here:
            return MONOTONIC_START + sched.now
        return real()

    return monotonic


def running_scheduler() -> Scheduler:
    """The scheduler of the run the calling thread is a simulated thread of.

    Raises:
        RuntimeError: no simulation runs on the calling thread.
    """
    if _scheduler is None or _scheduler.current_or_none() is None:
        raise RuntimeError("called outside a simulated run's threads")
    return _scheduler


def note(text: str) -> None:
    """Add `text` to the running simulation's trace and its hash (from a simulated thread).

    Raises:
        RuntimeError: no simulation runs on the calling thread.
    """
    running_scheduler().note(text)


def now() -> float:
    """The virtual seconds since the running simulation began.

    Raises:
        RuntimeError: no simulation runs on the calling thread.
    """
    return running_scheduler().now


def sleep(seconds: float) -> None:
    """Sleep `seconds` of virtual time (a simulated callback's duration).

    Raises:
        RuntimeError: no simulation runs on the calling thread.
    """
    sim.sleep(running_scheduler(), seconds)


def pid() -> int:
    """The simulated pid of the calling thread's process (the run's main process: 1).

    Raises:
        RuntimeError: no simulation runs on the calling thread.
    """
    sched = running_scheduler()
    return sched.current().process.pid


def start_process(target: Callable[[], object], *, name: str) -> int:
    """Start a simulated process that runs `target()` as its main thread; its pid.

    Its per-process state (directory, membership, clock, pykka's registry) is its own and
    fresh. It ends only when killed (`kill`): a process whose threads all ended idles.

    Raises:
        RuntimeError: no simulation runs on the calling thread.
    """
    sched = running_scheduler()
    task = sched.current_or_none()
    process = sched.new_process(name, sched.root if task is None else task.process)
    sim.Thread(sched, target=target, name=f"{name}-main", daemon=True, process=process).start()
    return process.pid


def kill(pid: int, sig: int = signal.SIGKILL) -> None:
    """Send `sig` to simulated process `pid`, as `os.kill`: `SIGKILL` (or another deadly
    signal) ends it at once (no `finally` runs; its backup keeps what committed),
    `SIGSTOP` stops it, `SIGCONT` runs it again. An ended process is left alone.

    Raises:
        RuntimeError: no simulation runs on the calling thread.
        ProcessLookupError: no simulated process has that pid.
    """
    sched = running_scheduler()
    process = next((p for p in sched.processes if p.pid == pid), None)
    if process is None:
        raise ProcessLookupError(f"no simulated process {pid}")
    if sig == signal.SIGSTOP:
        sched.stop(process)
    elif sig == signal.SIGCONT:
        sched.cont(process)
    else:
        sched.end(process, -sig)
