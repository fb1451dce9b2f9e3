"""The fault schedule of one run: a pure function of the plan and the run's seed.

Every fault of the plan draws from its own random generator, seeded with the run's seed
and the fault's index, so adding a fault to a plan does not move the others, and the
same seed always gives the same schedule: the same kinds, targets and times (and the
same `pick` for the choices made when the fault fires, such as which resource process).
A fault triggered by an event has no time here, only its trigger and delay.
"""

from __future__ import annotations

import dataclasses
import random

from rr_actors.errors import ConfigError
from rr_actors_lab.experiments.plan import MAX_INJECTIONS, FaultPlan, Plan, Trigger

__all__ = ["ScheduledFault", "fault_schedule"]


@dataclasses.dataclass(frozen=True)
class ScheduledFault:
    """One injection the run will make.

    Attributes:
        fault: index of the fault in the plan's `[[faults]]`.
        n: which injection of that fault this is (0, 1, ...).
        kind: the fault kind.
        target: the manager it hits (chosen from the fault's targets), or `None` for a
            `kill_resource` over every process manager.
        at: seconds from the start of the workload, or `None` for a triggered fault.
        pick: a number in `[0, 1)` for choices made when it fires.
        trigger: the event that fires it (triggered faults only).
        delay: seconds from the trigger to the injection.
    """

    fault: int
    n: int
    kind: str
    target: str | None
    at: float | None
    pick: float
    trigger: Trigger | None = None
    delay: float = 0.0


def fault_schedule(plan: Plan, seed: int) -> tuple[ScheduledFault, ...]:
    """Every injection of one run: timed ones sorted by time, then triggered ones; equal for
    equal plans and seeds.

    Raises:
        ConfigError: a fault could inject more than `MAX_INJECTIONS` times (a plan built by
            hand: reading refuses it).
    """
    timed: list[ScheduledFault] = []
    triggered: list[ScheduledFault] = []
    for index, fault in enumerate(plan.faults):
        rng = random.Random(f"rr-actors/{seed}/{index}")  # noqa: S311 - a schedule, not a secret
        if fault.most_injections(plan.duration) > MAX_INJECTIONS:
            raise ConfigError(
                f"faults[{index}] could inject more than {MAX_INJECTIONS} times in a run"
            )
        if fault.after is not None:
            triggered.append(_one(index, 0, fault, None, rng))
            continue
        times = fault.at if fault.every is None else _intervals(fault, plan.duration, rng)
        timed.extend(
            _one(index, n, fault, at, rng) for n, at in enumerate(times) if at < plan.duration
        )
    timed.sort(key=lambda s: (s.at, s.fault, s.n))
    return (*timed, *triggered)


def _one(
    index: int, n: int, fault: FaultPlan, at: float | None, rng: random.Random
) -> ScheduledFault:
    target = rng.choice(fault.targets) if fault.targets else None
    return ScheduledFault(
        fault=index,
        n=n,
        kind=fault.kind,
        target=target,
        at=at,
        pick=rng.random(),
        trigger=fault.after,
        delay=fault.delay,
    )


def _intervals(fault: FaultPlan, duration: float, rng: random.Random) -> list[float]:
    """Times of an `every` fault: from `start`, one interval after another, until `stop`."""
    assert fault.every is not None
    stop = min(duration, fault.stop) if fault.stop is not None else duration
    times: list[float] = []
    t = fault.start
    while fault.count is None or len(times) < fault.count:
        step = fault.every if isinstance(fault.every, float) else rng.uniform(*fault.every)
        t += step
        if t >= stop:
            break
        times.append(round(t, 6))
    return times
