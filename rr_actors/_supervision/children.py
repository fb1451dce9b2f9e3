"""A supervisor's children: the per-child record, its snapshots, its restart type's
meaning, and the running adapters.

Every running child offers `pid` and `stop(timeout) -> ManagerExit`: a `ThreadManager`
(a registrar in this process), a `ProcessManager` (`_process/manager.py`; a pool's
process too: `policy.PoolSetup`) or a `NestedSupervisor`; each tells its end through
`on_exit(ManagerExit)`, run on its watcher thread. What happens when a child exits on its
own, OTP's restart types and strategies, is decided in one place (`decide`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import TYPE_CHECKING, Literal, Protocol

from rr_actors._core import runtime
from rr_actors._process.manager import ManagerExit, ManagerProcess, stopped_cleanly
from rr_actors._registrar import Served, start_registrar
from rr_actors._registrar.messages import PeersStopped
from rr_actors.config import (
    Isolation,
    ManagerSpec,
    RegistrarConfig,
    RestartType,
    Strategy,
    SupervisorSpec,
    managers,
    tree_names,
)
from rr_actors.errors import RrError, SupervisorGaveUpError

if TYPE_CHECKING:
    from rr_actors._process.spare import SparePool
    from rr_actors._supervision.watching import EventRelay
    from rr_actors._transport.messenger import Address, Transport

logger = logging.getLogger("rr_actors")

ChildState = Literal["starting", "running", "restarting", "stopping", "stopped", "exited"]
"""Where a child is in its life (`ChildInfo.state`)."""


@dataclasses.dataclass(frozen=True)
class ChildInfo:
    """An immutable snapshot of one child (OTP's `which_children`, with more to see).

    Attributes:
        name: the child's name.
        kind: `"manager"` or `"supervisor"`.
        isolation: `"thread"` or `"process"` for a manager; for a supervisor
            `"process"` when it is a pool (in an OS process of its own), else `None`.
        restart: its restart type.
        state: `"starting"`, `"running"`, `"restarting"` (down, restart pending),
            `"stopping"`, `"stopped"` (by the supervisor) or `"exited"` (down on its own
            and not restarted; a transient one comes back with its group, as in OTP).
        pid: the process id of a running process manager, a running pool, or (for a
            child of a running pool) its pool's; else `None`.
        restarts: how many times it was restarted so far (with its nested supervisor
            too).
        last_exit: why its last incarnation ended (`None` before the first exit).
    """

    name: str
    kind: Literal["manager", "supervisor"]
    isolation: Isolation | None
    restart: RestartType
    state: ChildState
    pid: int | None
    restarts: int
    last_exit: str | None


@dataclasses.dataclass(frozen=True)
class ChildCounts:
    """OTP's `count_children`: how many children of which kind.

    Attributes:
        specs: every child, running or not.
        active: children running now.
        supervisors: children that are supervisors.
        managers: children that are managers (OTP's workers).
    """

    specs: int
    active: int
    supervisors: int
    managers: int


def snapshot(
    spec: ManagerSpec | SupervisorSpec,
    state: ChildState,
    pid: int | None,
    restarts: int,
    last_exit: str | None,
) -> ChildInfo:
    return ChildInfo(
        name=spec.name,
        kind="supervisor" if isinstance(spec, SupervisorSpec) else "manager",
        isolation=spec.isolation if isinstance(spec, ManagerSpec) else _pooled(spec),
        restart=spec.restart,
        state=state,
        pid=pid,
        restarts=restarts,
        last_exit=last_exit,
    )


def _pooled(spec: SupervisorSpec) -> Isolation | None:
    return "process" if spec.isolation == "process" else None


# -- what happens when a child exits on its own: OTP's restart types and strategies -------

Group = Callable[[str, Sequence[str], str], Iterable[str]]
"""`group(strategy, names, crashed)`: a classroom's copy of `affected` (`Steps.group`)."""


@dataclasses.dataclass(frozen=True)
class Decision:
    """What a supervisor does when a child exits on its own (`decide`).

    Attributes:
        group: the children its exit takes down and restarts, itself included, in start
            order; empty: it stays down and nothing else is touched.
        back: the names of `group` that come back (the others are stopped for good).
    """

    group: tuple[str, ...]
    back: frozenset[str]


def decide(
    strategy: Strategy,
    children: Sequence[tuple[str, RestartType]] | Mapping[str, RestartType],
    crashed: str,
    *,
    normal: bool,
    group: Group | None = None,
) -> Decision:
    """What happens when child `crashed` exits on its own (`normal`: a normal exit), in a
    supervisor of `strategy` whose `children` are `(name, restart type)` (or a mapping of
    them) in start order: OTP's `supervisor.erl` clauses, one screen.

    | `crashed`'s restart type | its exit | decision |
    |---|---|---|
    | `permanent` | any | its group goes down and comes back |
    | `transient` | abnormal | its group goes down and comes back |
    | `transient` | normal | it stays down, nothing else is touched |
    | `temporary` | any | it stays down, nothing else is touched |

    Its group is the strategy's (`affected`, or a classroom's copy `group`): `one_for_one`
    itself, `one_for_all` every child, `rest_for_one` itself and those started after it.
    Of the group every sibling comes back but a `temporary` one, stopped for good (a
    `transient` one that had exited normally too). The restart intensity is counted
    after this (`policy.Restarts`): past it, the supervisor gives up instead.
    """
    restart = children if isinstance(children, Mapping) else dict(children)
    if not restarts_after(restart[crashed], normal=normal):
        return Decision((), frozenset())
    if strategy == "one_for_one" and group is None:  # (its siblings are not read)
        return Decision((crashed,), frozenset((crashed,)))
    names = tuple(restart)
    taken = (
        affected(strategy, names, crashed)
        if group is None
        else tuple(group(strategy, names, crashed))
    )
    down = tuple(name for name in names if name in taken)
    back = frozenset(n for n in down if n == crashed or restart[n] != "temporary")
    return Decision(down, back)


def restarts_after(restart: RestartType, *, normal: bool) -> bool:
    """Whether a child that exited on its own is restarted (`decide`'s table: `permanent`
    always, `transient` after an abnormal exit, `temporary` never)."""
    return restart == "permanent" or (restart == "transient" and not normal)


def affected(strategy: Strategy, names: Sequence[str], crashed: str) -> tuple[str, ...]:
    """The children a crash of `crashed` takes down with it (OTP's strategies), in start
    order (`names`), itself included."""
    if strategy == "one_for_one":
        return (crashed,)
    if strategy == "one_for_all":
        return tuple(names)
    return tuple(names[names.index(crashed) :])


# -- running children --------------------------------------------------------------------


class Running(Protocol):
    """What a supervisor holds of a running child."""

    pid: int | None

    def stop(self, timeout: float | None, *, restarting: bool = False) -> ManagerExit:
        """Stop it (within `timeout` seconds, `None`: its spec's `shutdown`); how it ended
        (`restarting`: to be started again, its callers get `RegistrarUnavailableError`)."""
        ...


class ThreadManager:
    """A manager whose registrar runs in this process (its `setup` runs on this thread)."""

    pid: int | None = None

    def __init__(
        self,
        spec: ManagerSpec,
        config: RegistrarConfig,
        attached: Transport | None,
        on_exit: Callable[[ManagerExit], None],
        relay: EventRelay | None = None,
    ) -> None:
        self.spec = spec
        self.stopping = False
        upstream = relay.publisher if relay is not None else None
        registrar = start_registrar(config, setup=spec.setup, upstream=upstream, announced=True)
        try:
            if attached is not None:
                attached.serve(Served(registrar))
        except BaseException:
            with contextlib.suppress(RrError):
                registrar.stop(timeout=spec.shutdown)
            raise
        self.registrar = registrar

        def watch() -> None:
            registrar.wait_ended()
            if self.stopping:
                return
            if stopped_cleanly(spec.name):  # code in the manager called registrar.stop()
                on_exit(ManagerExit("normal", normal=True))
            else:
                on_exit(ManagerExit("crashed (registrar actor died)", normal=False))

        runtime.Thread(target=watch, name=f"rr-watch-{spec.name}", daemon=True).start()

    def tell_stopped(self, names: tuple[str, ...], _lost: tuple[str, ...] = ()) -> None:
        """Registrars `names` stopped for good (before its own stop, the tree's; lost: told)."""
        with contextlib.suppress(RrError):  # (it ended meanwhile: its stop says so)
            self.registrar.tell(PeersStopped(names))

    def stop(self, timeout: float | None, *, restarting: bool = False) -> ManagerExit:
        """Stop the registrar cleanly; tell its actor to crash if that takes too long."""
        timeout = self.spec.shutdown if timeout is None else timeout
        self.stopping = True
        registrar = self.registrar
        if not registrar.is_alive():
            return ManagerExit("crashed (registrar actor died)", normal=False)
        try:
            registrar.stop(timeout=timeout)
        except RrError as exc:
            logger.error(  # noqa: TRY400 - the timeout is the news, not its traceback
                "manager %s did not stop within %g s: %s", self.spec.name, timeout, exc
            )
            with contextlib.suppress(Exception):
                registrar._actor.crash()
            registrar.wait_ended(timeout)
            return ManagerExit(f"killed: no clean stop within {timeout:g} s", normal=False)
        return ManagerExit("shutdown", normal=True)


class ProcessManager:
    """A manager in its own OS process (see `rr_actors._process.manager`)."""

    def __init__(self, handle: ManagerProcess, shutdown: float) -> None:
        self.handle = handle
        self.handle_shutdown = shutdown
        self.pid: int | None = handle.pid

    @classmethod
    def start(
        cls,
        spec: ManagerSpec,
        setup: bytes,
        config: RegistrarConfig,
        address: Address | None,
        on_exit: Callable[[ManagerExit], None],
        spares: SparePool | None,
        relay: EventRelay | None = None,
        supervisor: str = "",
        on_announce: Callable[[str, bool], None] | None = None,
        hold: Callable[[ManagerProcess], None] | None = None,
    ) -> ProcessManager:
        """Start the manager (in a spare if there is one) and wait until it serves
        (`on_announce`: a pool's; `hold`: its pings wait, `ManagerProcess.start`).

        Raises:
            CatalogCorruptError: its backup cannot be read (with its `path`).
            RegistrarUnavailableError: it failed to start or died while starting.
            CallTimeoutError: it was not ready within its `start_timeout`.
        """
        forwarding = relay.forwarding if relay is not None else False
        handle = ManagerProcess.start(
            spec.name,
            setup,
            config,
            address,
            start_timeout=spec.start_timeout,
            heartbeat=spec.heartbeat,
            heartbeat_timeout=spec.hang_after,
            on_exit=on_exit,
            spare=spares.take() if spares is not None else None,
            forward_events=forwarding,
            on_events=relay.deliver if relay is not None else None,
            on_overloaded=None
            if relay is None
            else functools.partial(relay.overloaded, supervisor, spec.name),
            announced=True,
            on_announce=on_announce,
            hold=hold,
        )
        if relay is not None:
            relay.attach(handle, forwarding=forwarding)
        return cls(handle, spec.shutdown)

    def tell_stopped(self, names: tuple[str, ...], lost: tuple[str, ...] = ()) -> None:
        """Registrars `names` stopped for good, `lost` died (before its own stop, the tree's)."""
        self.handle.tell_stopped(names, lost)

    def stop(
        self, timeout: float | None, *, restarting: bool = False, wait_exit: bool = True
    ) -> ManagerExit:
        limit = self.handle_shutdown if timeout is None else timeout
        return self.handle.stop(limit, restarting=restarting, wait_exit=wait_exit)


class Level(Protocol):
    """One supervisor of the tree, as its parent and lookups see it (a `policy.Node`)."""

    spec: SupervisorSpec
    children: list[Child]
    by_name: dict[str, Child]  # its children by name (a lookup walks no list)
    nested: list[Child]  # its children that are supervisors, in start order
    has_pipes: bool  # whether a process manager or a pool is below it (control pipes)

    @property
    def gave_up(self) -> SupervisorGaveUpError | None: ...

    @property
    def giving_up(self) -> bool: ...

    def stop(
        self, timeout: float | None = None, *, restarting: bool = False, parallel: bool = False
    ) -> None: ...


class NestedSupervisor:
    """A supervisor running as the child of another."""

    pid: int | None = None

    def __init__(self, node: Level) -> None:
        self.node = node

    def stop(
        self, timeout: float | None, *, restarting: bool = False, parallel: bool = False
    ) -> ManagerExit:
        self.node.stop(timeout=timeout, restarting=restarting, parallel=parallel)
        return ManagerExit("shutdown", normal=True)


# -- a pool: a nested supervisor in an OS process of its own ------------------------------

POOL_HEARTBEAT = 1.0  # seconds: a pool's one registrar shares its interpreter with its managers


def is_pool(spec: ManagerSpec | SupervisorSpec) -> bool:
    return isinstance(spec, SupervisorSpec) and spec.isolation == "process"


def pool_manager(spec: SupervisorSpec) -> ManagerSpec:
    """How its parent starts and watches pool `spec`'s process: as a process manager named
    after it (its managers' `shutdown`s summed, plus 5 s; their `start_timeout`s summed)."""
    members = managers(spec)
    return ManagerSpec(
        spec.name,
        isolation="process",
        restart=spec.restart,
        shutdown=sum(m.shutdown for m in members) + 5.0,
        heartbeat=POOL_HEARTBEAT,
        start_timeout=sum(m.start_timeout for m in members) or 30.0,
    )


# -- the record of one child ---------------------------------------------------------------


_SHOWN = frozenset({"state", "running", "last_exit"})  # what a child's snapshot shows


@dataclasses.dataclass(eq=False)
class Child:
    """What a supervisor knows of one child (mutated on the supervisor's thread only;
    `published`: the snapshot waiters read, replaced under the tree's lock).

    A change of what its snapshot shows calls `on_change(child)` (its supervisor notes
    it, and publishes only the children that changed: a publish costs what changed, not
    the number of children).
    """

    spec: ManagerSpec | SupervisorSpec
    state: ChildState = "stopped"
    running: Running | None = None
    incarnation: int = 0  # bumped at each start and stop: older exit events are stale
    last_exit: str | None = None
    gave_up: SupervisorGaveUpError | None = None  # why it is down for good (a give-up)
    published: ChildInfo = dataclasses.field(init=False)
    subtree: frozenset[str] = dataclasses.field(init=False)  # names below a supervisor
    on_change: Callable[[Child], None] | None = dataclasses.field(default=None, repr=False)

    def __setattr__(self, name: str, value: object) -> None:
        object.__setattr__(self, name, value)
        if name in _SHOWN:
            on_change = self.__dict__.get("on_change")
            if on_change is not None:
                on_change(self)

    def __post_init__(self) -> None:
        self.published = self.info(0)
        spec = self.spec
        self.subtree = frozenset(tree_names(spec) if isinstance(spec, SupervisorSpec) else ())

    @property
    def name(self) -> str:
        return self.spec.name

    def info(self, restarts: int) -> ChildInfo:
        """A snapshot of the child now, with `restarts` (kept by the tree)."""
        pid = self.running.pid if self.running is not None else None
        return snapshot(self.spec, self.state, pid, restarts, self.last_exit)
