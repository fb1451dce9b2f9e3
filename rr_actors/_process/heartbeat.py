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

- the first `step` seconds of a silence count whole (unless a probe shows its registrar
  worked since the ping), unless the previous answer was late too (the watch is read
  only once an answer is late, or from the ping on after a late one: reading it at
  every ping would cost two files per thread, four times a second, per manager, on a
  quiet machine too);
- a manager silent for `STARVED_LIMIT` times its bound is hung however long it waited:
  one whose registrar is stuck while other threads of it (busy callbacks) keep waiting
  for a CPU would otherwise never be judged, and one that could not answer for that long
  is of no use to its peers either.

Where the platform has no watch (`portable`), no wait for a CPU is known: only the time its
registrar was seen busy (below) and the watcher's delay before its first look are excused.

*Busy is not hung* (issue 53): time in which its registrar was seen handling messages
does not count either (`Heartbeat.progress`; an excused late answer: `on_late`).

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
from collections.abc import Callable

from rr_actors._core.throttle import LogThrottle
from rr_actors._platform.base import CpuSample, CpuWatch

__all__ = ["STARVED_LIMIT", "Hang", "Heartbeat", "Late", "Look"]

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
        starved: it was judged only by `STARVED_LIMIT` (it waited for a CPU, or its
            registrar was busy with other messages, nearly all along).
        busy: seconds of the silence its registrar was seen handling other messages.
    """

    silent: float
    waited: float | None = None
    stopped: bool = False
    starved: bool = False
    busy: float = 0.0

    def reason(self) -> str:
        """What it was, for people: `no heartbeat answer for 0.751 s (stopped: ...)`."""
        text = f"no heartbeat answer for {self.silent:.3f} s"
        if self.stopped:
            return text + " (stopped: SIGSTOP or a debugger)"
        if self.starved and self.busy > (self.waited or 0.0):
            return (
                text + f", its registrar busy with other messages for {self.busy:.3f} s of it "
                f"({STARVED_LIMIT:g}x its bound)"
            )
        if self.starved:
            return (
                text
                + f", {self.waited:.3f} s of it waiting for a CPU ({STARVED_LIMIT:g}x its bound)"
            )
        if self.waited:
            return text + f", {self.waited:.3f} s of it waiting for a CPU"
        return text


@dataclasses.dataclass(frozen=True, slots=True)
class Look:
    """A late silence is being looked at: send the manager a `Probe(number)` (its answer
    goes to `Heartbeat.progress`)."""

    number: int


@dataclasses.dataclass(frozen=True, slots=True)
class Late:
    """A silence past the bound that was excused: the manager answered late, overloaded.

    Attributes:
        silent: seconds from the ping to its answer.
        bound: the bound it passed (`Heartbeat.bound`, seconds).
        excused: seconds of that which did not count (`busy`, and the share of `waited`
            outside it).
        waited: seconds of it its threads waited for a CPU (0.0: not known here).
        busy: seconds of it its registrar was handling other messages.
        queued: messages waiting in its registrar's mailbox at the last probe answered
            (-1: none was).
    """

    silent: float
    bound: float
    excused: float
    waited: float
    busy: float
    queued: int


class _Silence:
    """One ping in flight: when it was sent, the watch's reading once it was late, and what
    the probes' answers said of its registrar's progress."""

    __slots__ = (
        "base",
        "base_at",
        "busy",
        "counted",
        "handled",
        "handled_at",
        "number",
        "probed",
        "queued",
        "sent",
        "waited",
        "warned",
    )

    def __init__(self, number: int, sent: float) -> None:
        self.number = number
        self.sent = sent
        self.base: CpuSample | None = None  # the watch read at the first late look
        self.base_at: float | None = None  # when it was looked at first (or watched from)
        self.counted = 0.0  # seconds before `base_at` that count whole
        self.waited = 0.0  # seconds since `base_at` its threads waited for a CPU
        self.busy = 0.0  # seconds since `sent` its registrar was seen handling messages
        self.handled: int | None = None  # the registrar's handled count last heard
        self.handled_at = 0.0  # when that was heard
        self.queued = -1  # its mailbox's depth last heard
        self.probed = False  # a probe is unanswered
        self.warned = False


def _excused(waited: float, busy: float, silent: float) -> float:
    """Seconds of a `silent`-second silence that do not count: the `busy` ones (its
    registrar was seen working), and of the `waited` ones (waiting for a CPU, spread over
    the silence as far as anyone knows) the share that fell outside them. Never more
    than `silent`; the larger of the two when one is 0."""
    if silent <= 0.0:
        return 0.0
    return busy + waited * max(0.0, 1.0 - busy / silent)


class Heartbeat:
    """When to ping one manager, and whether its silence is a hang (its watcher thread).

    One ping is in flight at a time. Not thread-safe: the manager's watcher thread alone
    calls it.

    Args:
        name: the manager's name (for the log).
        period: seconds between pings.
        bound: seconds of silence, in time it could have run, after which it is hung
            (`ManagerSpec.hang_after`).
        cpu: the platform's watch of its process, or `None` (no time waiting for a CPU
            is known: without `probes`, the silence counts whole).
        now: the monotonic time now (the first ping goes a `period` later).
        probes: whether the manager answers probes (`tick` then returns a `Look` at each
            look at a late silence: send it a `Probe`, hand its answer to `progress`).
        on_late: called (on the caller's thread) with a `Late` when a ping is answered
            after more than `bound` seconds that were excused.
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
    ) -> None:
        self.name = name
        self.period = period
        self.bound = bound
        self.cpu = cpu
        self.probes = probes
        self.on_late = on_late
        self.step = min(period, bound / 3)
        """Seconds between looks at a silence (a hang is seen within `bound + step`)."""
        self.wake_at = now + period
        """When the watcher must call `tick` next (monotonic seconds)."""
        self._next_ping = self.wake_at
        self._sent = 0
        self._silence: _Silence | None = None
        self._late = False  # the last answer came after a look at its silence
        # one line at once, then one a minute at most: each kind on its own (one does not
        # hide the other)
        self._starved = LogThrottle(logger)  # waited for a CPU
        self._busy = LogThrottle(logger)  # its registrar was busy

    def tick(self, now: float) -> int | Look | Hang | None:
        """The watcher's turn at `now` (after it read what the pipe held).

        Returns:
            The number of a ping to send now (then call `sent`), a `Look` (send a probe;
            only with `probes`), a `Hang` (kill the manager), or `None`. `wake_at` says
            when to call again.
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
        if self.probes and now < self.wake_at:  # woken by the pipe (a probe's answer):
            return None  # looked at when due, not at every message
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
            if self._late and (self.cpu is not None or self.probes):  # likely late again:
                silence.base_at = now  # watch it from now
                silence.base = None if self.cpu is None else self.cpu.sample()

    def answered(self, number: int, now: float) -> bool:
        """Ping `number` was answered (read at `now`); whether it is the one in flight.

        An answer after more than `bound` seconds that were excused goes to `on_late`.
        """
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
                Late(
                    silent,
                    self.bound,
                    excused,
                    silence.waited,
                    silence.busy,
                    silence.queued,
                )
            )
        return True

    def progress(self, number: int, pinged: int, handled: int, queued: int, now: float) -> None:
        """A probe of ping `number` was answered (read at `now`): its registrar had handled
        `pinged` messages when the ping reached its process, `handled` now, and `queued`
        wait in its mailbox.

        A saturated manager answers late: its ping waits behind the calls in its mailbox,
        and its registrar waits for the GIL behind busy workers, which the kernel counts
        as sleep, not as waiting for a CPU. The manager's control loop answers a probe at
        once (`Inbox.handled`, its mailbox's size): the time since the previous answer (or
        since the ping) in which the count grew was spent working and does not count (a
        silence's run-queue delay counts only in the share of it not seen working:
        `_excused`).
        A registrar stuck in a handler handles nothing, so its silence counts; one stuck
        right after a message gains the interval it was handled in: since the previous
        answer, or for the first answer at most one `step` (a probe read late, its
        watcher delayed, credits no more). A process that cannot answer
        (stopped, or one thread holding the GIL throughout) gains nothing; the
        `STARVED_LIMIT` holds for a busy one too.
        """
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
        """Release the platform's watch."""
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
        """A probe to send now, if the manager answers them and none is unanswered."""
        if not self.probes or silence.probed:
            return None
        silence.probed = True
        return Look(silence.number)

    def _warn(self, silence: _Silence, silent: float, counted: float) -> None:
        if silence.busy > silence.waited:
            self._busy.warning(
                "manager %s has not answered its heartbeat for %.3f s, but it could run for "
                "only %.3f s of that without handling a message (its registrar was busy with "
                "other messages, %d queued: the manager is overloaded): not hung; it is "
                "killed if that reaches %g s, or the silence %g s",
                self.name,
                silent,
                counted,
                silence.queued,
                self.bound,
                STARVED_LIMIT * self.bound,
            )
            return
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
