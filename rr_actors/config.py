"""Configuration as frozen, validated data: registrars, managers, supervisors, backoff.

`RegistrarConfig` is TeMoto's `Configuration` (thesis table 4.2); `ManagerSpec` and
`SupervisorSpec` are OTP's child specifications; `Backoff` is what OTP lacks. Each is
validated at construction (`ConfigError` names the field) and changed with
`dataclasses.replace`.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import math
import os
import random as _random
import re
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Literal

from rr_actors._types import Setup
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
    "Strategy",
    "SupervisorSpec",
    "check_choice",
    "check_name",
    "check_seconds",
    "is_loopback",
    "managers",
    "tree_names",
    "walk",
]

RestartType = Literal["permanent", "transient", "temporary"]
Strategy = Literal["one_for_one", "one_for_all", "rest_for_one"]
Isolation = Literal["thread", "process"]

NAME_MAX = 64
"""The most characters in a registrar's, a system's or a member's name: the longest
common name a certificate holds (X.509's `ub-common-name`), as a member's name is one."""

NAME = re.compile(rf"[A-Za-z0-9_][A-Za-z0-9_.\-]{{0,{NAME_MAX - 1}}}")
"""A valid name, matched whole (`fullmatch`: `$` would accept a trailing newline): at most
`NAME_MAX` characters. It names files (`<name>.db`, `<name>.sock`), so it never starts
with `.` (`.`, `..`, hidden files) or `-` (read as an option by command-line tools)."""


def check_name(field: str, value: object, what: str = "a name") -> str:
    """`value` if it is a name (`NAME`), else `ConfigError` naming `field` and the rule broken.

    The one check of registrar, system and member names; a name too long (more than
    `NAME_MAX` characters) is told apart from one with a wrong character.

    Args:
        field: how the message names the argument or field (`"name"`, `"system"`).
        value: what was given.
        what: what a name is here, for the message (`"a member name"`).
    """
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


Durability = Literal["process", "power"]

DEFAULT_MAX_WORKERS = 64
"""Worker threads a registrar runs callbacks on at once, unless `max_workers` says otherwise."""

DEFAULT_MAX_PENDING = 1000
"""Loads a server may have queued or running at once, unless `max_pending` says otherwise:
far more than ordinary use has (issue 53)."""

DEFAULT_MAX_MESSAGE_BYTES = 16 * 1024 * 1024
"""The largest message (pickled) a registrar takes from another process, unless its
`max_message_bytes` says otherwise: 16 MiB."""


MAX_DEPENDENCY_DEPTH = 64
"""How deep a load chain may grow (a load whose `load` calls another, and so on): a call
that would make it deeper fails with `DependencyCycleError` (runaway recursion, rule 6),
rather than deadlock."""


def check_seconds(
    field: str, value: object, *, allow_none: bool = False, allow_zero: bool = False
) -> None:
    """Raise `ConfigError` naming `field` unless `value` is a finite number of seconds.

    It must be positive (or, with `allow_zero`, non-negative); `None` passes with
    `allow_none`. Booleans are refused although they are ints.
    """
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


def check_choice(field: str, value: object, choices: Sequence[str]) -> None:
    """Raise `ConfigError` naming `field` unless `value` is one of `choices`."""
    if value not in choices:
        raise ConfigError(f"{field} must be one of {', '.join(map(repr, choices))}, got {value!r}")


def is_loopback(host: str) -> bool:
    """Whether `host` names this machine only (`localhost`, 127.0.0.0/8, `::1`): where the
    observer and a carrier may listen without the user's leave to be reached from elsewhere.

    A DNS name other than `localhost` is not (it may resolve anywhere).
    """
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@dataclasses.dataclass(frozen=True)
class RegistrarConfig:
    """How a [`ResourceRegistrar`][rr_actors.ResourceRegistrar] behaves.

    Validated at construction; change a copy with `dataclasses.replace`.

    Attributes:
        name: registrar name, unique within its system; letters, digits, `_`, `-`, `.`,
            not starting with `.` or `-`, at most `NAME_MAX` (64) characters.
        backup_path: SQLite file that keeps the catalog, or `None` for an in-memory catalog.
        save_interval: with a backup, flush changes every this many seconds (`None`: never
            on a timer). A crash loses at most one interval of changes.
        save_on_modify: with a backup, make every load and unload durable before its
            caller gets the answer.
        erase_on_destruct: remove the backup after a clean `stop()` (a crash always keeps it).
        call_timeout: default `timeout` of every blocking call, in seconds.
        durability: `"process"` survives a crash of the process (SQLite `synchronous=NORMAL`),
            `"power"` also survives power loss (`synchronous=FULL`, slower).
        max_workers: worker threads that may run this registrar's callbacks at once
            (`load`, `unload`, status callbacks, comparisons of requests without a
            digest); callbacks beyond it wait in a queue, in order, for one to come free.
        compare_timeout: seconds the user code that matches a request without a digest
            (a custom class) with the requests served may run (its `__eq__`, `__hash__`,
            and pickling it for the backup); past them the call fails with
            `CallTimeoutError` and the registrar goes on serving.
        unload_timeout: seconds an `unload` callback may run (`None`: no bound); past
            them the resource is dropped from the catalog as failed, and a caller still
            waiting for the unload gets `CallTimeoutError`.
        max_message_bytes: the largest message, in bytes once pickled, that crosses a
            connection to this registrar from another process: a request or any other
            message it receives, and every answer it sends back. A caller in another
            process gets `MessageTooLargeError` before anything larger is sent; a larger
            response fails its call the same way (the consumer id is released). Messages
            within one process are not copied and not limited. Default: 16 MiB
            (`DEFAULT_MAX_MESSAGE_BYTES`), so that a message of plain bytes costs a
            manager far less than its default heartbeat timeout.
        max_pending: loads each server of this registrar may have queued or running at
            once (new loads: a dedup hit, or a caller joining a load under way, adds no
            work and is never refused). Past it a call waits and asks again within its
            `timeout` (a blocking one on its thread, an awaited one holding no thread),
            and gets `OverloadedError` (naming the registrar, the server and the bound)
            when too little time is left. Default: 1000 (`DEFAULT_MAX_PENDING`), which
            ordinary loads never reach; a server registered with its own
            (`register_server(..., max_pending=)`) has that one instead. A consumer
            registrar alone may take all of it; while others want loads there too, each
            takes at most its share (the bound divided among them), so one that floods a
            server cannot keep another's calls from it.

    Raises:
        ConfigError: a field is invalid; the message names it.
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

    def __post_init__(self) -> None:
        check_name("name", self.name, "a registrar name")
        if self.backup_path is not None and not isinstance(self.backup_path, str | os.PathLike):
            raise ConfigError(f"backup_path must be a path or None, got {self.backup_path!r}")
        check_seconds("save_interval", self.save_interval, allow_none=True)
        check_seconds("call_timeout", self.call_timeout)
        for flag in ("save_on_modify", "erase_on_destruct"):
            if not isinstance(getattr(self, flag), bool):
                raise ConfigError(f"{flag} must be a bool, got {getattr(self, flag)!r}")
        if self.durability not in ("process", "power"):
            raise ConfigError(f"durability must be 'process' or 'power', got {self.durability!r}")
        if (
            isinstance(self.max_workers, bool)
            or not isinstance(self.max_workers, int)
            or self.max_workers < 1
        ):
            raise ConfigError(f"max_workers must be an int >= 1, got {self.max_workers!r}")
        if (
            isinstance(self.max_pending, bool)
            or not isinstance(self.max_pending, int)
            or self.max_pending < 1
        ):
            raise ConfigError(f"max_pending must be an int >= 1, got {self.max_pending!r}")
        check_seconds("compare_timeout", self.compare_timeout)
        check_seconds("unload_timeout", self.unload_timeout, allow_none=True)
        if (
            isinstance(self.max_message_bytes, bool)
            or not isinstance(self.max_message_bytes, int)
            or self.max_message_bytes < 1
        ):
            raise ConfigError(
                f"max_message_bytes must be an int >= 1, got {self.max_message_bytes!r}"
            )

    def to_dict(self) -> dict[str, Any]:
        """Return the configuration as plain JSON-able data (with a schema version)."""
        data = dataclasses.asdict(self)
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
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - fields - {"schema"}
        if unknown:
            named = sorted(unknown)
            raise ConfigError(
                f"unknown RegistrarConfig fields: {named}" + _known_names(named[0], fields)
            )
        return cls(**{k: v for k, v in data.items() if k in fields})


# -- configuration -----------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Backoff:
    """Exponential backoff with jitter before a restart (something OTP does not have).

    The n-th restart within the supervisor's intensity window waits
    `min(max, initial * factor ** (n - 1))` seconds, scaled by a random factor in
    `[1 - jitter, 1 + jitter]` (never beyond `max`). The default (`initial=0`) restarts at once.

    Attributes:
        initial: delay before the first restart, in seconds (0: no delay at all).
        factor: growth of the delay per further restart within the window (>= 1).
        max: the longest delay, in seconds.
        jitter: relative spread of the delay, from 0 (none) to 1.

    Raises:
        ConfigError: a field is invalid; the message names it.
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
        setup: `setup(registrar)`, run in the manager after its catalog was restored and
            before it accepts traffic; registers its servers. May be a closure (it is
            cloudpickled for process managers). `None`: no servers. It runs on the main
            thread of a process manager, and on the supervisor's own thread for a thread
            manager. Either way the supervisor waits for it: supervision of the other
            children (crash handling, restarts) pauses until it returns, so keep it short
            (a process manager is bounded by `start_timeout`, a thread manager is not).
        isolation: `"thread"` (the registrar runs in the supervisor's process) or
            `"process"` (in its own OS process, so killing it kills nothing else).
        restart: `"permanent"` (always restarted), `"transient"` (restarted only after an
            abnormal exit) or `"temporary"` (never restarted).
        config: the registrar's configuration; its `name` must equal `name`. Default:
            `RegistrarConfig(name)`, with the supervisor's `state_dir` a backup at
            `<state_dir>/<name>.db` with `save_on_modify=True`.
        shutdown: seconds a clean stop may take before the manager is killed. A process
            manager is SIGKILLed. A thread cannot be killed: its registrar actor is told
            to crash, which takes effect once it finishes the callback it is stuck in; a
            restart that comes before that fails with `DuplicateNameError` (the old
            registrar still holds the name) and counts as another crash, so the
            supervisor gives up if the actor stays stuck.
        heartbeat: seconds between heartbeat pings to a process manager (`None`: off). A
            ping is answered through the registrar actor's mailbox, so a frozen process
            and a stuck registrar both count as hung. Thread managers have no heartbeat.
        heartbeat_timeout: seconds without an answer to a ping after which a process
            manager counts as hung: it is killed and handled like a crash. Default:
            three heartbeat periods (0.75 s with the default `heartbeat`). On Linux only
            the time it could have run counts: time its threads waited for a CPU (an
            overloaded machine) does not, up to ten times this bound; on any platform,
            time its registrar was seen working through its mailbox (a busy manager: a
            `ManagerOverloaded` event) does not either; a stopped or blocked manager is
            hung at the bound (docs: "What counts as a hang"). A
            manager whose answers say that it has been unable to accept connections for
            that long (out of file descriptors, say) is killed the same way, as unhealthy.
        start_timeout: seconds a manager may take to restore, set up and serve.

    Raises:
        ConfigError: a field is invalid; the message names it.
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
        """Seconds without a heartbeat answer after which it counts as hung (`None`: off):
        seconds it could have run, on Linux (see `heartbeat_timeout`)."""
        if self.heartbeat is None:
            return None
        if self.heartbeat_timeout is not None:
            return self.heartbeat_timeout
        return 3.0 * self.heartbeat


@dataclasses.dataclass(frozen=True)
class SupervisorSpec:
    """A nested supervisor as a child of another (its arguments are `Supervisor`'s).

    When it gives up, its parent sees a child that exited with OTP's `shutdown` (a
    normal exit): a `permanent` one is restarted by the parent's own strategy and
    intensity (escalation, as in OTP); a `transient` or `temporary` one stays down.

    Attributes:
        name: the child's name in its parent (unique in the tree).
        children: its children, started in this order.
        strategy, max_restarts, period, backoff: as for `Supervisor`.
        restart: its restart type in the parent.
        state_dir: where its managers keep their catalogs (default: the parent's).

    Raises:
        ConfigError: a field is invalid; the message names it.
    """

    name: str
    children: tuple[ManagerSpec | SupervisorSpec, ...]
    strategy: Strategy = "one_for_one"
    max_restarts: int = 3
    period: float = 5.0
    backoff: Backoff = Backoff()
    restart: RestartType = "permanent"
    state_dir: str | os.PathLike[str] | None = None

    def __post_init__(self) -> None:
        check_name("name", self.name, "a supervisor name")
        object.__setattr__(self, "children", tuple(self.children))
        check_choice("strategy", self.strategy, ("one_for_one", "one_for_all", "rest_for_one"))
        check_choice("restart", self.restart, ("permanent", "transient", "temporary"))
        if (
            isinstance(self.max_restarts, bool)
            or not isinstance(self.max_restarts, int)
            or (self.max_restarts < 0)
        ):
            raise ConfigError(f"max_restarts must be an int >= 0, got {self.max_restarts!r}")
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

    def has_processes(self) -> bool:
        """Whether any manager in this subtree runs in its own process."""
        return any(isinstance(c, ManagerSpec) and c.isolation == "process" for c, _ in walk(self))


def walk(
    spec: SupervisorSpec, path: tuple[SupervisorSpec, ...] = ()
) -> Iterator[tuple[ManagerSpec | SupervisorSpec, tuple[SupervisorSpec, ...]]]:
    """Every child below `spec`, depth first, each with the supervisors above it.

    The one walk over a spec tree: names, managers and state directories are read
    through it.

    Yields:
        `(child, path)`: `path` runs from `spec` down to the child's own supervisor.
    """
    path = (*path, spec)
    for child in spec.children:
        yield child, path
        if isinstance(child, SupervisorSpec):
            yield from walk(child, path)


def tree_names(spec: SupervisorSpec) -> list[str]:
    """The names of every child below `spec`, depth first (duplicates kept)."""
    return [child.name for child, _ in walk(spec)]


def managers(spec: SupervisorSpec) -> list[ManagerSpec]:
    """Every manager below `spec`, depth first."""
    return [child for child, _ in walk(spec) if isinstance(child, ManagerSpec)]
