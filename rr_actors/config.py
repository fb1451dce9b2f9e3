"""Configuration as frozen, validated data: registrars, managers, supervisors, backoff.

`RegistrarConfig` is TeMoto's `Configuration` (thesis table 4.2); `ManagerSpec` and
`SupervisorSpec` are OTP's child specifications; `Backoff` is what OTP lacks. Each raises
`ConfigError` naming the field at construction and is changed with `dataclasses.replace`.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import math
import os
import random as _random
import re
from collections.abc import Callable, Collection, Iterable, Iterator, Sequence
from collections.abc import Set as AbstractSet
from typing import Any, Literal

from rr_actors._types import Setup, Status
from rr_actors.errors import ConfigError, _known_names

__all__ = [
    "DEFAULT_MAX_MESSAGE_BYTES",
    "DEFAULT_MAX_PENDING",
    "DEFAULT_MAX_WORKERS",
    "MAX_DEPENDENCY_DEPTH",
    "NAME",
    "NAME_MAX",
    "Backoff",
    "Isolation",
    "ManagerSpec",
    "RegistrarConfig",
    "RestartType",
    "Setup",
    "Steps",
    "Strategy",
    "SupervisorSpec",
    "check_choice",
    "check_name",
    "check_seconds",
    "check_strs",
    "is_loopback",
    "managers",
    "tree_names",
    "walk",
]

RestartType = Literal["permanent", "transient", "temporary"]
Strategy = Literal["one_for_one", "one_for_all", "rest_for_one"]
Isolation = Literal["thread", "process"]

NAME_MAX = 64
"""The most characters in a registrar's, system's or member's name (X.509's `ub-common-name`)."""

NAME = re.compile(rf"[A-Za-z0-9_][A-Za-z0-9_.\-]{{0,{NAME_MAX - 1}}}")
"""A valid name (`fullmatch`): it names files, so it never starts with `.` or `-`."""


def check_name(field: str, value: object, what: str = "a name") -> str:
    """`value` if it is a name (`NAME`), else `ConfigError` naming `field` and `what` a name is
    here."""
    if isinstance(value, str) and len(value) > NAME_MAX:
        raise ConfigError(
            f"{field} {value!r} is {len(value)} characters long: {what} has at most "
            f"{NAME_MAX} (NAME_MAX, the longest common name a certificate holds)"
        )
    if not isinstance(value, str) or NAME.fullmatch(value) is None:
        raise ConfigError(
            f"{field} {value!r} is not {what}: letters, digits, '_', '-' or '.', not "
            f"starting with '.' or '-', at most {NAME_MAX} characters"
        )
    return value


def check_strs(**names: object) -> None:
    """`ConfigError` naming the first argument that is not a str (a name the other end judges)."""
    for field, value in names.items():
        if not isinstance(value, str):
            raise ConfigError(f"{field} must be a name (a str), got {value!r}")


Durability = Literal["process", "power"]

DEFAULT_MAX_WORKERS = 64
"""Worker threads a registrar runs callbacks on at once, unless `max_workers` says otherwise."""

DEFAULT_MAX_PENDING = 1000
"""Loads a server may have queued or running at once, unless `max_pending` says otherwise."""

DEFAULT_MAX_MESSAGE_BYTES = 16 * 1024 * 1024
"""The largest pickled message (16 MiB) a registrar takes from another process by default."""


MAX_DEPENDENCY_DEPTH = 64
"""How deep a load chain may grow: a deeper call fails with `DependencyCycleError` (rule 6)
rather than deadlock.
"""


def check_seconds(
    field: str, value: object, *, allow_none: bool = False, allow_zero: bool = False
) -> None:
    """`ConfigError` naming `field` unless `value` is a finite positive number of seconds
    (non-negative with `allow_zero`; `None` with `allow_none`; never a bool)."""
    if value is None and allow_none:
        return
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not math.isfinite(value)
        or value < 0
        or (value == 0 and not allow_zero)
    ):
        kind = "non-negative" if allow_zero else "positive"
        raise ConfigError(f"{field} must be a {kind} number of seconds, got {value!r}")


def _check_count(field: str, value: object, least: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise ConfigError(f"{field} must be an int >= {least}, got {value!r}")


def check_choice(field: str, value: object, choices: Sequence[str]) -> None:
    """Raise `ConfigError` naming `field` unless `value` is one of `choices`."""
    if value not in choices:
        raise ConfigError(f"{field} must be one of {', '.join(map(repr, choices))}, got {value!r}")


def is_loopback(host: str) -> bool:
    """Whether `host` names this machine only (`localhost`, 127.0.0.0/8, `::1`; another DNS name
    may resolve anywhere): where one may listen without the user's leave."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@dataclasses.dataclass(frozen=True)
class Steps:
    """The protocol's replaceable steps: a value passed in, `None` in a field meaning the
    registrar's (or the supervisor's) own code, anything else a copy of it that runs instead.

    Given through `RegistrarConfig(steps=)` (that registrar only) or `Supervisor(steps=)`
    (the tree's supervisors and the managers and `registrar()`s they start whose config
    names no steps of its own). The classroom kit (`rr_actors_lab.teach`) hands a student's
    copy in this way; its `STEPS` gives the registrar's own code of each. A step runs on the
    registrar's actor thread (or the supervisor's): it must return at once and must not call
    a registrar. It reaches a process manager only if it pickles (a module-level function).

    Attributes:
        climb: `climb(parent, resources, status) -> ids`: the resources a status delivered
            to a consumer id climbs to.
        shares: `shares(stored, request, loading, failed) -> bool`: the catalog's dedup test
            of a plain request.
        group: `group(strategy, names, crashed) -> names`: the children a crash restarts.
        unloads: `unloads(left) -> bool`: whether a release unloads (`left`: ids still on it).
        in_doubt: `in_doubt(state) -> bool`: whether a restored row was cut short by a crash.
        reconcile: `reconcile(mine, held, under_way) -> (release, unknown)`: a provider's
            reconcile with one consumer.
        release_order: `release_order(dependencies) -> order`: a teardown's order, `"unload"`
            among the dependencies' query ids.
        recent: `recent(times, now, period) -> int`: the restarts that count toward intensity
            (monotonic seconds).

    Raises:
        ConfigError: a field is neither `None` nor callable.
    """

    climb: Callable[[str | None, Collection[str], Status], Iterable[str]] | None = None
    shares: Callable[[Any, Any, bool, bool], bool] | None = None
    group: Callable[[str, Sequence[str], str], Iterable[str]] | None = None
    unloads: Callable[[Collection[str]], bool] | None = None
    in_doubt: Callable[[str], bool] | None = None
    reconcile: (
        Callable[
            [AbstractSet[str], AbstractSet[str], AbstractSet[str]],
            tuple[Iterable[str], Iterable[str]],
        ]
        | None
    ) = None
    release_order: Callable[[tuple[str, ...]], Iterable[str]] | None = None
    recent: Callable[[tuple[float, ...], float, float], int] | None = None

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if value is not None and not callable(value):
                raise ConfigError(f"steps.{field.name} must be a function or None, got {value!r}")


@dataclasses.dataclass(frozen=True)
class RegistrarConfig:
    """How a [`ResourceRegistrar`][rr_actors.ResourceRegistrar] behaves (TeMoto's `Configuration`).

    Attributes:
        name: registrar name, unique within its system (`NAME`, at most 64 characters).
        backup_path: SQLite file that keeps the catalog, or `None` for an in-memory catalog.
        save_interval: with a backup, flush changes every this many seconds (`None`: never on a
            timer); a crash loses at most one interval of changes.
        save_on_modify: with a backup, every load and unload is durable before its answer.
        erase_on_destruct: remove the backup after a clean `stop()` (a crash keeps it).
        call_timeout: default `timeout` of every blocking call, in seconds.
        durability: what an answered change survives (rule 14): `"process"` a kill of the
            process (nothing synced), `"power"` also an OS crash or power loss (all a restore
            reads synced before the answer; slower). Under a supervisor, at least the tree's.
        max_workers: worker threads running its callbacks at once (a running coroutine
            `load` holds a place, not a thread); more wait, in order.
        compare_timeout: seconds user code matching a request without a digest may run (`__eq__`,
            `__hash__`, pickling); past them the call fails with `CallTimeoutError`.
        unload_timeout: seconds an `unload` may run (`None`: no bound); past them the resource is
            dropped as failed and a waiting caller gets `CallTimeoutError`.
        max_message_bytes: the largest pickled message to or from this registrar across processes
            (default 16 MiB); a larger one fails its call with `MessageTooLargeError`, before a
            request is sent.
        max_pending: new loads each server may have queued or running (default 1000; a server's own
            `register_server(..., max_pending=)` wins; several consumers each get a share). Past it
            a call waits and asks again within its `timeout`, then raises `OverloadedError`.
        steps: the protocol steps this registrar runs instead of its own (`Steps`; default:
            none replaced). Not in `to_dict`.
    """

    name: str = "untitled"
    backup_path: str | os.PathLike[str] | None = None
    save_interval: float | None = 60.0
    save_on_modify: bool = False
    erase_on_destruct: bool = False
    call_timeout: float = 10.0
    durability: Durability = "process"
    max_workers: int = DEFAULT_MAX_WORKERS
    compare_timeout: float = 5.0
    unload_timeout: float | None = 60.0
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    max_pending: int = DEFAULT_MAX_PENDING
    steps: Steps = Steps()

    def __post_init__(self) -> None:
        check_name("name", self.name, "a registrar name")
        if not isinstance(self.steps, Steps):
            raise ConfigError(f"steps must be an rr_actors.config.Steps, got {self.steps!r}")
        if self.backup_path is not None and not isinstance(self.backup_path, str | os.PathLike):
            raise ConfigError(f"backup_path must be a path or None, got {self.backup_path!r}")
        check_seconds("save_interval", self.save_interval, allow_none=True)
        check_seconds("call_timeout", self.call_timeout)
        for flag in ("save_on_modify", "erase_on_destruct"):
            if not isinstance(getattr(self, flag), bool):
                raise ConfigError(f"{flag} must be a bool, got {getattr(self, flag)!r}")
        if self.durability not in ("process", "power"):
            raise ConfigError(f"durability must be 'process' or 'power', got {self.durability!r}")
        _check_count("max_workers", self.max_workers, 1)
        _check_count("max_pending", self.max_pending, 1)
        check_seconds("compare_timeout", self.compare_timeout)
        check_seconds("unload_timeout", self.unload_timeout, allow_none=True)
        _check_count("max_message_bytes", self.max_message_bytes, 1)

    def to_dict(self) -> dict[str, Any]:
        """Return the configuration as plain JSON-able data (with a schema version)."""
        data = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        del data["steps"]  # (functions: not data)
        data["backup_path"] = None if self.backup_path is None else os.fspath(self.backup_path)
        data["schema"] = 1
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> RegistrarConfig:
        """Build a configuration from [`to_dict`][rr_actors.RegistrarConfig.to_dict] output.

        Raises:
            ConfigError: unknown schema version, unknown field, or an invalid value.
        """
        if data.get("schema") != 1:
            raise ConfigError(f"unsupported RegistrarConfig schema {data.get('schema')!r}")
        fields = {f.name for f in dataclasses.fields(cls)} - {"steps"}
        unknown = set(data) - fields - {"schema"}
        if unknown:
            named = sorted(unknown)
            raise ConfigError(
                f"unknown RegistrarConfig fields: {named}" + _known_names(named[0], fields)
            )
        return cls(**{k: v for k, v in data.items() if k in fields})


@dataclasses.dataclass(frozen=True)
class Backoff:
    """Exponential backoff with jitter before a restart (something OTP does not have).

    The n-th restart within the intensity window waits `min(max, initial * factor ** (n - 1))`
    seconds, scaled by a random factor in `[1 - jitter, 1 + jitter]` (never beyond `max`).

    Attributes:
        initial: delay before the first restart, in seconds (0, the default: none).
        factor: growth of the delay per further restart within the window (>= 1).
        max: the longest delay, in seconds.
        jitter: relative spread of the delay, from 0 (none) to 1.
    """

    initial: float = 0.0
    factor: float = 2.0
    max: float = 30.0
    jitter: float = 0.2

    def __post_init__(self) -> None:
        check_seconds("Backoff.initial", self.initial, allow_zero=True)
        check_seconds("Backoff.max", self.max, allow_zero=True)
        if (
            isinstance(self.factor, bool)
            or not isinstance(self.factor, int | float)
            or not (math.isfinite(self.factor) and self.factor >= 1)
        ):
            raise ConfigError(f"Backoff.factor must be a number >= 1, got {self.factor!r}")
        if (
            isinstance(self.jitter, bool)
            or not isinstance(self.jitter, int | float)
            or not (0 <= self.jitter <= 1)
        ):
            raise ConfigError(f"Backoff.jitter must be a number from 0 to 1, got {self.jitter!r}")
        if self.max < self.initial:
            raise ConfigError(
                f"Backoff.max ({self.max!r}) must not be less than Backoff.initial "
                f"({self.initial!r})"
            )

    def delay(self, attempt: int, random: Callable[[], float] = _random.random) -> float:
        """The delay in seconds before restart number `attempt` (1 = first) of a window.

        Args:
            attempt: how many restarts (this one included) fall in the intensity window.
            random: returns a float in `[0, 1)`; injectable for tests.
        """
        if self.initial == 0 or attempt < 1:
            return 0.0
        base = min(self.max, self.initial * self.factor ** min(attempt - 1, 1000))
        spread = 1.0 + self.jitter * (2.0 * random() - 1.0)
        return min(self.max, max(0.0, base * spread))


@dataclasses.dataclass(frozen=True)
class ManagerSpec:
    """How to start and supervise one manager (OTP's child specification, as data).

    Attributes:
        name: the manager's registrar name, unique in the whole supervision tree.
        setup: `setup(registrar)`, registering its servers after the restore and before
            traffic (`None`: no servers); cloudpickled for a process manager. It runs on a
            process manager's main thread (bounded by `start_timeout`) or the supervisor's
            thread (unbounded), and supervision waits for it.
        isolation: `"thread"` (in the supervisor's process) or `"process"` (its own).
        restart: `"permanent"`, `"transient"` (only after an abnormal exit) or `"temporary"`.
        config: its registrar's configuration (same `name`). Default: `RegistrarConfig(name)`,
            with a supervisor's `state_dir` a backup `<state_dir>/<name>.db`, `save_on_modify`.
        shutdown: seconds a clean stop may take before the manager is killed (a process's
            registrar's own stop ends a fifth of it, 1 s at most, early: it reports and
            exits within it; a thread's registrar is told to crash once its callback
            returns, and a restart before then fails with `DuplicateNameError`, a crash).
        heartbeat: seconds between pings to a process manager (`None`: off); none once
            its supervisor's `stop()` began (its `shutdown` bounds its stop). A process
            pings 500 a second at most, all its managers': beyond, a WARNING says how often.
        heartbeat_timeout: seconds without an answer after which a process manager is hung,
            killed and handled as a crash (default three `heartbeat`s). Time spent waiting
            for a CPU (Linux) or busy (`ManagerOverloaded`) does not count (docs: "What
            counts as a hang"); one unable to accept connections that long is killed too.
        start_timeout: seconds a manager may take to restore, set up and serve.
    """

    name: str
    setup: Setup | None = None
    isolation: Isolation = "thread"
    restart: RestartType = "permanent"
    config: RegistrarConfig | None = None
    shutdown: float = 5.0
    heartbeat: float | None = 0.25
    heartbeat_timeout: float | None = None
    start_timeout: float = 30.0

    def __post_init__(self) -> None:
        check_name("name", self.name, "a manager name")
        if self.setup is not None and not callable(self.setup):
            raise ConfigError(
                f"setup of manager {self.name!r} must be callable, got {self.setup!r}"
            )
        check_choice("isolation", self.isolation, ("thread", "process"))
        check_choice("restart", self.restart, ("permanent", "transient", "temporary"))
        if self.config is not None:
            if not isinstance(self.config, RegistrarConfig):
                raise ConfigError(f"config must be a RegistrarConfig, got {self.config!r}")
            if self.config.name != self.name:
                raise ConfigError(
                    f"config.name ({self.config.name!r}) must equal the manager's name "
                    f"({self.name!r})"
                )
        check_seconds("shutdown", self.shutdown)
        if self.heartbeat is not None:
            check_seconds("heartbeat", self.heartbeat)
        if self.heartbeat_timeout is not None:
            check_seconds("heartbeat_timeout", self.heartbeat_timeout)
        check_seconds("start_timeout", self.start_timeout)

    @property
    def hang_after(self) -> float | None:
        """Seconds without a heartbeat answer after which it is hung (`None`: off)."""
        if self.heartbeat is None:
            return None
        if self.heartbeat_timeout is not None:
            return self.heartbeat_timeout
        return 3.0 * self.heartbeat


@dataclasses.dataclass(frozen=True)
class SupervisorSpec:
    """A nested supervisor as a child of another (its arguments are `Supervisor`'s).

    When it gives up, its parent sees OTP's `shutdown`: a `permanent` one is restarted under
    the parent's strategy and intensity (escalation, as in OTP); others stay down.

    With `isolation="process"` it is a *pool*: it runs in an OS process of its own with
    its thread managers (an Orleans silo hosting grains; in OTP terms a supervisor whose
    children share its node). It restarts each of them alone, by its own strategy and
    intensity; a SIGKILL of its process (or its give-up, or a hang of its process) is one
    crash of this child in its parent, which starts the process again, its managers
    restoring their catalogs before they serve (docs: "Big trees").

    Attributes:
        name: the child's name in its parent (unique in the tree).
        children: its children, started in this order.
        strategy, max_restarts, period, backoff: as for `Supervisor`.
        restart: its restart type in the parent.
        state_dir: where its managers keep their catalogs (default: the parent's).
        isolation: `"thread"` (default: it runs in its parent's process) or `"process"`
            (a pool in its own OS process; its children must all be thread managers and
            in-process supervisors, their setups picklable).
    """

    name: str
    children: tuple[ManagerSpec | SupervisorSpec, ...]
    strategy: Strategy = "one_for_one"
    max_restarts: int = 3
    period: float = 5.0
    backoff: Backoff = Backoff()
    restart: RestartType = "permanent"
    state_dir: str | os.PathLike[str] | None = None
    isolation: Isolation = "thread"

    def __post_init__(self) -> None:
        check_name("name", self.name, "a supervisor name")
        check_choice("isolation", self.isolation, ("thread", "process"))
        object.__setattr__(self, "children", tuple(self.children))
        check_choice("strategy", self.strategy, ("one_for_one", "one_for_all", "rest_for_one"))
        check_choice("restart", self.restart, ("permanent", "transient", "temporary"))
        _check_count("max_restarts", self.max_restarts, 0)
        check_seconds("period", self.period)
        if not isinstance(self.backoff, Backoff):
            raise ConfigError(f"backoff must be an rr_actors.Backoff, got {self.backoff!r}")
        seen: set[str] = set()
        for child in self.children:
            if not isinstance(child, ManagerSpec | SupervisorSpec):
                raise ConfigError(
                    f"children must be ManagerSpec or SupervisorSpec values, got {child!r}"
                )
        for name in tree_names(self):
            if name in seen:
                raise ConfigError(f"children: the name {name!r} is used twice in the tree")
            seen.add(name)
        if self.isolation == "process":
            _check_pool(self)

    def has_processes(self) -> bool:
        return any(c.isolation == "process" for c, _ in walk(self))


def _check_pool(pool: SupervisorSpec) -> None:
    """`ConfigError` unless everything below pool `pool` runs in its process (threads)."""
    for child, _ in walk(pool):
        if child.isolation == "process":
            kind = "manager" if isinstance(child, ManagerSpec) else "supervisor"
            raise ConfigError(
                f"children: {kind} {child.name!r} has isolation='process' inside supervisor "
                f"{pool.name!r}, which runs in a process of its own (isolation='process'): "
                "a pool holds thread managers only; make it a sibling of the pool instead"
            )


def walk(
    spec: SupervisorSpec, path: tuple[SupervisorSpec, ...] = ()
) -> Iterator[tuple[ManagerSpec | SupervisorSpec, tuple[SupervisorSpec, ...]]]:
    """Every child below `spec`, depth first, as `(child, path)`: the supervisors from `spec`
    down."""
    path = (*path, spec)
    for child in spec.children:
        yield child, path
        if isinstance(child, SupervisorSpec):
            yield from walk(child, path)


def tree_names(spec: SupervisorSpec) -> list[str]:
    return [child.name for child, _ in walk(spec)]


def managers(spec: SupervisorSpec) -> list[ManagerSpec]:
    return [child for child, _ in walk(spec) if isinstance(child, ManagerSpec)]
