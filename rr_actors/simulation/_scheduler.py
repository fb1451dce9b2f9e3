"""One seeded scheduler: every simulated thread a greenlet, one running at a time, on a
virtual clock.

```
 Scheduler.run(main)  (on the scheduler's greenlet)
   ┌─► a task ready? ── yes ─► pick one (the seeded choice) ─► switch to it; it runs until
   │        │                  it waits (`block`) or offers a choice point (`pause`) ─────┐
   │        no ─► a deadline due later? ── yes ─► the clock jumps to it; its tasks are    │
   │        │                                     ready (a wait's timeout, a sleep)       │
   │        │                              └ no ─► DeadlockError: who waits on what       │
   │        └─ main and every non-daemon task ended ─► the run is over                    │
   └──────────────────────────────────────────────────────────────────────────────────────┘
```

Time stands still while tasks run and jumps to the next deadline when none is ready. Every
choice is drawn from one `random.Random(seed)` among the ready tasks in number order (never
wake order), and the collector runs only between steps (`GC_STEPS`): a seed replays its
run exactly. A choice point (`pause`, where a real thread could be preempted without
blocking) yields with probability `preempt` (drawn as a geometric count of choice points).
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import hashlib
import heapq
import itertools
import logging
import math
import operator
import os
import random
import struct
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from types import FrameType
from typing import Any

import greenlet

from rr_actors.errors import RrError
from rr_actors.simulation._processes import Process, States

__all__ = ["DeadlockError", "LimitError", "Scheduler", "SimulationError", "Task"]

logger = logging.getLogger("rr_actors.simulation")

_HERE = str(Path(__file__).parent)
_ROOT = str(Path(__file__).parent.parent.parent)
_STEP = struct.Struct("<Id")
_number = operator.attrgetter("number")
_getcurrent = greenlet.getcurrent


class SimulationError(RrError):
    """A simulated run could not go on; the message says where it stood and who waited."""


class DeadlockError(SimulationError):
    """Nothing could run and nothing was due, while the run's main task (or another
    non-daemon one) had not ended: each waiting task is listed with what it waits on."""


class LimitError(SimulationError):
    """The run went past its limit of steps or of virtual time (a livelock, or a wait
    that a timer keeps putting off)."""


_LOGGERS = ("rr_actors", "rr_actors.events", "rr_actors.simulation", "pykka")
"""The loggers of the code a simulation runs (`_quiet`)."""

DROP_TRIES = 3
"""Times a task left at the end of a run is thrown `GreenletExit` before it is given up."""

GC_STEPS = 1_000
"""Steps between two collections (the collector is off meanwhile): a collection mid-task would
run finalizers there and change the addresses of new objects, so the same seed collects the
same garbage at the same point."""

_NOTHING: dict[
    str, Any
] = {}  # a task's contents of a namespace it keeps nothing in (never changed)
_GRAVEYARD: list[greenlet.greenlet] = []  # tasks that would not end when dropped
_NO_HOOKS = (None, None)  # the async generators' hooks of a thread that ran no loop


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """Drop the log records of this OS thread meanwhile (the dropped tasks' last words)."""
    ident = threading.get_ident()

    def other_threads(record: logging.LogRecord) -> bool:
        return record.thread != ident

    loggers = [logging.getLogger(name) for name in _LOGGERS]
    for log in loggers:
        log.addFilter(other_threads)
    try:
        yield
    finally:
        for log in loggers:
            log.removeFilter(other_threads)


class _Greenlet(greenlet.greenlet):
    """A greenlet that knows its task (`Scheduler.current`)."""

    task: Task


class Task:
    """One simulated thread: its greenlet, and what it waits on while it waits."""

    __slots__ = (
        "daemon",
        "ended",
        "glet",
        "held",
        "hooks",
        "killed",
        "locals",
        "loop",
        "name",
        "number",
        "process",
        "readied",
        "thread",
        "token",
        "waiting",
        "woken",
    )

    def __init__(self, number: int, name: str, daemon: bool, thread: Any, process: Process) -> None:
        self.number = number
        self.name = name
        self.daemon = daemon
        self.thread = thread  # the simulated `Thread` it runs
        self.process = process  # the simulated process it belongs to
        self.glet: _Greenlet | None = None
        self.ended = False
        self.killed = False  # its process ended: never switched to again
        self.held: list[Any] = []  # the simulated locks it holds (let go if it is killed)
        self.waiting: tuple[object, str] | None = None  # (primitive, operation) it waits in
        self.readied = False  # made ready while it waited (by a wake or its deadline)
        self.woken = False  # ... by a wake (not its deadline)
        self.token = 0  # the wait it is in (a timer of an earlier wait is stale)
        self.locals: list[dict[str, Any]] = []  # its contents of `runtime.local()`s
        # asyncio's per-thread state while it runs a loop (`_loop.py`): its running loop
        # and its async generators' hooks (each loop's `run_forever` sets its own)
        self.loop: Any = None
        self.hooks: Any = _NO_HOOKS

    def __repr__(self) -> str:
        return f"{self.name!r} (#{self.number})"


class Scheduler:
    """Runs tasks one at a time, chosen by a seeded `random.Random`, on a virtual clock.

    Args:
        seed: the seed of every choice (and, through `data`, of every random value).
        preempt: the probability that a task yields at a choice point (`pause`).
        locals: the thread-local namespaces each task keeps its own contents of.
        states: the per-process singletons each simulated process has its own state of.
        max_steps: steps (switches to a task) a run may take.
        until: virtual seconds a run may last.
        trace: keep each step (`trace`), not only their hash.
        cancelled: the run ends once this list is not empty (appended to from any thread).
    """

    def __init__(
        self,
        seed: int,
        *,
        preempt: float,
        locals: tuple[Any, ...],
        states: States,
        max_steps: int,
        until: float,
        trace: bool,
        cancelled: list[bool] | None = None,
    ) -> None:
        self.seed = seed
        self._choices = random.Random(seed)  # noqa: S311 - (a replayable run, not a secret)
        self.data = random.Random(f"rr_actors.simulation data {seed}")  # noqa: S311
        self.preempt = preempt
        self.gap = self._next_gap()  # choice points left before the next yield
        self.now = 0.0  # virtual seconds since the run began
        self.steps = 0
        self._locals = locals
        # their contents on the run's OS thread (made on it, as `_main`): a
        # `threading.local`'s `__dict__` is the same dict each time on one thread
        self._contents: list[dict[str, Any]] = [namespace.__dict__ for namespace in locals]
        self._max_steps = max_steps
        self._until = until
        self._ready: list[Task] = []
        self._timers: list[tuple[float, int, Task, int]] = []  # (deadline, seq, task, token)
        self._seq = itertools.count()
        self._numbers = itertools.count(1)
        self._tasks: list[Task] = []
        self._running = 0  # tasks not ended that keep the run going (non-daemon)
        self._hash = hashlib.blake2b(digest_size=16)
        self._unhashed = bytearray()  # steps not in `_hash` yet (hashed in one go: the same hash)
        self.trace: list[tuple[float, int, str]] | None = [] if trace else None
        self.errors: list[str] = []
        self._main = greenlet.getcurrent()  # (made on the thread it runs on)
        self.states = states
        self._pids = itertools.count(1)
        self.processes: list[Process] = []  # the first: the run's main process (`root`)
        self.loops: list[Any] = []  # asyncio loops made (`_loop.py`): each task has its own
        self._in_locals: Task | None = None  # whose contents the `runtime.local()`s hold
        # the task switched to (`None` while the scheduler runs): what `current()` says
        # without asking greenlet, on the run's OS thread (`current_or_none` asks it)
        self.running: Task | None = None
        # not empty: the run ends within `GC_STEPS` steps with `SimulationError` (its caller
        # was interrupted: a Ctrl-C, a SIGTERM; its folders can go once the run ended)
        self._cancelled = [] if cancelled is None else cancelled

    # -- tasks -----------------------------------------------------------------------

    def spawn(
        self,
        body: Callable[[], object],
        name: str,
        daemon: bool,
        thread: Any,
        process: Process | None = None,
    ) -> Task:
        """A new task that runs `body()`, ready at once, in `process` (`None`: the
        calling task's, or the root process's)."""
        if process is None:
            current = self.current_or_none()
            process = self.root if current is None else current.process
        task = Task(next(self._numbers), name, daemon, thread, process)
        process.tasks.append(task)
        task.locals = [_NOTHING] * len(self._locals)
        glet = _Greenlet(self._body(task, body), parent=self._main)
        glet.task = task
        task.glet = glet
        self._tasks.append(task)
        if not daemon:
            self._running += 1
        self._ready.append(task)
        return task

    def _body(self, task: Task, body: Callable[[], object]) -> Callable[[], None]:
        def run() -> None:
            try:
                body()
            except greenlet.GreenletExit:  # (dropped at the end of the run: `drop`)
                pass
            except BaseException as exc:  # what ends a thread (logged, as threading does)
                self.errors.append(f"{task.name}: {type(exc).__name__}: {exc}")
                logger.exception("simulated thread %s (seed %s) ended", task.name, self.seed)
            finally:
                if not task.killed:  # (a killed one was counted out by `end`)
                    task.ended = True
                    if not task.daemon:
                        self._running -= 1

        return run

    def current(self) -> Task:
        """The task that runs now.

        Raises:
            RuntimeError: the caller is no simulated thread (another thread asks `current_or_none`).
        """
        task = self.running
        if task is None:
            raise RuntimeError(
                "a simulated object was used outside the simulation's threads (a real "
                "thread, or code run while the simulation was not running)"
            )
        return task

    def current_or_none(self) -> Task | None:
        """The task that runs now, if the caller is one (also right from another OS
        thread: greenlet's current one is per thread)."""
        task: Task | None = getattr(_getcurrent(), "task", None)
        return task

    # -- waiting and waking ------------------------------------------------------------

    def block(self, waiting: tuple[object, str], deadline: float | None) -> bool:
        """Suspend the calling task in `waiting` (primitive, operation) until `wake` or
        `deadline` (virtual seconds; `None`: none); whether `wake` ended the wait."""
        task = self.running
        if task is None:
            task = self.current()  # (raises: no task calls)
        task.waiting = waiting
        task.readied = task.woken = False
        if deadline is not None:
            if deadline <= self.now:  # (due already: the others may run first)
                task.readied = True
                self._ready.append(task)
            else:
                heapq.heappush(self._timers, (deadline, next(self._seq), task, task.token))
        self._main.switch()
        task.waiting = None
        task.token += 1
        return task.woken

    def wake(self, task: Task) -> None:
        """End `task`'s wait (if it still waits): it is ready."""
        if task.waiting is not None and not task.readied and not task.killed:
            task.readied = task.woken = True
            self._ready.append(task)

    def pause(self) -> None:
        """A choice point: with probability `preempt`, the calling task yields (the primitives
        inline it)."""
        self.gap -= 1
        if self.gap < 0:
            self.yield_now()

    def yield_now(self) -> None:
        """The choice point whose turn it is to yield (`gap` below 0): the next gap is
        drawn, and the calling task (if a task calls) yields."""
        self.gap = self._next_gap()
        task = self.current_or_none()
        if task is not None:
            self.block((self, "pause"), self.now)

    def _next_gap(self) -> int:
        """Choice points that pass before the next yield: `k` with probability
        `(1 - preempt)**k * preempt`, as if each yielded with probability `preempt` on
        its own."""
        if self.preempt <= 0.0:
            return sys.maxsize
        if self.preempt >= 1.0:
            return 0
        return int(math.log(1.0 - self._choices.random()) / math.log1p(-self.preempt))

    def note(self, text: str) -> None:
        """Add `text` to the trace (and its hash), as said by the running task."""
        task = self.current_or_none()
        number = 0 if task is None else task.number
        self._hashed().update(f"note {number} {text}\n".encode())
        if self.trace is not None:
            self.trace.append((self.now, number, text))

    @property
    def hash(self) -> str:
        """The trace's hash so far (hex)."""
        return self._hashed().hexdigest()

    def _hashed(self) -> hashlib.blake2b:
        """The trace's hash, with the steps taken since it was last updated."""
        self._hash.update(self._unhashed)
        self._unhashed.clear()
        return self._hash

    # -- the loop ----------------------------------------------------------------------

    def run(self) -> None:
        """Run the tasks until no non-daemon task is left.

        Raises:
            DeadlockError: nothing can run and nothing is due while one is left.
            LimitError: past `max_steps` steps or `until` virtual seconds.
        """
        collecting = gc.isenabled()
        gc.disable()  # (it collects between two steps instead: `_collect`)
        try:
            self._loop()
        finally:
            if collecting:
                gc.enable()

    def _loop(self) -> None:
        ready = self._ready
        choose = self._choices.randrange
        states = self.states
        unhashed = self._unhashed  # (a bytearray: `+=` adds to it in place)
        max_steps, until = self._max_steps, self._until
        while self._running:
            if not ready and not self._advance():
                raise DeadlockError(self.report("deadlock: nothing can run and nothing is due"))
            if self.steps >= max_steps or self.now > until:
                raise LimitError(
                    self.report(
                        f"the run went past its limit ({max_steps} steps, "
                        f"{until:g} virtual seconds)"
                    )
                )
            if len(ready) > 1:
                ready.sort(key=_number)  # (the order they were woken in must not count)
                task = ready.pop(choose(len(ready)))
            else:
                task = ready.pop()
            process = task.process
            if process.stopped:  # (SIGSTOP: ready again at its `cont`)
                process.parked.append(task)
                continue
            self.steps += 1
            unhashed += _STEP.pack(task.number, self.now)
            if self.trace is not None:
                self.trace.append((self.now, task.number, task.name))
            if process is not states.installed:  # (`install`'s own first test, inline)
                states.install(process)
            if task is not self._in_locals:
                self._install_locals(task)
            assert task.glet is not None
            self.running = task
            task.glet.switch()
            self.running = None
            if not self.steps % GC_STEPS:
                self._hashed()  # (the steps' buffer kept small)
                _collect(self.steps)
                if self._cancelled:  # (here: a step's check would cost every step)
                    raise SimulationError(self.report("the run was cancelled"))

    def _install_locals(self, task: Task) -> None:
        """Swap in `task`'s contents of the `runtime.local()` namespaces (and asyncio's running
        loop)."""
        was, self._in_locals = self._in_locals, task
        keep = was is not None and not was.ended
        for i, contents in enumerate(self._contents):
            state = task.locals[i]
            if contents:
                if keep:
                    was.locals[i] = dict(contents)  # type: ignore[union-attr]
                contents.clear()
                if state:
                    contents.update(state)
            else:
                if keep:
                    was.locals[i] = _NOTHING  # type: ignore[union-attr]
                if state:  # (most tasks keep nothing in most namespaces)
                    contents.update(state)
        if self.loops:  # (asyncio's per-thread state is per OS thread: each task its own)
            if was is not None:
                was.loop, was.hooks = asyncio._get_running_loop(), sys.get_asyncgen_hooks()
            asyncio._set_running_loop(task.loop)
            sys.set_asyncgen_hooks(*task.hooks)

    def drop(self) -> int:
        """End every task left; how many would not end.

        A greenlet suspended when its OS thread ends is never freed, so each is thrown
        `GreenletExit` where it waits (`DROP_TRIES` times at most), its `finally` blocks run
        unlogged (`_quiet`): the run is over, they change nothing of it.
        """
        self.preempt = 0.0  # (no choice points: a `finally` block runs through)
        self.gap = self._next_gap()
        stuck = 0
        with _quiet():
            for task in self._tasks:
                glet = task.glet
                if task.ended or glet is None or not glet:  # (ended, or never started)
                    continue
                for _ in range(DROP_TRIES):
                    task.waiting = None
                    self.running = task
                    try:
                        glet.throw(greenlet.GreenletExit)
                    finally:
                        self.running = None
                    if glet.dead:
                        break
                else:
                    stuck += 1
                    _GRAVEYARD.append(glet)  # (never freed: at least not half run)
        self._ready.clear()
        self._timers.clear()
        return stuck

    def _advance(self) -> bool:
        """Move the clock to the next deadline and ready its tasks; whether there was one."""
        timers = self._timers
        while timers:
            deadline, _, task, token = heapq.heappop(timers)
            if task.token != token or task.waiting is None or task.readied or task.killed:
                continue  # (a stale timer: that wait ended already, or its process did)
            self.now = max(self.now, deadline)
            task.readied = True
            self._ready.append(task)
            while timers and timers[0][0] <= self.now:  # everything due at this instant
                _, _, task, token = heapq.heappop(timers)
                stale = task.token != token or task.waiting is None or task.readied
                if not stale and not task.killed:
                    task.readied = True
                    self._ready.append(task)
            return True
        return False

    # -- processes ---------------------------------------------------------------------

    @property
    def root(self) -> Process:
        """The run's main process (the first made, once the simulated seams are in: its
        fresh state is made of simulated locks)."""
        return self.processes[0]

    def new_process(self, name: str, parent: Process | None = None) -> Process:
        """A new simulated process, with a pid of its own and fresh per-process state
        (no task yet: `spawn` its first), started by `parent` (`None`: the run's first)."""
        pid = None if parent is None else parent.pid
        process = Process(next(self._pids), name, self.states.fresh(), pid)
        self.processes.append(process)
        return process

    def end(self, process: Process, exitcode: int) -> None:
        """End `process` (a SIGKILL: `-9`; an exit: its code): its tasks never run again, the locks
        of other processes' objects they held are let go, its files closed, then its `at_end`
        callbacks run, then its `at_reaped` ones. From one of its own tasks, never returns."""
        if not process.alive:
            return
        process.exitcode = exitcode
        process.ended_at = self.now
        process.stopped = False
        process.parked.clear()
        me = self.current_or_none()
        for task in process.tasks:
            if task.ended or task.killed:
                continue
            task.killed = True
            if not task.daemon:
                self._running -= 1
            for lock in reversed(task.held):
                if lock.maker is not process:  # (another's: a carrier's, shared)
                    lock.let_go()
            task.held.clear()
        self._ready[:] = [task for task in self._ready if not task.killed]
        process.close_files()
        ends, process.at_end = process.at_end, []
        reaped, process.at_reaped = process.at_reaped, []
        for at_end in (*ends, *reaped):  # (each may yield: none tells the end before
            at_end()  # what the process held is let go)
        if me is not None and me.killed:
            self._main.switch()  # (never switched back to)
            raise AssertionError("a killed task ran again")  # pragma: no cover

    def stop(self, process: Process) -> None:
        """SIGSTOP: `process`'s tasks are not run until `cont`."""
        if process.alive and not process.stopped:
            process.stopped = True
            process.stopped_at = self.now

    def cont(self, process: Process) -> None:
        """SIGCONT: `process`'s tasks run again (those made ready meanwhile are ready)."""
        if process.stopped:
            process.stopped = False
            self._ready.extend(process.parked)
            process.parked.clear()

    # -- reports -----------------------------------------------------------------------

    def report(self, what: str) -> str:
        """`what`, where the run stood, and what each task left waits on."""
        lines = [
            f"{what}, at virtual time {self.now:g} s after {self.steps} steps (seed {self.seed})"
        ]
        for task in self._tasks:
            if task.ended or task.killed:
                continue
            kind = "daemon " if task.daemon else ""
            if task.process is not self.root:
                kind += f"(process {task.process.pid}) "
            if task.waiting is None:
                lines.append(f"  {kind}{task!r}: ready")
                continue
            primitive, operation = task.waiting
            what = f"{type(primitive).__name__}.{operation}{_describe(primitive)}"
            lines.append(f"  {kind}{task!r} waits in {what}")
            lines.extend(f"      at {where}" for where in _where(task))
        return "\n".join(lines)


def _collect(steps: int) -> None:
    """Collect garbage now, between two steps: the youngest generation; each tenth time
    the next one too; each hundredth, all (as CPython's thresholds of 10 do)."""
    if steps % (GC_STEPS * 100) == 0:
        gc.collect()
    else:
        gc.collect(1 if steps % (GC_STEPS * 10) == 0 else 0)


def _describe(primitive: object) -> str:
    """` (made at file:line, ...)` of a simulated primitive, or nothing."""
    describe = getattr(primitive, "describe", None)
    return f" ({describe()})" if callable(describe) else ""


def _where(task: Task, depth: int = 4) -> list[str]:
    """The innermost frames of `task`'s code (not the simulation's): file:line (function)."""
    frame: FrameType | None = None if task.glet is None else task.glet.gr_frame
    while frame is not None and frame.f_code.co_filename.startswith(_HERE):
        frame = frame.f_back
    places: list[str] = []
    while frame is not None and len(places) < depth:
        if frame.f_code.co_filename.startswith(_HERE):
            break  # (the task's start: the rest is the simulation's)
        places.append(
            f"{short_path(frame.f_code.co_filename)}:{frame.f_lineno} ({frame.f_code.co_name})"
        )
        frame = frame.f_back
    return places


def short_path(filename: str) -> str:
    """`filename` from the package's parent (`rr_actors/...`), or the working directory."""
    for root in (_ROOT, os.getcwd()):
        if filename.startswith(root + os.sep):
            return filename[len(root) + 1 :]
    return filename
