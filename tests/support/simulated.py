"""A rule checked on the simulation over many seeds, for the test modules that moved a
semantic-rule test there (issue 42, part 4).

A real run explores the one interleaving the machine happens to produce, and a test whose
rule needs a bound (a dependency's unload held up to a second) pays it in real seconds.
On `rr_actors.simulation` the same protocol code runs on greenlets of one thread, a
seeded scheduler picks the interleaving and the clock is virtual: the bound costs
nothing, and each seed is another interleaving (each one replays:
`simulation.run(scenario, seed=S, preempt=PREEMPT)`).
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from types import CodeType
from typing import Any

import pykka

import rr_actors as rr
from rr_actors import simulation

__all__ = [
    "PREEMPT",
    "SEEDS",
    "Interrupted",
    "InterruptedAgain",
    "interrupted_when",
    "seeds_where",
    "stopped_clean",
]

SEEDS = range(100)
"""The seeds a moved test runs with."""

PREEMPT = 0.1
"""How often a simulated thread yields where it would not block."""


def seeds_where(
    scenario: Callable[[], Any],
    broken: Callable[[Any], bool],
    seeds: Iterable[int] = SEEDS,
) -> list[int]:
    """The seeds whose run of `scenario` is `broken` (or ended a thread with an error)."""
    failed = []
    for seed in seeds:
        run = simulation.run(scenario, seed=seed, preempt=PREEMPT)
        if run.errors or broken(run.value):
            failed.append(seed)
    return failed


def stopped_clean(*registrars: rr.ResourceRegistrar) -> bool:
    """Stop `registrars` (inside the run); whether no actor was left running afterwards."""
    for registrar in registrars:
        registrar.stop()
    return [] == pykka.ActorRegistry.get_all()


class Interrupted(KeyboardInterrupt):
    """What `interrupted_when`'s SIGINT handler raises (pytest's own Ctrl-C left alone)."""


class InterruptedAgain(KeyboardInterrupt):
    """What `interrupted_when(..., twice=True)`'s second signal (SIGUSR1) raises."""


@contextlib.contextmanager
def interrupted_when(
    began: threading.Event, *, twice: bool = False, waiting_in: CodeType | None = None
) -> Iterator[list[tuple[str, BaseException | None]]]:
    """Interrupt the main thread (a SIGINT, raised as `Interrupted`) once `began` is set: a
    real event a simulated run sets, its caller then waiting on the run (as a Ctrl-C or a
    test's timeout lands). The handler is put back after; no SIGINT once the block ended.

    `twice`: a second signal (SIGUSR1) is sent with it, both pending as the main thread
    wakes (a test's timeout that came with the Ctrl-C): signals are handled in their
    numbers' order, one per check, so its `InterruptedAgain` is raised at the next point
    the main thread checks for signals, inside the handling of the first.

    `waiting_in`: and only once the main thread's innermost frame runs this code (its wait
    on the run, not `Thread.start`'s), polled for up to 60 s.

    Yields the signals handled, in order, each with the exception being handled then."""
    over = threading.Event()
    handled: list[tuple[str, BaseException | None]] = []

    def interrupt() -> None:
        if began.wait(60) and not over.is_set():
            main = threading.main_thread().ident or 0
            deadline = time.monotonic() + 60
            while waiting_in is not None and time.monotonic() < deadline:
                frame = sys._current_frames().get(main)
                if frame is not None and frame.f_code is waiting_in:
                    break
                if over.wait(0.001):  # (a poll of where the main thread is, bounded)
                    return
            if twice:  # (both sent in one C loop, the GIL held: the main thread cannot handle
                # the first before the second is pending; then SIGINT's handler runs first)
                list(map(signal.pthread_kill, (main, main), (signal.SIGUSR1, signal.SIGINT)))
            else:
                signal.pthread_kill(main, signal.SIGINT)

    def raise_interrupted(_signum: int, _frame: object) -> None:
        handled.append(("SIGINT", sys.exception()))
        raise Interrupted

    def raise_again(_signum: int, _frame: object) -> None:
        handled.append(("SIGUSR1", sys.exception()))
        raise InterruptedAgain

    previous_again = signal.signal(signal.SIGUSR1, raise_again)
    previous = signal.signal(signal.SIGINT, raise_interrupted)
    sender = threading.Thread(target=interrupt, daemon=True)
    sender.start()
    try:
        yield handled
    finally:
        over.set()
        began.set()  # (the sender ends now, interrupting nothing)
        try:
            sender.join(60)
        finally:
            signal.signal(signal.SIGINT, previous)
            signal.signal(signal.SIGUSR1, previous_again)
