"""A bounded pool of daemon threads that runs user callbacks off the actors' mailboxes.

```
 submit(task) ──► an idle worker? ──yes──────────────► it runs the task
                       │ no
                       ├── fewer than max_workers? ──► a new worker thread runs it
                       └── otherwise ────────────────► queued: the next worker that is
                                                       free takes it (urgent jobs first,
                                                       then one lane after another)
 job.cancel() ──► a queued job never runs (a running one is left alone)
 a job with a timeout ──► the watchdog (one thread, while jobs are watched): overdue ──►
     abandon it (its thread no longer counts; another may start) ──► on_overdue()
```

A hung callback costs one thread while it hangs, nothing else. The lanes take turns (round robin):
a consumer that floods the queue delays another's load by one job per worker, not by its whole
backlog. A `held` job (a coroutine load) keeps its place, not its thread, until `release()`.
"""

from __future__ import annotations

import collections
import enum
import logging
from collections.abc import Callable

from rr_actors._core import runtime
from rr_actors.config import DEFAULT_MAX_WORKERS

logger = logging.getLogger("rr_actors")


class _State(enum.Enum):
    QUEUED = "queued"
    RUNNING = "running"
    DONE = "done"
    CANCELLED = "cancelled"  # abandoned before it ran: it never will
    ABANDONED = "abandoned"  # abandoned while it ran: its thread no longer counts


def _nothing() -> None: ...


class Job:
    """One task submitted to a `Workers` pool (see `Workers.submit`)."""

    __slots__ = (
        "_deadline", "_held", "_key", "_on_overdue", "_pool", "_quiet", "_state", "_timeout",
        "task",
    )  # fmt: skip

    def __init__(
        self,
        pool: Workers,
        task: Callable[[], None],
        timeout: float | None,
        on_overdue: Callable[[], None] | None,
        quiet: bool = False,
        held: bool = False,
    ) -> None:
        self._pool = pool
        self._held = held
        self._key: object = None  # (counted in `Workers.waiting` while queued)
        self.task = task
        self._timeout = timeout
        self._on_overdue = on_overdue
        self._quiet = quiet
        self._state = _State.QUEUED
        self._deadline = 0.0

    @property
    def running(self) -> bool:
        return self._state is _State.RUNNING

    def abandon(self) -> bool:
        """Give up on it (queued: never runs; running: stops counting); whether it had not ended."""
        return self._pool._abandon(self)

    def cancel(self) -> bool:
        """Withdraw it if it has not started; whether it was still queued."""
        return self._pool._cancel(self)


class Workers:
    """Run zero-argument callables on at most `max_workers` reused daemon threads
    (`rr-<name>-worker-<n>`), an idle one exiting after `idle_timeout` seconds."""

    def __init__(
        self, name: str, *, max_workers: int = DEFAULT_MAX_WORKERS, idle_timeout: float = 10.0
    ) -> None:
        self._name = name
        self._max = max_workers
        self._idle_timeout = idle_timeout
        self._lock = runtime.Lock()
        # one turn per queued job: the first urgent job, else the next lane's
        self._jobs: runtime.SimpleQueue[None] = runtime.SimpleQueue()
        self._urgent: collections.deque[Job] = collections.deque()
        # the other jobs by lane, and the lanes in the order they take their turns
        self._lanes: dict[str, collections.deque[Job]] = {}
        self._turns: collections.deque[str] = collections.deque()
        self._idle = 0  # workers waiting for a job, minus jobs queued (negative: a backlog)
        self._live = 0  # worker threads that count against max_workers
        self._numbered = 0
        self._abandoned = 0
        self._watched: dict[Job, float] = {}  # running jobs with a timeout -> deadline
        self._watching = runtime.Condition(self._lock)
        self._watchdog = False  # a watchdog thread runs
        self._waiting: dict[object, int] = {}  # key -> its jobs queued, neither begun nor cancelled

    @property
    def max_workers(self) -> int:
        return self._max

    @property
    def queued(self) -> int:
        """Tasks waiting for a worker (a cancelled one counts until it is skipped)."""
        return max(0, -self._idle)

    def waiting(self, key: object) -> int:
        """Jobs submitted with `key` still queued: not begun, not cancelled (withdrawn)."""
        return self._waiting.get(key, 0)

    @property
    def abandoned(self) -> int:
        """Jobs given up on while they ran (their threads run on until they return)."""
        return self._abandoned

    def submit(
        self,
        task: Callable[[], None],
        *,
        timeout: float | None = None,
        on_overdue: Callable[[], None] | None = None,
        quiet: bool = False,
        urgent: bool = False,
        lane: str = "",
        held: bool = False,
        key: object = None,
    ) -> Job:
        """Run `task` on a worker thread once one is free; what it raises is logged.
        `timeout`: seconds it may run, then it is abandoned, `on_overdue()` on the watchdog's
        thread (DEBUG if `quiet`). Queued: `urgent` first, the others by `lane` in turns.
        `held`: its place stays taken once `task` returned, until `release()`. `key`: counted
        in `waiting(key)` while it is queued.
        `RuntimeError`: no worker was free and the OS refused a thread."""
        job = Job(self, task, timeout, on_overdue, quiet, held)
        with self._lock:
            if held and self._idle >= 0 and self._live < self._max:  # a place free: no thread
                self._live += 1
                job._state = _State.DONE
            elif self._idle > 0 or self._live >= self._max:
                self._idle -= 1  # an idle worker takes it, or the next one that comes free
                if urgent:
                    self._urgent.append(job)
                else:
                    self._queue(job, lane)
                    if key is not None:
                        job._key, self._waiting[key] = key, self._waiting.get(key, 0) + 1
                self._jobs.put(None)
                return job
            else:
                self._live += 1
        if job._state is _State.DONE:
            task()  # (it starts the job's work, on this thread: `release()` once that ended)
            return job
        try:
            self._start_worker(job)
        except RuntimeError:
            with self._lock:
                self._live -= 1
            raise
        return job

    def _start_worker(self, job: Job | None) -> None:
        with self._lock:
            self._numbered += 1
            number = self._numbered
        runtime.Thread(
            target=self._run, args=(job,), name=f"rr-{self._name}-worker-{number}", daemon=True
        ).start()

    def _run(self, job: Job | None) -> None:
        while True:
            if job is not None:
                if self._begin(job):
                    try:
                        job.task()
                    except BaseException:  # a worker must survive anything a task does
                        logger.exception("uncaught exception in an rr_actors worker task")
                if not self._end(job):  # abandoned while it ran: no longer one of ours
                    return
            with self._lock:
                self._idle += 1
            job = self._next_job()
            if job is None:
                return

    def _next_job(self) -> Job | None:
        """Wait for a queued job; `None` once idle for `idle_timeout` with nobody counting on it."""
        while True:
            try:
                self._jobs.get(timeout=self._idle_timeout)
            except runtime.Empty:
                with self._lock:
                    if self._idle > 0:  # nobody counts on this worker: leave
                        self._idle -= 1
                        self._live -= 1
                        return None
                continue
            with self._lock:  # (each turn's job was queued before its turn)
                return self._urgent.popleft() if self._urgent else self._take()

    def _queue(self, job: Job, lane: str) -> None:
        """Queue `job` last in `lane` (hold the lock); a new lane's turn comes after the others."""
        jobs = self._lanes.get(lane)
        if jobs is None:
            jobs = self._lanes[lane] = collections.deque()
            self._turns.append(lane)
        jobs.append(job)

    def _take(self) -> Job:
        """The first job of the lane whose turn it is (hold the lock); it goes last or away."""
        lane = self._turns.popleft()
        jobs = self._lanes[lane]
        job = jobs.popleft()
        if jobs:
            self._turns.append(lane)
        else:
            del self._lanes[lane]
        return job

    def _begin(self, job: Job) -> bool:
        with self._lock:
            if job._state is not _State.QUEUED:
                return False
            self._unqueued(job)
            job._state = _State.RUNNING
            if job._timeout is None:
                return True
            job._deadline = runtime.monotonic() + job._timeout
            self._watched[job] = job._deadline
            start_watchdog = not self._watchdog
            self._watchdog = True
            self._watching.notify()
        if start_watchdog:
            self._start_watchdog()
        return True

    def _end(self, job: Job) -> bool:
        with self._lock:
            self._watched.pop(job, None)
            if job._state is _State.ABANDONED:
                return False
            if job._state is _State.RUNNING:
                job._state = _State.DONE
                if job._held and self._live >= self._max:  # (the job keeps its place,
                    return False  # and no other is free for the thread: it ends)
                self._live += job._held
            return True

    def release(self) -> None:
        """A held job's work ended: its place goes to the next queued job."""
        with self._lock:
            self._live -= 1
        self._refill()

    def _refill(self) -> None:  # (a job waits and a place is free: a new worker takes it)
        with self._lock:
            if self._idle >= 0 or self._live >= self._max:
                return
            self._live += 1
        try:
            self._start_worker(None)
        except RuntimeError:
            with self._lock:
                self._live -= 1

    def _unqueued(self, job: Job) -> None:
        """`job` leaves the queue (hold the lock): it no longer counts in `waiting`."""
        if (key := job._key) is not None and (left := self._waiting[key] - 1):
            self._waiting[key] = left  # (a reader without the lock sees the old count or this)
        elif key is not None:
            del self._waiting[key]

    def _cancel(self, job: Job) -> bool:
        with self._lock:
            if job._state is not _State.QUEUED:
                return False
            self._unqueued(job)
            job._state = _State.CANCELLED  # the worker that takes it skips it
            job.task = _nothing  # (what it holds is freed now, not when it is skipped)
            job._on_overdue = None
            return True

    def _abandon(self, job: Job) -> bool:
        with self._lock:
            state = job._state
            if state is not _State.QUEUED and state is not _State.RUNNING:
                return False
            self._watched.pop(job, None)
            if state is _State.QUEUED:
                self._unqueued(job)
                job._state = _State.CANCELLED  # the worker that takes it skips it
                return True
            job._state = _State.ABANDONED
            self._abandoned += 1
            self._live -= 1  # its thread runs on, uncounted
        log = logger.debug if job._quiet else logger.warning
        log(
            "registrar %s: a callback overran its time and was abandoned; its thread "
            "runs on until it returns (%d abandoned so far)",
            self._name,
            self._abandoned,
        )
        self._refill()  # a queued job may run now on a new worker
        return True

    # -- the watchdog -----------------------------------------------------------------

    def _start_watchdog(self) -> None:
        try:
            runtime.Thread(
                target=self._watch, name=f"rr-{self._name}-watchdog", daemon=True
            ).start()
        except RuntimeError:  # no thread: jobs run unbounded until a later start works
            logger.exception("registrar %s: no thread to bound callbacks' time", self._name)
            with self._lock:
                self._watchdog = False

    def _watch(self) -> None:
        while True:
            with self._lock:
                overdue = self._overdue()
                if overdue is None:
                    self._watchdog = False
                    return
            for job in overdue:
                if job.abandon() and job._on_overdue is not None:
                    try:
                        job._on_overdue()
                    except Exception:
                        logger.exception("an overdue job's handler raised")

    def _overdue(self) -> list[Job] | None:
        idle_since = runtime.monotonic()
        while True:
            now = runtime.monotonic()
            if not self._watched:
                if now - idle_since >= self._idle_timeout:
                    return None
                self._watching.wait(self._idle_timeout - (now - idle_since))
                continue
            overdue = [job for job, deadline in self._watched.items() if deadline <= now]
            if overdue:
                return overdue
            self._watching.wait(min(self._watched.values()) - now)
            idle_since = runtime.monotonic()
