"""A plan as data and as its schema: msgspec Structs whose field types carry the limits
(`Annotated[..., Meta]`), which `reading` decodes the TOML into; `docs/reference/plan.md`."""

from __future__ import annotations

import dataclasses
import functools
import math
import operator
import typing
from typing import Annotated, Any, Literal

import msgspec
from msgspec import Meta

from rr_actors import events
from rr_actors.config import Backoff
from rr_actors.errors import ConfigError

__all__ = [
    "FAULT_KINDS",
    "HOST_KINDS",
    "MAX_INJECTIONS",
    "MAX_SECONDS",
    "MAX_SEED",
    "MIN_EVERY",
    "PLACEHOLDERS",
    "SIMULATION_KINDS",
    "CallMix",
    "Compare",
    "FaultPlan",
    "HostsPlan",
    "ManagerPlan",
    "Plan",
    "PlanError",
    "SupervisorPlan",
    "Trigger",
    "Workload",
]

FaultKind = Literal[
    "kill_manager",
    "kill_resource",
    "hang_manager",
    "load_error",
    "cut_connections",
    "cut",
    "partition",
    "freeze",
    "kill_router",
    "duplicate_delivery",
    "kill_before_answer",
    "kill_in_setup",
    "partition_serving",
    "split_brain",
    "deaf_manager",
    "kill_program",
    "kill_before_commit",
    "corrupt_backup",
]

FAULT_KINDS: tuple[FaultKind, ...] = typing.get_args(FaultKind)  # every kind a plan may name
HOST_KINDS = frozenset({"cut", "partition", "freeze", "kill_router"})  # act between hosts
SIMULATION_KINDS = frozenset(  # aimed where only a simulation can stop or reach (--simulate)
    {
        "duplicate_delivery",
        "kill_before_answer",
        "kill_in_setup",
        "partition_serving",
        "split_brain",
        "deaf_manager",
        "kill_program",
        "kill_before_commit",
        "corrupt_backup",
    }
)
NEEDS_PROCESS = frozenset({"kill_resource", "hang_manager", "cut_connections"} | SIMULATION_KINDS)
MAX_HOSTS = 8  # the most hosts of a plan (a veth between every two: 28 links)
# The limits (docs/reference/plan.md). Longer than MAX_SECONDS (11.6 days) overflows the waits
# of `threading` once added to the clock: a bound here is a clear error, not a dead thread.
MAX_SECONDS = 1e6  # the longest duration, time or wait, in seconds
MIN_EVERY = 1e-3  # the shortest interval of an `every` fault, in seconds
MAX_INJECTIONS = 100_000  # the most injections of one fault in one run
MAX_CLIENTS = 1_000  # the most client threads of a workload (each has a registrar)
MAX_AWAITED = 10_000  # the most calls a client awaits at once (`awaited`)
MAX_FETCH_EVERY = 1_000_000  # the most calls between two fetches (`fetch_every`)
MAX_REPEAT = 10_000  # the most runs per compared value
MAX_COUNT = 1_000_000  # the most of any other count: `keys`, `max_restarts`, `loads`, `nth`
MAX_RATE = 1e6  # the most calls per second per client (and the largest `weight`)
PLACEHOLDERS = frozenset({"key", "client", "run_dir", "pid"})  # of request templates: `{key}`

EVENT_TYPES: dict[str, type[Any]] = {  # the events an `after` trigger may name
    cls.__name__: cls
    for cls in typing.get_args(events.Event)
    if cls not in (events.EventsDropped, events.EventsUnpublished)
}

# The types of plan values, with their limits (msgspec checks them; `reading` words the errors).
Seconds = Annotated[float, Meta(gt=0, le=MAX_SECONDS)]
SecondsOrZero = Annotated[float, Meta(ge=0, le=MAX_SECONDS)]
Interval = Annotated[float, Meta(ge=MIN_EVERY, le=MAX_SECONDS)]
Name = Annotated[str, Meta(pattern=r"\A[\w.-]+\Z")]
Text = Annotated[str, Meta(max_length=10_000)]
Count = Annotated[int, Meta(ge=1, le=MAX_COUNT)]
MAX_SEED = 2**63 - 1  # the largest seed (`--seed`); a run's is `seed + repeat - 1`
Seed = Annotated[int, Meta(ge=-(2**63), le=MAX_SEED)]
Repeat = Annotated[int, Meta(ge=1, le=MAX_REPEAT)]
Restart = Literal["permanent", "transient", "temporary"]
BackupDamage = Literal["delete", "truncate", "flip", "foreign", "digests"]  # corrupt_backup's `how`
Names = Annotated[tuple[str, ...], Meta(min_length=1)]


class PlanError(ConfigError):
    """A plan is invalid: the message names the file, the line, the key and what is wrong.

    Attributes:
        source: the plan's file name (or `"<plan>"` for text without a file).
        line: the 1-based line of the key (0 if there is no such key, e.g. a missing one).
        key: the key's dotted path, array elements as `[i]` (e.g. `faults[1].target`).
        problem: what is wrong, without the location.
    """

    def __init__(self, source: str, line: int, key: str, problem: str) -> None:
        where = f"{source}:{line}" if line else source
        super().__init__(f"{where}: {key}: {problem}" if key else f"{where}: {problem}")
        self.source, self.line, self.key, self.problem = source, line, key, problem

    def __reduce__(self) -> tuple[Any, ...]:
        return (type(self), (self.source, self.line, self.key, self.problem))


class _Table(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A table of a plan: its fields are its keys (`encode_name`); other keys are refused."""


class ManagerPlan(_Table, frozen=True, tag_field="_node", tag="manager"):
    """One manager of the tree: what `ManagerSpec` it becomes in every run (times in seconds)."""

    name: Name  # the manager's (registrar's) name
    setup: str  # import path of its `setup(registrar, **options)`: "module:function"
    options: dict[str, Any] = {}  # for `setup`
    isolation: Literal["thread", "process"] = "process"
    restart: Restart = "permanent"
    heartbeat: Seconds | None = 0.25  # between heartbeat pings; `None` (`false`): off
    heartbeat_timeout: Seconds | None = None  # silence until hung (`None`: 3 heartbeats)
    shutdown: Seconds = 5.0  # a clean stop may take this long before it is killed
    start_timeout: Seconds = 30.0  # to restore, set up and serve
    host: Name | None = None  # a host of `[hosts]` (None: the run's own host, the first)


class SupervisorPlan(_Table, frozen=True, tag_field="_node", tag="supervisor"):
    """A supervisor of the tree (the top one is `Plan.tree`); a child with `children` is one."""

    name: Name
    children: Annotated[tuple[ManagerPlan | SupervisorPlan, ...], Meta(min_length=1)]
    strategy: Literal["one_for_one", "one_for_all", "rest_for_one"] = "one_for_one"
    max_restarts: Annotated[int, Meta(ge=0, le=MAX_COUNT)] = 3  # at most this many restarts
    period: Seconds = 5.0  # ... within this many seconds
    backoff: Backoff = msgspec.field(default_factory=Backoff)  # delay before restarts
    restart: Restart = "permanent"  # its restart type in its parent (nested ones only)

    def managers(self) -> list[ManagerPlan]:
        """Every manager below this supervisor, depth first, in start order."""
        nested = (c.managers() if isinstance(c, SupervisorPlan) else [c] for c in self.children)
        return [manager for managers in nested for manager in managers]

    def supervisors(self) -> list[SupervisorPlan]:
        """This supervisor and every nested one, depth first."""
        nested = (c.supervisors() for c in self.children if isinstance(c, SupervisorPlan))
        return [self, *(supervisor for supervisors in nested for supervisor in supervisors)]


class BackoffPlan(_Table, frozen=True):
    """`backoff = { ... }`: the keys of `Backoff`, within a plan's limits."""

    initial: SecondsOrZero = 0.0
    factor: Annotated[float, Meta(ge=1, le=MAX_SECONDS)] = 2.0
    max: SecondsOrZero = 30.0
    jitter: Annotated[float, Meta(ge=0, le=1)] = 0.2


class CallMix(_Table, frozen=True):
    """One kind of call the workload makes (an entry of `[[workload.calls]]`); `request` is a
    template (`{key}`, `{client}`, `{run_dir}`; a string that is exactly `"{pid}"`: the pid)."""

    manager: str  # the provider registrar called
    server: Annotated[str, Meta(min_length=1)]  # the resource server on it
    weight: Annotated[float, Meta(gt=0, le=MAX_RATE)] = 1.0  # relative frequency
    shared: Annotated[float, Meta(ge=0, le=1)] = 0.5  # of calls for one of `keys` shared requests
    keys: Count = 4  # the rest ask for a request of their own
    again: Annotated[float, Meta(ge=0, le=1)] = 0.0  # of answered calls, called again while held
    request: Any = "{key}"
    factory: str | None = None  # import path of `factory(key, context) -> request`


class Workload(_Table, frozen=True):
    """What the clients do while faults hit the tree (times in seconds)."""

    clients: Annotated[int, Meta(ge=0, le=MAX_CLIENTS)] = 1  # threads, each a registrar
    rate: Annotated[float, Meta(ge=1 / MAX_SECONDS, le=MAX_RATE)] | None = 5.0  # None: "max"
    arrivals: Literal["poisson", "fixed"] = "poisson"  # seeded gaps of mean 1/rate, or fixed
    hold: SecondsOrZero = 0.5  # a client keeps each resource this long, then unloads it
    timeout: Seconds = 5.0  # a call may take this long, retries through restarts included
    retry: bool = True  # false: a call is made once, never retried (a careless caller)
    awaited: Annotated[int, Meta(ge=0, le=MAX_AWAITED)] = 0  # >0: calls awaited at once, each slot
    cancel: Annotated[float, Meta(ge=0, le=1)] = 0.0  # of the awaited calls, the share cancelled
    cancel_within: SecondsOrZero = 0.05  # each cancelled 0 to this many seconds after it starts
    fetch_every: Annotated[int, Meta(ge=0, le=MAX_FETCH_EVERY)] = 0  # >0: fetch after N calls
    status_wait: SecondsOrZero = 0.0  # >0: each status callback of `slow_clients` waits so long
    slow_clients: Annotated[int, Meta(ge=0, le=MAX_CLIENTS)] = 1  # the first N clients
    calls: tuple[CallMix, ...] = ()
    # the calls made, `[client, n]` pairs (the client's n-th call due, from 1; its draws are
    # made either way, so the calls made are as they were): None, every one (`shrink`)
    only: tuple[tuple[Annotated[int, Meta(ge=0, le=MAX_CLIENTS)], Count], ...] | None = None

    def callers(self) -> list[int]:
        """The clients started, by index: every one, but one `only` gives no call."""
        named = None if self.only is None else {client for client, _ in self.only}
        return [i for i in range(self.clients) if named is None or i in named]


class Trigger(_Table, frozen=True):
    """`after = { event = "ChildRestarted", child = "erm", nth = 1 }`: when a fault fires."""

    event: str  # an event type of `rr_actors.events`
    match: dict[str, Any] = {}  # its field values
    nth: Count = 1  # the fault fires after the n-th matching event of the run


def _after(name: str, event: type[Any]) -> type[msgspec.Struct]:
    """The table `after = { event = name, ... }` takes: `nth` and any field of the event."""
    hints = typing.get_type_hints(event)
    keys = [f.name for f in dataclasses.fields(event) if f.name not in ("at", "hlc")]  # (times)
    fields = [(key, hints[key] | msgspec.UnsetType, msgspec.UNSET) for key in keys]
    return msgspec.defstruct(
        name, [("nth", Count, 1), *fields], bases=(_Table,), tag=name, tag_field="event"
    )


AFTER: Any = functools.reduce(operator.or_, map(_after, EVENT_TYPES, EVENT_TYPES.values()))


class FaultPlan(_Table, frozen=True):
    """One entry of `[[faults]]`: what to do, to whom (one of `targets`, seeded; empty, for
    `kill_resource`: any process manager's), and when: one of `at`, `every` (an interval, or
    `(low, high)` for seeded random ones in between) and `after` (times in seconds)."""

    kind: FaultKind
    targets: Names = msgspec.field(default=(), name="target")  # managers (hosts: freeze, ...)
    link: tuple[Name, Name] | None = None  # cut: the two hosts whose link goes down
    hosts: Annotated[tuple[Name, ...], Meta(min_length=1)] = ()  # partition: cut from the rest
    at: Annotated[tuple[SecondsOrZero, ...], Meta(min_length=1)] = ()  # from the workload's start
    every: float | tuple[float, float] | None = None  # `reading` checks it: Interval or Every
    start: SecondsOrZero = 0.0  # with `every`: the first interval starts here
    stop: Seconds | None = None  # with `every`: none at or after this (default: the end)
    count: Annotated[int, Meta(ge=1, le=MAX_INJECTIONS)] | None = None  # with `every`
    after: Trigger | None = None  # inject when an event happens, `delay` later
    delay: SecondsOrZero = 0.0
    # a hang's, load error's, partition_serving's, split_brain's, deaf_manager's,
    # duplicate_delivery's (default 1 s)
    for_s: Seconds | None = msgspec.field(default=None, name="for")
    loads: Count = 1  # load_error: how many loads raise (without `for_s`)
    server: str | None = None  # load_error: only loads of this server (default: any)
    message: Text = "injected load error"  # load_error: the exception's message
    # corrupt_backup: what is done to the killed manager's backup before its restart
    how: BackupDamage = "flip"

    def most_injections(self, duration: float) -> int:
        """At most how many injections this fault makes in a run of `duration` seconds."""
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


class Every(_Table, frozen=True):
    """`every = { min = 0.5, max = 2 }`: seeded random intervals drawn in between."""

    min: Interval
    max: Interval

    def __post_init__(self) -> None:
        if self.max < self.min:
            raise ValueError(f"max ({self.max:g} s) must not be less than min ({self.min:g} s)")


class HostsPlan(_Table, frozen=True):
    """`[hosts]`: the run's hosts, network namespaces joined by a veth between every two
    (needs root), on one Zenoh system with mutual TLS. The first is the run's own host:
    its clients and every manager without `host` (times in seconds)."""

    names: Annotated[tuple[Name, ...], Meta(min_length=2, max_length=MAX_HOSTS)]
    lease: Annotated[float, Meta(ge=0.01, le=3600)] = 1.0  # `ZenohNetwork(lease=)` of every host
    start_timeout: Seconds = 30.0  # a host's router and tree start within this long
    # rule 22 at a heal: "first_served", "majority" or "module:function" (`resolve=`)
    resolve: Annotated[str, Meta(min_length=1)] = "first_served"

    @property
    def home(self) -> str:
        """The run's own host (the first name)."""
        return self.names[0]


class Compare(_Table, frozen=True):
    """`[compare]`: run the plan once per value of one setting, a dotted key: `"tree.strategy"`,
    a child by its name `"tree.children.erm.heartbeat"`, a fault by its index `"faults.0.every"`."""

    setting: Annotated[str, Meta(min_length=1)]
    values: Annotated[tuple[Any, ...], Meta(min_length=1)]  # in the order the runs take them


@dataclasses.dataclass(frozen=True)
class Plan:
    """A whole experiment: validated, ready to run with `rr_actors_lab.experiments.run`. `variants`
    holds `(value, plan)` per compared value (`((None, self),)` without `compare`)."""

    name: str  # the `runs.csv` column `plan`
    duration: Seconds  # of workload and faults per run
    tree: SupervisorPlan
    description: str = ""
    repeat: Repeat = 1  # runs per compared value
    seed: Seed = 0  # of the first run (run `i` of a value uses `seed + i`)
    recovery_timeout: Seconds = 10.0  # at the end, to wait for every manager to serve
    state: bool = True  # whether managers keep durable catalogs (a state directory per run)
    stop: Literal["reverse", "parallel"] = "reverse"  # how a run's end stops the tree
    # when the run's event log subscribes: before the tree starts, or once it serves (its
    # managers' starts unheard; their processes' forwarding switched on mid-run)
    listen: Literal["before_start", "after_start"] = "before_start"
    workload: Workload = Workload(clients=0)  # noqa: RUF009 - frozen, so shared safely
    faults: tuple[FaultPlan, ...] = ()
    hosts: HostsPlan | None = None
    compare: Compare | None = None
    variants: tuple[tuple[Any, Plan], ...] = dataclasses.field(
        default=(), repr=False, compare=False
    )
    source: str | None = None  # the file it was read from (`None` for text)
    base_dir: str | None = None  # searched first for its import paths (the file's own)

    def managers(self) -> list[ManagerPlan]:
        """Every manager of the tree, depth first, in start order."""
        return self.tree.managers()

    def manager(self, name: str) -> ManagerPlan:
        """The manager called `name` (`KeyError` if none)."""
        return {manager.name: manager for manager in self.managers()}[name]

    def host_of(self, manager: str) -> str | None:
        """The host a manager runs on (`None` without `[hosts]`)."""
        if self.hosts is None:
            return None
        placed = self.manager(manager).host
        return placed if placed is not None else self.hosts.home

    def setting_label(self) -> str:
        """The compared setting's key, or `""` without `compare`."""
        return self.compare.setting if self.compare is not None else ""

    def with_changes(
        self, *, repeat: int | None = None, seed: int | None = None, duration: float | None = None
    ) -> Plan:
        """A copy with another `repeat`, `seed` or `duration` (`None`: keep), for every variant (a
        shorter `duration` drops the faults after the new end).

        Raises:
            ConfigError: `repeat` not from 1 to `MAX_REPEAT`, `seed` (or `seed + repeat - 1`) not
                64 bits, `duration` not in (0, `MAX_SECONDS`], or an `every` fault past
                `MAX_INJECTIONS`.
        """
        changes: dict[str, Any] = {}
        for key, value, hint, what in (
            ("repeat", repeat, Repeat, f"an int from 1 to {MAX_REPEAT}"),
            ("seed", seed, Seed, "a 64-bit integer"),
            ("duration", duration, Seconds, f"a positive number of seconds up to {MAX_SECONDS:g}"),
        ):
            try:
                changes |= {} if value is None else {key: msgspec.convert(value, hint)}
            except msgspec.ValidationError:
                raise ConfigError(f"{key} must be {what}, got {value!r}") from None
        for index, fault in (x for _, p in self.variants for x in enumerate(p.faults)):
            if duration is not None and fault.most_injections(duration) > MAX_INJECTIONS:
                problem = f"would inject more than {MAX_INJECTIONS} times in a run"
                raise ConfigError(f"duration {duration:g} s: faults[{index}] {problem}")
        last = changes.get("seed", self.seed) + changes.get("repeat", self.repeat) - 1
        if last > MAX_SEED:
            raise ConfigError(f"seed: the last run's seed {last} would be past 64 bits")
        variants = tuple((v, dataclasses.replace(p, **changes)) for v, p in self.variants)
        return dataclasses.replace(self, **changes, variants=variants)
