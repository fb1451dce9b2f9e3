"""The parent's side of a manager's heartbeat: when to ping, and when a silence is a hang.

```
 the watcher (ManagerProcess.turn)          Heartbeat                   the kernel (Linux)
   woke at `wake_at`, pipe read ──► tick(now)
                                      no ping in flight, due ──► Ping(n) ──► control pipe
                                      ping n unanswered ──► judge(now) ──► CpuWatch.sample()
                                                                           /proc/<pid>/stat,
                                                                           task/*/schedstat
                                      ◄── None (wait on) | Hang (kill it)
   Pong(n) read ──────────────────► answered(n)
```

A manager is *hung* when it has not answered a ping for `bound` seconds of time in which
it could have run: the time its threads waited for a CPU (the kernel's run-queue delay,
`Platform.watch_cpu`) and the time its registrar was seen handling messages (a probe's
answer: busy is not hung) do not count; time stopped, blocked or running without
answering does. The first `step` seconds count whole (the watch is read only once an
answer is late), and a silence of `STARVED_LIMIT` times the bound is a hang however it
was spent. Why this and not a phi accrual detector: docs/explanation/failure-semantics.md,
"What counts as a hang".
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Callable

from rr_actors._core import runtime
from rr_actors._core.throttle import LogThrottle
from rr_actors._platform.base import CpuSample, CpuWatch

logger = logging.getLogger("rr_actors")

STARVED_LIMIT = 10.0
"""A manager silent for this many times its bound is hung, however long it waited."""

PINGS_PER_SECOND = 500.0
"""The pings a process's watcher writes a second at most, all its managers' (issue 69)."""


class Pace:
    """Spreads a process's heartbeats' pings `1 / rate` seconds apart at least (the watcher's
    `slot`s); past the rate a `slot` says what each gets, again once the beats doubled since
    (`warned`: their count then), each pinged half as often as said (not at every join)."""

    def __init__(self, rate: float) -> None:
        self.rate, self.beats, self.asked, self.warned = rate, 0, 0.0, 0
        self._next = 0.0  # (monotonic) the earliest the next ping may go
        self._lock = runtime.Lock()

    def join(self, period: float, change: int = 1) -> None:
        with self._lock:  # (any thread; once none beats, it may warn again)
            self.beats += change
            self.asked = self.asked + change / period if self.beats else 0.0
            if not self.beats:
                self.warned = 0

    def slot(self, now: float) -> float:
        """When a ping due at `now` goes (the watcher's thread alone; it is taken)."""
        if self.asked > self.rate and self.beats >= 2 * self.warned:
            with self._lock:  # (a join may race it: checked again, and set, under its lock)
                beats, asked = self.beats, self.asked
                warn = asked > self.rate and beats >= 2 * self.warned
                if warn:
                    self.warned = beats
            if warn:  # (logged once it let go of the lock: no join waits on a log handler)
                every = beats / self.rate
                logger.warning(
                    "%d managers' heartbeats ask for %.0f pings a second, more than the %g "
                    "this process writes: each is pinged every %.2f s instead, and a hang is "
                    "found within that and its heartbeat_timeout (a heartbeat of %.2f s or "
                    "more says so)",
                    *(beats, asked, self.rate, every, every),
                )
        at = self._next = max(now, self._next)
        self._next += 1.0 / self.rate
        return at


PACE = Pace(PINGS_PER_SECOND)
"""This process's (`ManagerProcess`'s heartbeats)."""
os.register_at_fork(after_in_child=lambda: Pace.__init__(PACE, PINGS_PER_SECOND))


@dataclasses.dataclass(frozen=True, slots=True)
class Hang:
    """A silence judged a hang: the manager is to be killed (seconds; `waited`: `None` if
    not known; `starved`: judged only by `STARVED_LIMIT`)."""

    silent: float
    waited: float | None = None
    stopped: bool = False
    starved: bool = False
    busy: float = 0.0

    def reason(self) -> str:
        text = f"no heartbeat answer for {self.silent:.3f} s"
        limit = f" ({STARVED_LIMIT:g}x its bound)" if self.starved else ""
        if self.stopped:
            return text + " (stopped: SIGSTOP or a debugger)"
        if self.starved and self.busy > (self.waited or 0.0):
            text += f", its registrar busy with other messages for {self.busy:.3f} s of it"
        elif self.waited:
            text += f", {self.waited:.3f} s of it waiting for a CPU"
        return text + limit


@dataclasses.dataclass(frozen=True, slots=True)
class Look:
    """Send the manager a `Probe(number)` (its answer goes to `Heartbeat.progress`)."""

    number: int


@dataclasses.dataclass(frozen=True, slots=True)
class Late:
    """A silence past the bound that was excused: the manager answered late, overloaded
    (seconds; `queued`: its mailbox's depth at the last probe answered, -1: none was)."""

    silent: float
    bound: float
    excused: float
    waited: float
    busy: float
    queued: int


@dataclasses.dataclass(slots=True)
class _Silence:
    """One ping in flight, the watch's reading once it was late, the probes' answers."""

    number: int
    sent: float
    base: CpuSample | None = None  # the watch read at the first late look
    base_at: float | None = None  # when it was looked at first (or watched from)
    counted: float = 0.0  # seconds before `base_at` that count whole
    waited: float = 0.0  # seconds since `base_at` its threads waited for a CPU
    busy: float = 0.0  # seconds since `sent` its registrar was seen handling messages
    handled: int | None = None  # the registrar's handled count last heard
    handled_at: float = 0.0  # when that was heard
    queued: int = -1  # its mailbox's depth last heard
    probed: bool = False  # a probe is unanswered
    warned: bool = False


def _excused(waited: float, busy: float, silent: float) -> float:
    """Seconds of a silence that do not count: the `busy` ones, and the share of the `waited`
    ones (spread over the silence) that fell outside them."""
    if silent <= 0.0:
        return 0.0
    return busy + waited * max(0.0, 1.0 - busy / silent)


class Heartbeat:
    """When to ping one manager, and whether its silence is a hang (its watcher thread
    alone calls it; one ping in flight at a time).

    `period`, `bound` (`ManagerSpec.hang_after`): seconds; `cpu`: the platform's watch
    (`None`: no CPU wait known); `probes`: `tick` returns a `Look` at each look at a late
    silence; `on_late`: called with a `Late` when an answer past `bound` was excused;
    `pace`: its pings go at its `slot`s (`close` leaves it).
    """

    def __init__(
        self,
        name: str,
        period: float,
        bound: float,
        cpu: CpuWatch | None,
        now: float,
        *,
        probes: bool = False,
        on_late: Callable[[Late], None] | None = None,
        pace: Pace | None = None,
    ) -> None:
        self.name = name
        self.period = period
        self.bound = bound
        self.cpu = cpu
        self.probes = probes
        self.on_late = on_late
        self.step = min(period, bound / 3)  # seconds between looks at a silence
        self.wake_at = now + period  # when the watcher calls `tick` next
        self._next_ping = self.wake_at
        self.pace, self._slotted = pace, False  # (`_next_ping` is a slot taken)
        if pace is not None:
            pace.join(period)
        self._sent = 0
        self._silence: _Silence | None = None
        self._late = False  # the last answer came after a look at its silence
        self._starved = LogThrottle(logger)  # waited for a CPU
        self._busy = LogThrottle(logger)  # its registrar was busy

    def restart(self, now: float) -> None:
        """Its first ping at `now` (it was held: nothing in flight, nothing judged)."""
        self.wake_at = self._next_ping = now

    def tick(self, now: float) -> int | Look | Hang | None:
        """The watcher's turn at `now`: the number of a ping to send (then call `sent`), a
        `Look`, a `Hang`, or `None`; `wake_at` says when to call again."""
        silence = self._silence
        if silence is None:
            if self.pace is not None and now >= self._next_ping and not self._slotted:
                self._next_ping, self._slotted = self.pace.slot(now), True  # (a later one)
            if now < self._next_ping:
                self.wake_at = self._next_ping
                return None
            self._slotted = False
            self._sent += 1
            self._silence = _Silence(self._sent, now)
            self._next_ping = now + self.period
            self.wake_at = now + self.step
            return self._sent
        if self.probes and now < self.wake_at:  # woken by the pipe (a probe's answer):
            return None  # looked at when due, not at every message
        self.wake_at = now + self.step
        return self._judge(silence, now)

    def sent(self, now: float) -> None:
        """The ping was written at `now`: its silence starts then."""
        silence = self._silence
        if silence is not None:
            silence.sent = now
            self._next_ping = now + self.period
            self.wake_at = now + self.step
            if self._late and (self.cpu is not None or self.probes):  # likely late again:
                silence.base_at = now  # watch it from now
                silence.base = None if self.cpu is None else self.cpu.sample()

    def answered(self, number: int, now: float) -> bool:
        """Ping `number` was answered at `now`; whether it is the one in flight."""
        silence = self._silence
        if silence is None or silence.number != number:
            return False  # (an answer to an earlier ping, or none in flight)
        self._silence = None
        silent = now - silence.sent
        self._late = silence.base_at is not None and silent > self.step
        self.wake_at = max(now, self._next_ping)
        excused = _excused(silence.waited, silence.busy, silent)
        if silent > self.bound and excused > 0.0 and self.on_late is not None:
            self.on_late(
                Late(silent, self.bound, excused, silence.waited, silence.busy, silence.queued)
            )
        return True

    def progress(self, number: int, pinged: int, handled: int, queued: int, now: float) -> None:
        """A probe of ping `number` was answered at `now`: its registrar had handled
        `pinged` messages at the ping, `handled` now, `queued` wait. The time since the
        previous answer (the first: at most one `step`) in which the count grew was spent
        working and does not count."""
        silence = self._silence
        if silence is None or silence.number != number:
            return  # (a probe of an earlier silence)
        silence.probed = False
        if silence.handled is None:  # (a stuck one's last message may have been the first
            before, start = pinged, max(silence.sent, now - self.step)  # after the ping)
        else:
            before, start = silence.handled, silence.handled_at
        if handled > before:
            silence.busy += max(0.0, now - start)
        silence.handled, silence.handled_at, silence.queued = handled, now, queued

    def close(self) -> None:
        pace, self.pace = self.pace, None
        if pace is not None:  # (first: a sampler whose close raises leaves no beat counted)
            pace.join(self.period, -1)
        if self.cpu is not None:
            self.cpu.close()

    def _judge(self, silence: _Silence, now: float) -> Look | Hang | None:
        silent = now - silence.sent
        sample = None if self.cpu is None else self.cpu.sample()
        if sample is None and not self.probes:  # nothing known (or it exited: its sentinel
            return Hang(silent) if silent > self.bound else None  # tells that next)
        if silence.base_at is None:
            silence.base, silence.base_at = sample, now
            silence.counted = min(silent, self.step)
            return self._look(silence)
        since = now - silence.base_at
        if sample is not None and silence.base is not None:
            silence.waited = min(since, max(0.0, sample.waited - silence.base.waited))
        before = silence.base_at - silence.sent - silence.counted  # (the watcher's delay)
        counted = silent - _excused(before + silence.waited, silence.busy, silent)
        waited = silence.waited if silence.base is not None else None
        if sample is not None and sample.stopped and silent > self.bound:
            return Hang(silent, waited, stopped=True)
        if counted > self.bound:
            return Hang(silent, waited)
        if silent > STARVED_LIMIT * self.bound:
            return Hang(silent, waited, starved=True, busy=silence.busy)
        if silent > self.bound and not silence.warned:
            silence.warned = True
            self._warn(silence, silent, counted)
        return self._look(silence)

    def _look(self, silence: _Silence) -> Look | None:
        if not self.probes or silence.probed:
            return None
        silence.probed = True
        return Look(silence.number)

    def _warn(self, silence: _Silence, silent: float, counted: float) -> None:
        busy = silence.busy > silence.waited
        (self._busy if busy else self._starved).warning(
            "manager %s has not answered its heartbeat for %.3f s, but it could run for "
            "only %.3f s of that %s: not hung; it is killed if that reaches %g s, or the "
            "silence %g s",
            *(self.name, silent, counted),
            f"without handling a message (its registrar was busy with other messages, "
            f"{silence.queued} queued: the manager is overloaded)"
            if busy
            else "(it waited for a CPU the rest: the machine is overloaded)",
            self.bound,
            STARVED_LIMIT * self.bound,
        )
