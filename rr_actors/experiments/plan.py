"""A plan as data: the supervision tree, the workload, the faults and the repeats.

Frozen dataclasses, built only by `reading` (`load_plan`, `parse_plan`) after every value
was checked, and read by the run (`runner`, `workload`, `inject`, `schedule`). `PlanError`
is the error every invalid plan raises.

The TOML format is documented in `docs/reference/plan.md`.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from collections.abc import Mapping
from typing import Any, Literal

from rr_actors import events
from rr_actors.config import Backoff
from rr_actors.errors import ConfigError

__all__ = [
    "FAULT_KINDS",
    "MAX_INJECTIONS",
    "MAX_SECONDS",
    "MIN_EVERY",
    "PLACEHOLDERS",
    "CallMix",
    "Compare",
    "FaultPlan",
    "ManagerPlan",
    "Plan",
    "PlanError",
    "SupervisorPlan",
    "Trigger",
    "Workload",
    "is_number",
]

FaultKind = Literal[
    "kill_manager", "kill_resource", "hang_manager", "load_error", "cut_connections"
]

FAULT_KINDS: tuple[FaultKind, ...] = typing.get_args(FaultKind)
"""Every fault kind a plan may name (see `docs/reference/plan.md`)."""

NEEDS_PROCESS = frozenset({"kill_resource", "hang_manager", "cut_connections"})
"""Fault kinds that act on a manager's OS process (its isolation must be `"process"`)."""

MAX_SECONDS = 1e6
"""The longest duration, time or wait a plan may give, in seconds (about 11.6 days).

Longer ones overflow the waits of `threading` (about 292 years) once added to the clock,
and no experiment needs them: a bound here is a clear error before the run, not a dead
thread in it."""

MIN_EVERY = 1e-3
"""The shortest interval of an `every` fault, in seconds (one injection per millisecond)."""

MAX_INJECTIONS = 100_000
"""The most injections one fault may make in one run (`every` with a short interval)."""

PLACEHOLDERS = frozenset({"key", "client", "run_dir", "pid"})
"""Names a request template may use in its strings: `{key}`, `{client}`, `{run_dir}`, `{pid}`."""

EVENT_TYPES: dict[str, type[Any]] = {  # the events an `after` trigger may name
    cls.__name__: cls for cls in typing.get_args(events.Event) if cls is not events.EventsDropped
}


class PlanError(ConfigError):
    """A plan is invalid: the message names the file, the line, the key and what is wrong.

    Attributes:
        source: the plan's file name (or `"<plan>"` for text without a file).
        line: the 1-based line of the key (0 if the plan has no such key, e.g. a
            missing one at the top).
        key: the key's dotted path, array elements as `[i]` (e.g. `faults[1].target`).
        problem: what is wrong, without the location.
    """

    def __init__(self, source: str, line: int, key: str, problem: str) -> None:
        where = f"{source}:{line}" if line else source
        super().__init__(f"{where}: {key}: {problem}" if key else f"{where}: {problem}")
        self.source = source
        self.line = line
        self.key = key
        self.problem = problem

    def __reduce__(self) -> tuple[Any, ...]:
        return (type(self), (self.source, self.line, self.key, self.problem))


# -- the plan as data -------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ManagerPlan:
    """One manager of the tree: what `ManagerSpec` it becomes in every run.

    Attributes:
        name: the manager's (registrar's) name.
        setup: import path of its `setup(registrar, **options)`, as `"module:function"`.
        options: keyword arguments for `setup`.
        isolation: `"process"` (default in plans) or `"thread"`.
        restart: `"permanent"`, `"transient"` or `"temporary"`.
        heartbeat: seconds between heartbeat pings, or `None` (off).
        heartbeat_timeout: seconds of silence before it counts as hung (`None`: three
            heartbeats).
        shutdown: seconds a clean stop may take before it is killed.
        start_timeout: seconds it may take to restore, set up and serve.
    """

    name: str
    setup: str
    options: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    isolation: Literal["thread", "process"] = "process"
    restart: Literal["permanent", "transient", "temporary"] = "permanent"
    heartbeat: float | None = 0.25
    heartbeat_timeout: float | None = None
    shutdown: float = 5.0
    start_timeout: float = 30.0


@dataclasses.dataclass(frozen=True)
class SupervisorPlan:
    """A supervisor of the tree (the top one is `Plan.tree`).

    Attributes:
        name: its name.
        children: its managers and nested supervisors, in start order.
        strategy: `"one_for_one"`, `"one_for_all"` or `"rest_for_one"`.
        max_restarts: restart intensity: at most this many restarts ...
        period: ... within this many seconds.
        backoff: delay before restarts.
        restart: its restart type in its parent (nested supervisors only).
    """

    name: str
    children: tuple[ManagerPlan | SupervisorPlan, ...]
    strategy: Literal["one_for_one", "one_for_all", "rest_for_one"] = "one_for_one"
    max_restarts: int = 3
    period: float = 5.0
    backoff: Backoff = dataclasses.field(default_factory=Backoff)
    restart: Literal["permanent", "transient", "temporary"] = "permanent"

    def managers(self) -> list[ManagerPlan]:
        """Every manager below this supervisor, depth first, in start order."""
        found: list[ManagerPlan] = []
        for child in self.children:
            found.extend(child.managers() if isinstance(child, SupervisorPlan) else [child])
        return found

    def supervisors(self) -> list[SupervisorPlan]:
        """This supervisor and every nested one, depth first."""
        found = [self]
        for child in self.children:
            if isinstance(child, SupervisorPlan):
                found.extend(child.supervisors())
        return found


@dataclasses.dataclass(frozen=True)
class CallMix:
    """One kind of call the workload makes (an entry of `[[workload.calls]]`).

    Attributes:
        manager: the provider registrar called.
        server: the resource server on it.
        weight: relative frequency of this kind among the workload's calls.
        shared: fraction of these calls that ask for one of `keys` shared requests
            (deduplicated by the provider); the rest ask for a request of their own.
        keys: how many distinct shared requests there are.
        request: the request template (strings may use `{key}`, `{client}`,
            `{run_dir}`; a string that is exactly `"{pid}"` becomes the run process's pid).
        factory: import path of `factory(key, context) -> request` instead of a template.
    """

    manager: str
    server: str
    weight: float = 1.0
    shared: float = 0.5
    keys: int = 4
    request: Any = "{key}"
    factory: str | None = None


@dataclasses.dataclass(frozen=True)
class Workload:
    """What the clients do while faults hit the tree.

    Attributes:
        clients: how many client threads call (each with a consumer registrar).
        rate: calls per second per client, or `None` for as fast as they can.
        arrivals: `"poisson"` (seeded random gaps of mean `1/rate`) or `"fixed"`.
        hold: seconds a client keeps each resource before it unloads it.
        timeout: seconds a call may take, retries through restarts included.
        calls: the mix of calls.
    """

    clients: int = 1
    rate: float | None = 5.0
    arrivals: Literal["poisson", "fixed"] = "poisson"
    hold: float = 0.5
    timeout: float = 5.0
    calls: tuple[CallMix, ...] = ()


@dataclasses.dataclass(frozen=True)
class Trigger:
    """`after = { event = "ChildRestarted", child = "erm", nth = 1 }`: when a fault fires.

    Attributes:
        event: an event type of `rr_actors.events` (e.g. `"ChildRestarted"`).
        match: field values the event must have (e.g. `{"child": "erm"}`).
        nth: the fault fires after the n-th matching event of the run.
    """

    event: str
    match: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    nth: int = 1


@dataclasses.dataclass(frozen=True)
class FaultPlan:
    """One entry of `[[faults]]`: what to do, to whom, and when.

    Exactly one of `at`, `every` and `after` says when.

    Attributes:
        kind: one of `FAULT_KINDS`.
        targets: the managers it may hit (one is picked per injection, seeded); for
            `kill_resource`, whose processes (empty: any process manager's).
        at: fixed times, seconds from the start of the workload.
        every: a fixed interval in seconds, or `(low, high)` for seeded random
            intervals drawn uniformly in between.
        start: with `every`: the first interval starts here (seconds).
        stop: with `every`: no injection at or after this time (default: the duration).
        count: with `every`: at most this many injections.
        after: inject when an event happens (then `delay` seconds later).
        delay: seconds from the trigger event to the injection.
        for_s: how long a hang (or a load error) lasts, in seconds.
        loads: `load_error`: how many loads raise (when `for_s` is not given).
        server: `load_error`: only loads of this server raise (default: any).
        message: `load_error`: the message of the exception the load raises.
    """

    kind: FaultKind
    targets: tuple[str, ...] = ()
    at: tuple[float, ...] = ()
    every: float | tuple[float, float] | None = None
    start: float = 0.0
    stop: float | None = None
    count: int | None = None
    after: Trigger | None = None
    delay: float = 0.0
    for_s: float | None = None
    loads: int = 1
    server: str | None = None
    message: str = "injected load error"

    def most_injections(self, duration: float) -> int:
        """At most how many injections this fault makes in one run.

        An upper bound (the exact number of an `every` fault with random intervals is
        known only from the schedule); plans keep it within `MAX_INJECTIONS`.

        Args:
            duration: the run's duration, in seconds.

        Returns:
            The bound: 1 for a triggered fault, the number of `at` times, or for `every`
            the span from `start` to `stop` (or `duration`) over the shortest interval,
            within `count`.
        """
        if self.after is not None:
            return 1
        if self.every is None:
            return len(self.at)
        low = self.every if isinstance(self.every, float) else self.every[0]
        stop = duration if self.stop is None else min(duration, self.stop)
        if low <= 0:  # only a plan built by hand: reading refuses it
            return MAX_INJECTIONS + 1
        bound = max(0, math.ceil((stop - self.start) / low))
        return bound if self.count is None else min(bound, self.count)


@dataclasses.dataclass(frozen=True)
class Compare:
    """`[compare]`: run the same plan once per value of one setting.

    Attributes:
        setting: the setting's dotted key (`"tree.strategy"`; a child by its name:
            `"tree.children.erm.heartbeat"`; a fault by its index: `"faults.0.every"`).
        values: the values, in the order the runs take them.
    """

    setting: str
    values: tuple[Any, ...]


@dataclasses.dataclass(frozen=True)
class Plan:
    """A whole experiment: validated, ready to run with `rr_actors.experiments.run`.

    Attributes:
        name: the plan's name (the `runs.csv` column `plan`).
        description: free text.
        duration: seconds of workload and faults per run.
        repeat: runs per compared value.
        seed: seed of the first run (run `i` of a value uses `seed + i`).
        recovery_timeout: seconds a run waits at its end for every manager to serve
            again before it unloads what the clients hold.
        tree: the top supervisor.
        state: whether managers keep durable catalogs (a state directory per run).
        workload: the clients.
        faults: the faults.
        compare: the compared setting, or `None`.
        variants: `(value, plan)` per compared value (`((None, self),)` without
            `compare`); each plan has that value applied and `compare` set to `None`.
        source: the file it was read from (`None` for text).
        base_dir: the directory searched first for the plan's import paths (the plan
            file's own), or `None`.
    """

    name: str
    duration: float
    tree: SupervisorPlan
    description: str = ""
    repeat: int = 1
    seed: int = 0
    recovery_timeout: float = 10.0
    state: bool = True
    workload: Workload = Workload(clients=0)
    faults: tuple[FaultPlan, ...] = ()
    compare: Compare | None = None
    variants: tuple[tuple[Any, Plan], ...] = dataclasses.field(
        default=(), repr=False, compare=False
    )
    source: str | None = None
    base_dir: str | None = None

    def managers(self) -> list[ManagerPlan]:
        """Every manager of the tree, depth first, in start order."""
        return self.tree.managers()

    def manager(self, name: str) -> ManagerPlan:
        """The manager called `name`.

        Raises:
            KeyError: no manager of that name.
        """
        for manager in self.managers():
            if manager.name == name:
                return manager
        raise KeyError(name)

    def setting_label(self) -> str:
        """The compared setting's key, or `""` without `compare`."""
        return self.compare.setting if self.compare is not None else ""

    def with_changes(
        self,
        *,
        repeat: int | None = None,
        seed: int | None = None,
        duration: float | None = None,
    ) -> Plan:
        """A copy with another `repeat`, `seed` or `duration` (for every compared value).

        A shorter `duration` drops the faults that would come after the new end.

        Args:
            repeat: runs per compared value (an int >= 1); `None`: keep the plan's.
            seed: the seed of the first repeat; `None`: keep the plan's.
            duration: seconds each run's workload lasts (> 0); `None`: keep the plan's.

        Returns:
            The changed plan (this one is not changed).

        Raises:
            ConfigError: a value is out of range (`duration` above `MAX_SECONDS`, or so
                long that an `every` fault would inject more than `MAX_INJECTIONS` times).
        """
        if repeat is not None and (isinstance(repeat, bool) or repeat < 1):
            raise ConfigError(f"repeat must be an int >= 1, got {repeat!r}")
        if duration is not None and not (is_number(duration) and 0 < duration <= MAX_SECONDS):
            raise ConfigError(
                f"duration must be a positive number of seconds up to {MAX_SECONDS:g}, "
                f"got {duration!r}"
            )
        if duration is not None:
            for _, plan in self.variants:
                for index, fault in enumerate(plan.faults):
                    if fault.most_injections(duration) > MAX_INJECTIONS:
                        raise ConfigError(
                            f"duration {duration:g} s: faults[{index}] would inject more than "
                            f"{MAX_INJECTIONS} times in a run"
                        )
        changes: dict[str, Any] = {}
        if repeat is not None:
            changes["repeat"] = repeat
        if seed is not None:
            changes["seed"] = seed
        if duration is not None:
            changes["duration"] = float(duration)
        variants = tuple(
            (value, dataclasses.replace(plan, **changes)) for value, plan in self.variants
        )
        return dataclasses.replace(self, **changes, variants=variants)


def is_number(value: object) -> bool:
    """Whether `value` is a finite int or float (not a bool)."""
    return (
        isinstance(value, int | float)
        and not isinstance(value, bool)
        and math.isfinite(float(value))
    )
