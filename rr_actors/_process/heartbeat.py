"""The parent's side of a manager's heartbeat: when to ping, and when a silence is a hang.

```
 watcher thread (ManagerProcess._watch)      Heartbeat                   the kernel (Linux)
   woke at `wake_at`, pipe read ──► tick(now)
                                      no ping in flight, due ──► Ping(n) ──► control pipe
                                      ping n unanswered ──► judge(now) ──► CpuWatch.sample()
                                                                           /proc/<pid>/stat,
                                                                           task/*/schedstat
                                      ◄── None (wait on) | Hang (kill it)
   Pong(n) read ──────────────────► answered(n)
```

A manager is *hung* when it has not answered a ping for `bound` seconds of time in which
it could have run. An answer needs a few milliseconds of CPU in the manager (its control
loop, its registrar's mailbox); on a machine with more runnable threads than CPUs it
waits for them, and a bound on the wall clock alone kills healthy managers there. So the
silence is reduced by the time the manager's threads spent runnable but waiting for a
CPU, which the kernel counts (`Platform.watch_cpu`: Linux's run-queue delay). What stays
counts against it: time it was stopped (`SIGSTOP`, a debugger: it cannot even wait for a
CPU), blocked (a deadlock, a lock, I/O) or running without answering. The watcher's own
delays do not count either: a silence starts when its ping was written, and what the
pipe holds is read before a silence is judged (`ManagerProcess._watch`). Two bounds
keep the excuse honest:

- the first `step` seconds of a silence count whole, unless the previous answer was
  late too (the watch is read only once an answer is late, or from the ping on after a
  late one: reading it at every ping would cost two files per thread, four times a
  second, per manager, on a quiet machine too);
- a manager silent for `STARVED_LIMIT` times its bound is hung however long it waited:
  one whose registrar is stuck while other threads of it (busy callbacks) keep waiting
  for a CPU would otherwise never be judged, and one that could not answer for that long
  is of no use to its peers either.

Where the platform has no watch (`portable`), the silence counts whole: a fixed bound.

Alternatives weighed: a phi accrual failure detector (Hayashibara et al. 2004; Akka,
Cassandra) learns the distribution of past answer times and suspects a peer when the
current silence is improbable under it. It suits peers across a network, where nothing
better is known; here the kernel knows why a silence lasts. Learning comes too late for
a sudden load (a burst of manager starts: the distribution was learned from the quiet
answers before it), and it would lengthen the detection of a real hang after every slow
period. psutil reads CPU times and a state, not the run-queue delay: it could tell
"stopped", not "starved" from "stuck".
"""

from __future__ import annotations

import dataclasses
import logging

from rr_actors._core.throttle import LogThrottle
from rr_actors._platform.base import CpuSample, CpuWatch

__all__ = ["STARVED_LIMIT", "Hang", "Heartbeat"]

logger = logging.getLogger("rr_actors")

STARVED_LIMIT = 10.0
"""A manager silent for this many times its bound is hung, however long it waited for a
CPU (7.5 s with the default bound)."""


@dataclasses.dataclass(frozen=True, slots=True)
class Hang:
    """A silence judged a hang: the manager is to be killed.

    Attributes:
        silent: seconds since the ping it did not answer was sent.
        waited: seconds of that its threads waited for a CPU (`None`: not known here).
        stopped: it was stopped (`SIGSTOP`, a debugger) when judged.
        starved: it was judged only by `STARVED_LIMIT` (it waited for a CPU nearly all
            along).
    """

    silent: float
    waited: float | None = None
    stopped: bool = False
    starved: bool = False

    def reason(self) -> str:
        """What it was, for people: `no heartbeat answer for 0.751 s (stopped: ...)`."""
        text = f"no heartbeat answer for {self.silent:.3f} s"
        if self.stopped:
            return text + " (stopped: SIGSTOP or a debugger)"
        if self.starved:
            return (
                text
                + f", {self.waited:.3f} s of it waiting for a CPU ({STARVED_LIMIT:g}x its bound)"
            )
        if self.waited:
            return text + f", {self.waited:.3f} s of it waiting for a CPU"
        return text


class _Silence:
    """One ping in flight: when it was sent, and the watch's reading once it was late."""

    __slots__ = ("base", "base_at", "counted", "number", "sent", "warned")

    def __init__(self, number: int, sent: float) -> None:
        self.number = number
        self.sent = sent
        self.base: CpuSample | None = None  # the watch read at the first late look
        self.base_at = 0.0
        self.counted = 0.0  # seconds before `base_at` that count whole
        self.warned = False


class Heartbeat:
    """When to ping one manager, and whether its silence is a hang (its watcher thread).

    One ping is in flight at a time. Not thread-safe: the manager's watcher thread alone
    calls it.

    Args:
        name: the manager's name (for the log).
        period: seconds between pings.
        bound: seconds of silence, in time it could have run, after which it is hung
            (`ManagerSpec.hang_after`).
        cpu: the platform's watch of its process, or `None` (the silence counts whole).
        now: the monotonic time now (the first ping goes a `period` later).
    """

    def __init__(
        self, name: str, period: float, bound: float, cpu: CpuWatch | None, now: float
    ) -> None:
        self.name = name
        self.period = period
        self.bound = bound
        self.cpu = cpu
        self.step = min(period, bound / 3)
        """Seconds between looks at a silence (a hang is seen within `bound + step`)."""
        self.wake_at = now + period
        """When the watcher must call `tick` next (monotonic seconds)."""
        self._next_ping = self.wake_at
        self._sent = 0
        self._silence: _Silence | None = None
        self._late = False  # the last answer came after a look at its silence
        self._starved = LogThrottle(logger)  # one line at once, then one a minute at most

    def tick(self, now: float) -> int | Hang | None:
        """The watcher's turn at `now` (after it read what the pipe held).

        Returns:
            The number of a ping to send now (then call `sent`), a `Hang` (kill the
            manager), or `None`. `wake_at` says when to call again.
        """
        silence = self._silence
        if silence is None:
            if now < self._next_ping:
                self.wake_at = self._next_ping
                return None
            self._sent += 1
            self._silence = _Silence(self._sent, now)
            self._next_ping = now + self.period
            self.wake_at = now + self.step
            return self._sent
        self.wake_at = now + self.step
        return self._judge(silence, now)

    def sent(self, now: float) -> None:
        """The ping `tick` asked for was written to the pipe at `now`: its silence starts
        then (a watcher slow to send it, waiting for the GIL, does not count against the
        manager)."""
        silence = self._silence
        if silence is not None:
            silence.sent = now
            self._next_ping = now + self.period
            self.wake_at = now + self.step
            if self._late and self.cpu is not None:  # likely late again: watch it from now
                silence.base, silence.base_at = self.cpu.sample(), now

    def answered(self, number: int, now: float) -> bool:
        """Ping `number` was answered (read at `now`); whether it is the one in flight."""
        silence = self._silence
        if silence is None or silence.number != number:
            return False  # (an answer to an earlier ping, or none in flight)
        self._silence = None
        self._late = silence.base is not None and now - silence.sent > self.step
        self.wake_at = max(now, self._next_ping)
        return True

    def close(self) -> None:
        """Release the platform's watch."""
        if self.cpu is not None:
            self.cpu.close()

    def _judge(self, silence: _Silence, now: float) -> Hang | None:
        silent = now - silence.sent
        sample = None if self.cpu is None else self.cpu.sample()
        if sample is None:  # nothing known (or it exited: its sentinel tells that next)
            return Hang(silent) if silent > self.bound else None
        if silence.base is None:
            silence.base, silence.base_at = sample, now
            silence.counted = min(silent, self.step)
            return None
        since = now - silence.base_at
        waited = min(since, max(0.0, sample.waited - silence.base.waited))
        counted = silence.counted + since - waited
        if sample.stopped and silent > self.bound:
            return Hang(silent, waited, stopped=True)
        if counted > self.bound:
            return Hang(silent, waited)
        if silent > STARVED_LIMIT * self.bound:
            return Hang(silent, waited, starved=True)
        if silent > self.bound and not silence.warned:
            silence.warned = True
            self._starved.warning(
                "manager %s has not answered its heartbeat for %.3f s, but it could run for "
                "only %.3f s of that (it waited for a CPU the rest: the machine is "
                "overloaded): not hung; it is killed if that reaches %g s, or the silence %g s",
                self.name,
                silent,
                counted,
                self.bound,
                STARVED_LIMIT * self.bound,
            )
        return None
