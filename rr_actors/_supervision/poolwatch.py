"""A pool's hang watch: the heartbeat of each thread manager in a pool's process.

```
 PoolWatch thread (in the pool's process)          each running thread manager
   every step: tick its Heartbeat ──► ping n ──► its registrar actor's mailbox (`ping`)
                                   ◄── answered(n) ◄── the actor got to it
                                   Look ──► progress: its mailbox's handled count (busy
                                            is not hung, `_process/heartbeat.py`)
                                   Hang ──► `on_hang(name, hang)`: the pool's process ends
```

A process manager's heartbeat watches the pool's own registrar, not the thread managers
inside it; this watch pings each of them in its process, with the same judgement (its
spec's `heartbeat` and `hang_after`, the time its actor was seen working excused). A
thread cannot be killed, so a hung one ends the pool's process (`POOL_HUNG_EXIT`): its
parent restarts the pool, and each of its managers restores its catalog.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator
from typing import Any

from rr_actors._core import runtime
from rr_actors._core.actor import Inbox
from rr_actors._process.heartbeat import Hang, Heartbeat, Look
from rr_actors._supervision.children import Level, NestedSupervisor, ThreadManager

__all__ = ["PoolWatch"]


@dataclasses.dataclass(eq=False)
class _Watched:
    registrar: Any  # its ResourceRegistrar (a new one: a new incarnation, watched afresh)
    beat: Heartbeat
    inbox: Inbox
    pinged: int = 0  # its mailbox's handled count when the ping in flight was sent


class _Answer:
    """The reply to a ping: the beat hears it (under the watch's lock)."""

    def __init__(self, watch: PoolWatch, watched: _Watched, number: int) -> None:
        self.watch, self.watched, self.number = watch, watched, number

    def set_result(self, _: Any) -> None:
        with self.watch.lock:
            self.watched.beat.answered(self.number, runtime.monotonic())

    def set_error(self, _: BaseException) -> None:
        pass  # (the actor died: its supervisor restarts it, a new incarnation is watched)


class PoolWatch:
    """Pings each running thread manager below `level` (a pool's root) on a thread of its
    own; calls `on_hang(name, hang)` once, on that thread, for the first one hung."""

    def __init__(self, level: Level, on_hang: Callable[[str, Hang], None]) -> None:
        self.level = level
        self.on_hang = on_hang
        self.lock = runtime.Lock()
        self.watched: dict[str, _Watched] = {}
        self.closed = runtime.Event()
        self.thread = runtime.Thread(target=self._run, name="rr-pool-watch", daemon=True)

    def start(self) -> PoolWatch:
        self.thread.start()
        return self

    def close(self) -> None:
        """No more judgements (the pool stops)."""
        with self.lock:
            self.closed.set()

    def _run(self) -> None:
        while not self.closed.wait(self._step()):
            with self.lock:
                if self.closed.is_set():
                    return
                hung = self._tick(runtime.monotonic())
            if hung is not None:
                self.on_hang(*hung)
                return

    def _step(self) -> float:
        steps = [w.beat.step for w in self.watched.values()]
        return min(steps, default=0.05)

    def _tick(self, now: float) -> tuple[str, Hang] | None:
        running = dict(_thread_managers(self.level))
        for name in list(self.watched):
            if name not in running:
                del self.watched[name]  # (down, or restarting: watched again once it runs)
        for name, manager in running.items():
            spec, registrar = manager.spec, manager.registrar
            if spec.heartbeat is None or spec.hang_after is None:
                continue
            watched = self.watched.get(name)
            if watched is None or watched.registrar is not registrar:
                inbox = registrar._actor.ref.actor_inbox
                assert isinstance(inbox, Inbox)  # (a registrar actor's)
                beat = Heartbeat(name, spec.heartbeat, spec.hang_after, None, now, probes=True)
                watched = self.watched[name] = _Watched(registrar, beat, inbox)
            if not registrar._actor.ref.is_alive():
                continue  # it died: its supervisor hears it and restarts it
            verdict = watched.beat.tick(now)
            if isinstance(verdict, Hang):
                return name, verdict
            if isinstance(verdict, Look):
                inbox = watched.inbox
                watched.beat.progress(
                    verdict.number, watched.pinged, inbox.handled, inbox.qsize(), now
                )
            elif verdict is not None:
                watched.pinged = watched.inbox.handled
                registrar._actor.ping(_Answer(self, watched, verdict))
                watched.beat.sent(now)
        return None


def _thread_managers(level: Level) -> Iterator[tuple[str, ThreadManager]]:
    """The running thread managers below `level`, nested supervisors' too."""
    for child in list(level.children):
        running = child.running
        if isinstance(running, ThreadManager) and child.state == "running":
            yield child.name, running
        elif isinstance(running, NestedSupervisor):
            yield from _thread_managers(running.node)
