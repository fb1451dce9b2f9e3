"""Supervision trees of managers, after Erlang/OTP's `supervisor` (design principles, sup_princ).

A [`Supervisor`][rr_actors.Supervisor] starts its children (managers, or nested
supervisors) in order, watches them and restarts them by policy:

* strategies `one_for_one`, `one_for_all`, `rest_for_one` (which siblings restart with a
  crashed child);
* restart types `permanent` (always restarted), `transient` (restarted after an abnormal
  exit), `temporary` (never restarted);
* restart intensity: more than `max_restarts` restarts within `period` seconds and the
  supervisor gives up: it stops every child and reports `SupervisorGaveUpError` (to its
  parent supervisor, which treats it as a crashed child, or to its owner);
* what OTP lacks: exponential [`Backoff`][rr_actors.Backoff] with jitter before a restart.

The supervisor is a thread with a mailbox: one event at a time, never polling. A manager
process's death is seen by a watcher thread blocked on the process sentinel; a thread
manager's death by a watcher blocked on its registrar actor's stop event. Time (the
intensity window and the backoff timers) goes through an injectable `clock` and `timer`.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import itertools
import logging
import os
import queue
import random as _random
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Literal, Protocol

import cloudpickle

from rr_actors._core.directory import DIRECTORY
from rr_actors._core.timers import Cancellable, Timer, thread_timer
from rr_actors._process.manager import ManagerExit, stopped_cleanly
from rr_actors._registrar import ResourceRegistrar, Served
from rr_actors._registrar.messages import Abandon, ConsumerDown, Crash
from rr_actors._types import Query, StatusCallback
from rr_actors.config import (
    Backoff,
    Isolation,
    ManagerSpec,
    RegistrarConfig,
    RestartType,
    Strategy,
    SupervisorSpec,
    check_seconds,
    tree_names,
)
from rr_actors.errors import (
    CallTimeoutError,
    ConfigError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    RrError,
    SupervisorGaveUpError,
    UnknownServerError,
)

if TYPE_CHECKING:
    from rr_actors._process.manager import ManagerProcess, Spare

__all__ = [
    "Backoff",
    "ChildCounts",
    "ChildInfo",
    "ManagerSpec",
    "RestartIntensity",
    "Supervisor",
    "SupervisorSpec",
]

logger = logging.getLogger("rr_actors")

ChildState = Literal["starting", "running", "restarting", "stopping", "stopped", "exited"]
Clock = Callable[[], float]


# -- introspection -----------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ChildInfo:
    """An immutable snapshot of one child (OTP's `which_children`, with more to see).

    Attributes:
        name: the child's name.
        kind: `"manager"` or `"supervisor"`.
        isolation: `"thread"` or `"process"` for a manager, `None` for a supervisor.
        restart: its restart type.
        state: `"starting"`, `"running"`, `"restarting"` (down, restart pending),
            `"stopping"`, `"stopped"` (by the supervisor) or `"exited"` (down for good:
            temporary, or transient after a normal exit).
        pid: the process id of a running process manager, else `None`.
        restarts: how many times it was restarted so far, counting the times it came
            back with its nested supervisor when the parent restarted that one.
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


class RestartIntensity:
    """OTP's restart intensity: at most `max_restarts` restarts within `period` seconds.

    Pure logic over an injectable clock (no threads).
    """

    def __init__(self, max_restarts: int, period: float, clock: Clock = time.monotonic) -> None:
        self.max_restarts = max_restarts
        self.period = period
        self.clock = clock
        self._times: collections.deque[float] = collections.deque()

    def add(self) -> bool:
        """Count one restart now; return `False` if that exceeds the intensity (give up)."""
        now = self.clock()
        self._times.append(now)
        while self._times and now - self._times[0] >= self.period:
            self._times.popleft()
        return len(self._times) <= self.max_restarts

    @property
    def recent(self) -> int:
        """Restarts counted within the current window (this one included, after `add`)."""
        return len(self._times)


# -- running children --------------------------------------------------------------------


class _Running(Protocol):
    pid: int | None

    def stop(self, timeout: float | None) -> ManagerExit: ...


class _ThreadManager:
    """A manager whose registrar runs in this process."""

    pid: int | None = None

    def __init__(
        self,
        spec: ManagerSpec,
        config: RegistrarConfig,
        attached: Any,
        on_exit: Callable[[ManagerExit], None],
    ) -> None:
        self.spec = spec
        self.stopping = False
        # setup runs before the registrar serves: loads arriving meanwhile wait for it
        registrar = ResourceRegistrar.start(config, setup=spec.setup)
        try:
            if attached is not None:
                attached.serve(Served(registrar))
        except BaseException:
            with contextlib.suppress(RrError):
                registrar.stop(timeout=spec.shutdown)
            raise
        self.registrar = registrar
        ref = registrar._ref

        def watch() -> None:
            ref.actor_stopped.wait()
            if self.stopping:
                return
            if stopped_cleanly(spec.name):  # code in the manager called registrar.stop()
                on_exit(ManagerExit("normal", normal=True))
            else:
                on_exit(ManagerExit("crashed (registrar actor died)", normal=False))

        threading.Thread(target=watch, name=f"rr-watch-{spec.name}", daemon=True).start()

    def stop(self, timeout: float | None) -> ManagerExit:
        timeout = self.spec.shutdown if timeout is None else timeout
        self.stopping = True
        ref = self.registrar._ref
        if not ref.is_alive():
            return ManagerExit("crashed (registrar actor died)", normal=False)
        try:
            self.registrar.stop(timeout=timeout)
        except RrError as exc:
            logger.error(  # noqa: TRY400 - the timeout is the news, not its traceback
                "manager %s did not stop within %g s: %s", self.spec.name, timeout, exc
            )
            with contextlib.suppress(Exception):
                ref.tell(Crash())
            ref.actor_stopped.wait(timeout)
            return ManagerExit(f"killed: no clean stop within {timeout:g} s", normal=False)
        return ManagerExit("shutdown", normal=True)


class _ProcessManager:
    """A manager in its own OS process (see `rr_actors._process.manager`)."""

    def __init__(self, handle: ManagerProcess, shutdown: float) -> None:
        self.handle = handle
        self.handle_shutdown = shutdown
        self.pid: int | None = handle.pid

    def stop(self, timeout: float | None) -> ManagerExit:
        return self.handle.stop(self.handle_shutdown if timeout is None else timeout)


class _NestedSupervisor:
    """A supervisor running as the child of another."""

    pid: int | None = None

    def __init__(self, supervisor: Supervisor) -> None:
        self.supervisor = supervisor

    def stop(self, timeout: float | None) -> ManagerExit:
        self.supervisor.stop(timeout=timeout)
        return ManagerExit("shutdown", normal=True)


@dataclasses.dataclass
class _Child:
    spec: ManagerSpec | SupervisorSpec
    state: ChildState = "stopped"
    running: _Running | None = None
    incarnation: int = 0
    last_exit: str | None = None
    gave_up: SupervisorGaveUpError | None = None  # why it is down for good (a give-up)

    @property
    def name(self) -> str:
        return self.spec.name

    def info(self, restarts: int) -> ChildInfo:
        spec = self.spec
        return ChildInfo(
            name=spec.name,
            kind="supervisor" if isinstance(spec, SupervisorSpec) else "manager",
            isolation=spec.isolation if isinstance(spec, ManagerSpec) else None,
            restart=spec.restart,
            state=self.state,
            pid=self.running.pid if self.running is not None else None,
            restarts=restarts,
            last_exit=self.last_exit,
        )


# -- mailbox events ----------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Exited:
    name: str
    incarnation: int
    exit: ManagerExit


@dataclasses.dataclass(frozen=True)
class _Restart:
    names: tuple[str, ...]
    generation: int


@dataclasses.dataclass(frozen=True)
class _Do:
    fn: Callable[[], Any]
    done: queue.SimpleQueue[tuple[bool, Any]]


@dataclasses.dataclass(frozen=True)
class _Quit:
    pass


_SUPERVISOR_NAMES = itertools.count(1)
_MIN_STOP = 1e-3  # seconds a child still gets to stop when an overall stop bound ran out


def _tree_specs(spec: SupervisorSpec) -> dict[str, ManagerSpec | SupervisorSpec]:
    specs: dict[str, ManagerSpec | SupervisorSpec] = {}
    for child in spec.children:
        specs[child.name] = child
        if isinstance(child, SupervisorSpec):
            specs.update(_tree_specs(child))
    return specs


class _Tree:
    """What every supervisor of one tree shares (made by the root, kept across incarnations).

    Nested supervisors are replaced when their parent restarts them; what must outlive an
    incarnation lives here, keyed by child name (names are unique in a tree).
    """

    def __init__(self, spec: SupervisorSpec) -> None:
        self.cond = threading.Condition()  # published snapshots of the whole tree; waiters
        self.specs = _tree_specs(spec)
        self.latest: dict[str, ChildInfo] = {}  # the last published snapshot of every child
        self.restarts: dict[str, int] = {}  # starts after the first, across incarnations
        self.started: set[str] = set()
        self.setups: dict[str, bytes] = {}  # process managers' cloudpickled setups
        self.abandon_lock = threading.Lock()
        self.abandon_later: dict[str, list[tuple[str, str]]] = {}  # name -> (query id, origin)
        self.wait_cursor: dict[str, int] = {}

    def spec_info(self, name: str, state: ChildState) -> ChildInfo:
        """The snapshot of a child whose supervisor is down: `state`, no pid."""
        spec = self.specs[name]
        last = self.latest.get(name)
        return ChildInfo(
            name=name,
            kind="supervisor" if isinstance(spec, SupervisorSpec) else "manager",
            isolation=spec.isolation if isinstance(spec, ManagerSpec) else None,
            restart=spec.restart,
            state=state,
            pid=None,
            restarts=self.restarts.get(name, 0),
            last_exit=last.last_exit if last is not None else None,
        )


@dataclasses.dataclass(frozen=True)
class _Found:
    """A child found anywhere in the tree, and a give-up on its path that is final."""

    info: ChildInfo
    gave_up: SupervisorGaveUpError | None


class Supervisor:
    """Starts managers in order, restarts them by policy, stops them in reverse order.

    Follows Erlang/OTP's supervisor (strategies, restart types, restart intensity with
    escalation), plus exponential backoff with jitter. Use it as a context manager, or call
    [`start`][rr_actors.Supervisor.start] and [`stop`][rr_actors.Supervisor.stop].

    ```python
    sup = rr.Supervisor([rr.ManagerSpec("erm", setup=erm_setup, isolation="process"),
                         rr.ManagerSpec("cm", setup=cm_setup)],
                        strategy="one_for_one", max_restarts=3, period=5.0, state_dir="state")
    with sup:
        app = sup.registrar("action")
        app.call("cm", "filtered_camera", {...})
    ```

    Args:
        children: `ManagerSpec` and `SupervisorSpec` values, started in this order.
        strategy: `"one_for_one"` (restart the crashed child), `"one_for_all"` (restart
            every child) or `"rest_for_one"` (restart it and the children started after it).
        max_restarts: at most this many restarts within `period` seconds; one more and the
            supervisor gives up.
        period: the intensity window, in seconds.
        backoff: delay before restarts (default: none).
        state_dir: directory for the managers' catalogs (`<state_dir>/<name>.db`,
            `save_on_modify=True`) unless a spec gives its own `config`.
        name: this supervisor's name (for logs and thread names).
        clock: monotonic clock in seconds for the intensity window (injectable for tests).
        timer: `timer(delay, fn)` that runs `fn` after `delay` seconds (injectable for tests);
            a zero delay restarts without a timer.
        random: float in `[0, 1)` for the backoff jitter (injectable for tests).

    Raises:
        ConfigError: an argument is invalid; the message names it.
    """

    def __init__(
        self,
        children: Sequence[ManagerSpec | SupervisorSpec],
        *,
        strategy: Strategy = "one_for_one",
        max_restarts: int = 3,
        period: float = 5.0,
        backoff: Backoff | None = None,
        state_dir: str | os.PathLike[str] | None = None,
        name: str | None = None,
        clock: Clock = time.monotonic,
        timer: Timer = thread_timer,
        random: Callable[[], float] = _random.random,
    ) -> None:
        self._spec = SupervisorSpec(
            name=name or f"supervisor-{next(_SUPERVISOR_NAMES)}",
            children=tuple(children),
            strategy=strategy,
            max_restarts=max_restarts,
            period=period,
            backoff=backoff if backoff is not None else Backoff(),
            state_dir=state_dir,
        )
        self._clock = clock
        self._timer = timer
        self._random = random
        self._tree = _Tree(self._spec)
        self._parent: Supervisor | None = None
        self._on_gave_up: Callable[[SupervisorGaveUpError], None] | None = None
        self._system: Any = None
        self._attached: Any = None
        self._owns_system = False
        self._children = [_Child(spec) for spec in self._spec.children]
        self._intensity = RestartIntensity(max_restarts, period, clock)
        self._mailbox: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._infos: tuple[ChildInfo, ...] = self._snapshots()
        self._subtrees = {
            c.name: frozenset(tree_names(c))
            for c in self._spec.children
            if isinstance(c, SupervisorSpec)
        }
        self._gave_up: SupervisorGaveUpError | None = None
        self._stopped = False
        self._generation = 0
        self._timers: list[Cancellable] = []
        self._registrars: list[ResourceRegistrar] = []
        self._spare: Spare | None = None  # root only: an idle manager process, ready to use
        self._spare_lock = threading.Lock()
        self._spares = False  # root only: keep a spare (the tree has process managers)

    @classmethod
    def _nested(cls, spec: SupervisorSpec, parent: Supervisor) -> Supervisor:
        sup = cls(
            spec.children,
            strategy=spec.strategy,
            max_restarts=spec.max_restarts,
            period=spec.period,
            backoff=spec.backoff,
            state_dir=spec.state_dir if spec.state_dir is not None else parent._spec.state_dir,
            name=spec.name,
            clock=parent._clock,
            timer=parent._timer,
            random=parent._random,
        )
        sup._parent = parent
        sup._system, sup._attached = parent._system, parent._attached
        sup._tree = parent._tree
        for child in sup._children:  # a new incarnation: say how the last one ended
            last = sup._tree.latest.get(child.name)
            child.last_exit = last.last_exit if last is not None else None
        sup._infos = sup._snapshots()
        return sup

    # -- properties -------------------------------------------------------------------

    @property
    def name(self) -> str:
        """This supervisor's name."""
        return self._spec.name

    @property
    def gave_up(self) -> SupervisorGaveUpError | None:
        """The error it gave up with (restart intensity exceeded), or `None`."""
        return self._gave_up

    @property
    def system(self) -> Any:
        """The transport system its process managers are attached to (`None` without any)."""
        return self._system

    # -- life cycle -------------------------------------------------------------------

    def start(self) -> Supervisor:
        """Start every child in order; return once all are running (serving).

        Raises:
            SupervisorGaveUpError: a child failed to start (its setup raised, its backup
                could not be read, ...); the children already started were stopped again,
                in reverse order. The cause is chained.
            ConfigError: a process manager's `setup` cannot be pickled.
        """
        if self._thread is not None:
            raise ConfigError(f"supervisor {self.name!r} was already started")
        if self._spec.state_dir is not None:
            os.makedirs(self._spec.state_dir, exist_ok=True)
        if self._parent is None:
            self._prepare_root()
        self._thread = threading.Thread(
            target=self._loop, name=f"rr-supervisor-{self.name}", daemon=True
        )
        self._thread.start()
        try:
            self._do(self._start_all)
        except BaseException:
            self._mailbox.put(_Quit())
            self._thread.join(30.0)
            if self._parent is None:
                with self._spare_lock:
                    self._spares = False
                self._release_spare()
                self._close_system()
            raise
        return self

    def stop(self, *, timeout: float | None = None) -> None:
        """Stop the registrars from `registrar()`, then every child in reverse start order.

        Each child gets its spec's `shutdown` seconds to stop cleanly before it is killed
        (see `ManagerSpec.shutdown` for what that means for a thread manager). Stopping a
        stopped supervisor is a no-op.

        Args:
            timeout: an overall bound in seconds: a child still running when it ran out
                gets no more than what is left of it (at least 1 ms) before it is killed,
                even if its `shutdown` is longer. `None`: every child gets its full
                `shutdown`. The bound starts once the supervisor's thread takes up the
                stop (it first finishes a child start that is under way).

        Raises:
            ConfigError: `timeout` is not a positive number of seconds.
        """
        if timeout is not None:
            check_seconds("timeout", timeout)
        deadline = None if timeout is None else time.monotonic() + timeout
        if self._thread is None or self._stopped:
            return
        for registrar in reversed(self._registrars):
            with contextlib.suppress(RrError):
                registrar.stop(timeout=_left(deadline))
        self._registrars.clear()
        with self._spare_lock:
            self._spares = False  # no new spare while the children stop
        if self._thread.is_alive():
            with contextlib.suppress(RrError):
                self._do(lambda: self._stop_all(deadline))
            self._mailbox.put(_Quit())
            self._thread.join(60.0)
        self._stopped = True
        if self._parent is None:
            self._release_spare()
            self._close_system()

    def __enter__(self) -> Supervisor:
        return self.start()

    def __exit__(self, exc_type: object, *_: object) -> None:
        self.stop()
        if exc_type is None and self._gave_up is not None:
            raise self._gave_up

    def _prepare_root(self) -> None:
        self._pickle_setups(self._spec)
        if self._spec.has_processes():
            from rr_actors._transport import System  # noqa: PLC0415

            self._system = System.create()  # also attaches this process
            self._owns_system = True
            self._attached = self._system
            self._spares = True

    def _pickle_setups(self, spec: SupervisorSpec) -> None:
        for child in spec.children:
            if isinstance(child, SupervisorSpec):
                self._pickle_setups(child)
            elif child.isolation == "process":
                try:
                    self._tree.setups[child.name] = cloudpickle.dumps(child.setup)
                except Exception as exc:
                    raise ConfigError(
                        f"setup of manager {child.name!r} is not picklable: {exc}"
                    ) from exc

    # -- the spare manager process (root supervisor only) ----------------------------------

    def _take_spare(self) -> Spare | None:
        """Hand out the idle spare process, if there is one (any supervisor's thread)."""
        with self._spare_lock:
            spare, self._spare = self._spare, None
        return spare

    def _replenish_spare(self) -> None:
        """Start a new spare if none is waiting (mailbox thread, after a start is published).

        A restart then only hands the manager's arguments to a process that already runs:
        the process start (forkserver fork and child bootstrap) is off the restart path.
        """
        with self._spare_lock:
            if not self._spares or self._spare is not None:
                return
        from rr_actors._process.manager import Spare  # noqa: PLC0415

        try:
            spare = Spare.start()
        except Exception:
            logger.exception("supervisor %s could not start a spare manager process", self.name)
            return
        with self._spare_lock:
            if self._spares and self._spare is None:
                self._spare, spare = spare, None  # type: ignore[assignment]
        if spare is not None:  # stopped meanwhile
            spare.close()

    def _release_spare(self) -> None:
        spare = self._take_spare()
        if spare is not None:
            spare.close()

    def _close_system(self) -> None:
        if self._attached is not None:
            with contextlib.suppress(Exception):
                self._attached.close()
        if self._owns_system and self._system is not None:
            with contextlib.suppress(Exception):
                self._system.close()
        self._attached = None

    # -- introspection ----------------------------------------------------------------

    def which_children(self) -> tuple[ChildInfo, ...]:
        """Immutable snapshots of the children, in start order (OTP's `which_children`)."""
        with self._tree.cond:
            return self._infos

    def count_children(self) -> ChildCounts:
        """How many children of which kind, and how many run now (OTP's `count_children`)."""
        infos = self.which_children()
        return ChildCounts(
            specs=len(infos),
            active=sum(1 for i in infos if i.state == "running"),
            supervisors=sum(1 for i in infos if i.kind == "supervisor"),
            managers=sum(1 for i in infos if i.kind == "manager"),
        )

    def child(self, name: str) -> ChildInfo:
        """The snapshot of the child `name`, searched through nested supervisors too.

        A child of a nested supervisor that is down (being restarted by its parent, say)
        has that supervisor's state (`"restarting"`, ...) and no pid.

        Raises:
            UnknownServerError: no child of that name in this tree.
        """
        found = self._root()._lookup(name)
        if found is None:
            raise UnknownServerError(f"supervisor {self.name!r} has no child named {name!r}")
        return found.info

    def _lookup(self, name: str) -> _Found | None:
        """Find `name` below this supervisor by the specs, whether its supervisor runs or not."""
        with self._tree.cond:
            return self._locate(name, None)

    def _locate(self, name: str, down: ChildState | None) -> _Found | None:
        """`_lookup` (tree lock held); `down`: the state of a supervisor above that is down."""
        tree = self._tree
        for child, info in zip(self._children, self._infos, strict=True):
            if child.name == name:
                if down is not None:
                    return _Found(tree.spec_info(name, down), None)
                return _Found(info, child.gave_up if info.state in ("exited", "stopped") else None)
            if name not in self._subtrees.get(child.name, ()):
                continue
            state = down if down is not None else info.state
            running = child.running
            if state == "running" and isinstance(running, _NestedSupervisor):
                nested = running.supervisor
                if nested._gave_up is None:
                    return nested._locate(name, None)
                if child.spec.restart == "temporary":  # no one restarts it: final
                    found = nested._locate(name, None)
                    return None if found is None else _Found(found.info, nested._gave_up)
                state = "restarting"  # its parent will restart it (or give up itself)
            elif state == "running":
                state = "starting"
            final = child.gave_up if state in ("exited", "stopped") else None
            return _Found(tree.spec_info(name, state), final)
        return None

    def _child_object(self, name: str) -> _Child | None:
        """The live `_Child` record of `name` (in a running nested supervisor), if any."""
        for child in list(self._children):
            if child.name == name:
                return child
            running = child.running
            if isinstance(running, _NestedSupervisor):
                found = running.supervisor._child_object(name)
                if found is not None:
                    return found
        return None

    def wait_restarted(
        self, name: str, *, timeout: float, restarts: int | None = None
    ) -> ChildInfo:
        """Wait until child `name` (anywhere in the tree) was restarted and is running again.

        A child of a nested supervisor counts as restarted also when its supervisor was
        restarted by its parent (escalation): restart counts are kept per name across
        incarnations of the nested supervisor.

        Args:
            name: the child's name.
            timeout: seconds to wait at most.
            restarts: wait until it was restarted at least this many times in total.
                Default: one more restart than the previous `wait_restarted` for this
                child returned (1 the first time), so "kill, wait, kill, wait" works even
                when a restart completes before the wait starts.

        Returns:
            The child's snapshot, running.

        Raises:
            CallTimeoutError: not restarted within `timeout` seconds.
            SupervisorGaveUpError: the tree gave up on it: its supervisor gave up and no
                supervisor above will restart that one (the top one gave up, or a nested
                one whose restart type is `temporary`).
            RegistrarUnavailableError: it exited for good (temporary, or transient after a
                normal exit) or its supervisor was stopped.
            UnknownServerError: no child of that name.
        """
        root = self._root()
        tree = self._tree
        target = restarts if restarts is not None else tree.wait_cursor.get(name, 0) + 1
        outcome: list[ChildInfo | RrError] = []

        def settled() -> bool:  # runs with the tree lock held, at every publish
            found = root._locate(name, None)
            if found is None:
                outcome.append(
                    UnknownServerError(f"supervisor {root.name!r} has no child named {name!r}")
                )
                return True
            info = found.info
            error = root._gave_up or found.gave_up
            if info.state == "running" and info.restarts >= target:
                outcome.append(info)
            elif error is not None:
                outcome.append(error)
            elif info.state in ("exited", "stopped") and info.restarts < target:
                outcome.append(
                    RegistrarUnavailableError(
                        f"child {name!r} is {info.state} ({info.last_exit}) and will not be "
                        "restarted"
                    )
                )
            return bool(outcome)

        with tree.cond:
            if not tree.cond.wait_for(settled, timeout):
                found = root._locate(name, None)
                state = (
                    f" (state {found.info.state}, {found.info.restarts} restarts)" if found else ""
                )
                raise CallTimeoutError(
                    f"child {name!r} was not restarted within {timeout:g} s{state}"
                )
        result = outcome[-1]
        if isinstance(result, RrError):
            raise result
        tree.wait_cursor[name] = result.restarts
        return result

    # -- registrars, calls, manager access ----------------------------------------------

    def registrar(self, config: RegistrarConfig | str) -> ResourceRegistrar:
        """Start a consumer registrar in this process, on this supervisor's system.

        Process managers can reach it (status notifications, nested calls). It is not
        supervised; the supervisor stops it first when it stops.

        Args:
            config: a `RegistrarConfig` or a name.

        Raises:
            DuplicateNameError: a registrar of that name runs in this process.
            ConfigError: the configuration is invalid or the supervisor is not running.
        """
        if self._thread is None or self._stopped:
            raise ConfigError(f"supervisor {self.name!r} is not running")
        registrar = ResourceRegistrar.start(config)
        if self._attached is not None:
            try:
                self._attached.serve(Served(registrar))
            except BaseException:
                registrar.stop()
                raise
        self._registrars.append(registrar)
        return registrar

    def run_in(
        self, name: str, fn: Callable[[ResourceRegistrar], Any], *, timeout: float = 10.0
    ) -> Any:
        """Run `fn(registrar)` against manager `name`'s registrar, where it lives.

        For a process manager `fn` is cloudpickled and runs on a fresh thread of that
        process, over the system's transport (`AttachedSystem.run`); its result must
        pickle. For a thread manager it runs on the calling thread.

        Args:
            name: the manager's name (anywhere in the tree).
            fn: called with the manager's `ResourceRegistrar`.
            timeout: seconds to wait for the result of a process manager.

        Returns:
            What `fn` returned.

        Raises:
            UnknownServerError: no manager of that name in the tree.
            RegistrarUnavailableError: it is not running, or died before answering.
            RegistrarStoppedError: its registrar was stopped before answering (by `fn`,
                for example).
            CallTimeoutError: no answer within `timeout` seconds.
            ConfigError: `fn` cannot be pickled (process manager).
            RrError: the result cannot be pickled (process manager).
            Exception: whatever `fn` raised.
        """
        spec = self._tree.specs.get(name)
        if not isinstance(spec, ManagerSpec):
            what = "a supervisor, not a manager" if spec is not None else "not in the tree"
            raise UnknownServerError(f"supervisor {self.name!r}: {name!r} is {what}")
        child = self._root()._child_object(name)
        running = child.running if child is not None else None
        if isinstance(running, _ThreadManager):
            return fn(running.registrar)
        if isinstance(running, _ProcessManager) and self._system is not None:
            return self._system.run(name, fn, timeout=timeout)
        raise RegistrarUnavailableError(f"manager {name!r} is not running")

    def call_with_retry(
        self,
        consumer: ResourceRegistrar,
        target_rr: str,
        server: str,
        request: Any,
        *,
        on_status: StatusCallback | None = None,
        timeout: float | None = None,
        query_id: str | None = None,
    ) -> Query:
        """`consumer.call(...)`, waiting out a restart of `target_rr` and retrying.

        Every attempt uses the same caller-generated query id, so the provider's restored
        catalog recognises a retry of a call it already answered before it died: the
        resource is never loaded twice and no second consumer id is created. If the wait
        for the restart runs out, the id is abandoned at the provider (at once if it runs
        again by then, else when it comes back), so nothing leaks. A restart of the
        provider's nested supervisor by its parent (escalation) is waited out too.

        Args:
            consumer: the calling registrar.
            target_rr: provider registrar name, as for `ResourceRegistrar.call`.
            server: server name on it.
            request: the request value.
            on_status: client status callback, as for `ResourceRegistrar.call`.
            timeout: seconds for the whole call, restarts and retries included
                (default: the consumer's `call_timeout`).
            query_id: the id to use (default: a fresh UUID4).

        Returns:
            The `Query`, with the provider's response.

        Raises:
            RegistrarUnavailableError: the provider died and will not be restarted.
            SupervisorGaveUpError: the tree gave up on the provider while the call waited.
            CallTimeoutError: no answer (restart included) within `timeout` seconds.
            ResourceLoadError: as for `ResourceRegistrar.call`.
            DependencyCycleError: as for `ResourceRegistrar.call`.
            UnknownServerError: as for `ResourceRegistrar.call`.
            RegistrarStoppedError: as for `ResourceRegistrar.call` (not when the
                supervisor stopped the provider to restart it).
        """
        limit = timeout if timeout is not None else consumer.config.call_timeout
        qid = query_id or str(uuid.uuid4())
        deadline = time.monotonic() + limit
        root = self._root()
        while True:
            found = root._lookup(target_rr)
            before = found.info.restarts if found is not None else 0
            left = deadline - time.monotonic()
            if left <= 0:
                self._abandon_after_restart(target_rr, qid, consumer.name)
                raise CallTimeoutError(
                    f"call to '{target_rr}/{server}' timed out after {limit:g} s"
                )
            try:
                return consumer.call(
                    target_rr, server, request, on_status=on_status, timeout=left, query_id=qid
                )
            except RegistrarUnavailableError:
                if found is None or found.info.restart == "temporary":
                    raise
            except RegistrarStoppedError:
                now = root._lookup(target_rr)  # stopped by its supervisor for a restart?
                if now is None or now.info.state not in ("stopping", "restarting", "starting"):
                    raise
            try:
                self.wait_restarted(
                    target_rr, timeout=max(deadline - time.monotonic(), 1e-3), restarts=before + 1
                )
            except CallTimeoutError:
                self._abandon_after_restart(target_rr, qid, consumer.name)
                raise CallTimeoutError(
                    f"call to '{target_rr}/{server}' timed out after {limit:g} s while "
                    f"{target_rr!r} was restarting"
                ) from None

    def _abandon_after_restart(self, name: str, query_id: str, origin: str) -> None:
        """Abandon `query_id` at provider `name`: now if it runs, else when it is back.

        Under the tree's abandon lock, which `_start_child` takes after marking a child
        running: an id is either sent here or handed to the next start, never left behind.
        """
        tree = self._tree
        with tree.abandon_lock:
            child = self._root()._child_object(name)
            if child is None or child.state != "running" or child.running is None:
                tree.abandon_later.setdefault(name, []).append((query_id, origin))
                return
        with contextlib.suppress(RrError):
            DIRECTORY.lookup(name).tell(Abandon(query_id, origin))

    # -- the mailbox ------------------------------------------------------------------

    def _loop(self) -> None:
        while True:
            event = self._mailbox.get()
            if isinstance(event, _Quit):
                return
            try:
                if isinstance(event, _Exited):
                    self._on_exited(event)
                elif isinstance(event, _Restart):
                    self._on_restart(event)
                elif isinstance(event, _Do):
                    try:
                        event.done.put((True, event.fn()))
                    except BaseException as exc:  # noqa: BLE001 - handed to the caller
                        event.done.put((False, exc))
            except Exception:
                logger.exception("supervisor %s failed handling %r", self.name, event)
            self._publish()

    def _do(self, fn: Callable[[], Any]) -> Any:
        done: queue.SimpleQueue[tuple[bool, Any]] = queue.SimpleQueue()
        self._mailbox.put(_Do(fn, done))
        ok, value = done.get()
        if not ok:
            raise value
        return value

    def _do_async(self, fn: Callable[[], Any]) -> None:
        self._mailbox.put(_Do(fn, queue.SimpleQueue()))

    def _snapshots(self) -> tuple[ChildInfo, ...]:
        restarts = self._tree.restarts
        return tuple(c.info(restarts.get(c.name, 0)) for c in self._children)

    def _publish(self) -> None:
        """Publish the children's snapshots and wake every waiter of the tree."""
        tree = self._tree
        with tree.cond:
            self._infos = self._snapshots()
            for info in self._infos:
                tree.latest[info.name] = info
            tree.cond.notify_all()

    def _post_exit(self, name: str, incarnation: int) -> Callable[[ManagerExit], None]:
        def post(result: ManagerExit) -> None:
            self._mailbox.put(_Exited(name, incarnation, result))

        return post

    # -- starting and stopping children (mailbox thread) ------------------------------

    def _config(self, spec: ManagerSpec) -> RegistrarConfig:
        if spec.config is not None:
            return spec.config
        state_dir = self._spec.state_dir
        if state_dir is None:
            return RegistrarConfig(name=spec.name)
        return RegistrarConfig(
            name=spec.name,
            backup_path=os.path.join(os.fspath(state_dir), f"{spec.name}.db"),
            save_on_modify=True,
        )

    def _start_child(self, child: _Child) -> None:
        """Start one incarnation of `child`; raise what its start raised."""
        child.incarnation += 1
        child.state = "starting"
        self._publish()
        spec = child.spec
        post = self._post_exit(child.name, child.incarnation)
        if isinstance(spec, SupervisorSpec):
            nested = Supervisor._nested(spec, self)
            incarnation = child.incarnation

            def escalate(error: SupervisorGaveUpError) -> None:
                self._mailbox.put(
                    _Exited(spec.name, incarnation, ManagerExit(f"gave up: {error}", normal=False))
                )

            nested._on_gave_up = escalate
            nested.start()
            child.running = _NestedSupervisor(nested)
            child.gave_up = None
        else:
            if spec.restart != "temporary":
                DIRECTORY.restart_expected.add(spec.name)  # death watch waits for us
            if spec.isolation == "thread":
                child.running = _ThreadManager(spec, self._config(spec), self._attached, post)
            else:
                from rr_actors._process.manager import ManagerProcess  # noqa: PLC0415

                root = self._root()
                try:
                    handle = ManagerProcess.start(
                        spec.name,
                        self._tree.setups[spec.name],
                        self._config(spec),
                        self._system.address if self._system is not None else None,
                        start_timeout=spec.start_timeout,
                        heartbeat=spec.heartbeat,
                        heartbeat_timeout=spec.hang_after,
                        on_exit=post,
                        spare=root._take_spare(),
                    )
                finally:  # runs after this start was published: off the restart path
                    root._do_async(root._replenish_spare)
                child.running = _ProcessManager(handle, spec.shutdown)
        child.state = "running"
        tree = self._tree
        if child.name in tree.started:  # a restart: by this supervisor, or of its parent
            tree.restarts[child.name] = tree.restarts.get(child.name, 0) + 1
        tree.started.add(child.name)
        with tree.abandon_lock:  # see _abandon_after_restart
            abandoned = tree.abandon_later.pop(child.name, [])
        for query_id, origin in abandoned:
            with contextlib.suppress(RrError):
                DIRECTORY.lookup(child.name).tell(Abandon(query_id, origin))

    def _start_all(self) -> None:
        started: list[_Child] = []
        for child in self._children:
            try:
                self._start_child(child)
            except BaseException as exc:
                child.state = "stopped"
                child.last_exit = f"failed to start: {exc}"
                self._forget(child, dead=False)  # no restart is coming: no death-watch hold
                for done in reversed(started):
                    self._stop_child(done, final=True)
                raise SupervisorGaveUpError(
                    f"supervisor {self.name!r}: child {child.name!r} failed to start: {exc}"
                ) from exc
            started.append(child)
            self._publish()

    def _stop_child(self, child: _Child, *, final: bool, deadline: float | None = None) -> None:
        """Stop a running child (its spec's shutdown, bounded by `deadline`, then a kill)."""
        running = child.running
        if running is None:
            if final:
                dead = child.state == "restarting"  # it crashed and will not come back now
                if child.state != "exited":
                    child.state = "stopped"
                self._forget(child, dead=dead)
            return
        child.state = "stopping"
        child.incarnation += 1  # its watcher's exit event is now stale
        self._publish()
        limit: float | None = _left(deadline)
        if isinstance(child.spec, ManagerSpec):
            limit = child.spec.shutdown if limit is None else min(limit, child.spec.shutdown)
        result = running.stop(limit)
        child.running = None
        child.state = "stopped"
        child.last_exit = result.reason
        if final:
            self._forget(child, dead=not result.normal)

    def _forget(self, child: _Child, *, dead: bool) -> None:
        """The child will not come back: release what it held (death watch) if it died."""
        if isinstance(child.spec, ManagerSpec):
            DIRECTORY.restart_expected.discard(child.name)
            if dead:
                self._root()._consumer_down(child.name)

    def _cancel_restarts(self) -> None:
        """Make every scheduled restart stale (new generation) and cancel its timer."""
        self._generation += 1
        for timer in self._timers:
            timer.cancel()
        self._timers.clear()

    def _stop_all(self, deadline: float | None = None) -> None:
        self._cancel_restarts()
        for child in reversed(self._children):
            self._stop_child(child, final=True, deadline=deadline)

    def _root(self) -> Supervisor:
        sup = self
        while sup._parent is not None:
            sup = sup._parent
        return sup

    def _living_registrars(self) -> list[str]:
        names: list[str] = []
        for child in list(self._children):
            running = child.running
            if isinstance(running, _NestedSupervisor):
                names.extend(running.supervisor._living_registrars())
            elif isinstance(running, _ProcessManager):
                names.append(child.name)
        return names

    def _consumer_down(self, name: str) -> None:
        """Death watch: tell every living registrar that consumer `name` is gone for good."""
        local = {peer.name for peer in DIRECTORY.local_peers()}
        for target in sorted(local | set(self._living_registrars())):
            if target == name:
                continue
            try:
                DIRECTORY.lookup(target).tell(ConsumerDown(name))
            except RrError:
                logger.debug("death watch: %s unreachable", target)

    # -- crashes and restarts (mailbox thread) ----------------------------------------

    def _on_exited(self, event: _Exited) -> None:
        child = next((c for c in self._children if c.name == event.name), None)
        if child is None or child.incarnation != event.incarnation or self._gave_up:
            return  # a stale event: that incarnation was stopped on purpose
        if isinstance(child.running, _NestedSupervisor):
            nested = child.running.supervisor
            child.gave_up = nested.gave_up
            nested.stop()  # it gave up: end its mailbox thread
        child.running = None
        child.last_exit = event.exit.reason
        restart = child.spec.restart
        logger.warning(
            "supervisor %s: child %s exited: %s", self.name, child.name, event.exit.reason
        )
        if restart == "temporary" or (restart == "transient" and event.exit.normal):
            child.state = "exited"
            self._forget(child, dead=not event.exit.normal)
            return
        child.state = "restarting"
        self._publish()
        if not self._intensity.add():
            self._give_up(child)
            return
        names = self._affected(child)
        for other in reversed([c for c in self._children if c.name in names]):
            if other is not child and other.running is not None:
                self._stop_child(other, final=other.spec.restart == "temporary")
                if other.spec.restart == "temporary":
                    other.state = "exited"
                else:
                    other.state = "restarting"
        names = tuple(
            n
            for n in names
            if n == child.name
            or next(c for c in self._children if c.name == n).spec.restart != "temporary"
        )
        self._schedule(names)

    def _affected(self, child: _Child) -> tuple[str, ...]:
        strategy = self._spec.strategy
        if strategy == "one_for_one":
            return (child.name,)
        if strategy == "one_for_all":
            return tuple(c.name for c in self._children if c.state != "exited" or c is child)
        index = self._children.index(child)
        return tuple(c.name for c in self._children[index:] if c.state != "exited" or c is child)

    def _schedule(self, names: tuple[str, ...]) -> None:
        delay = self._spec.backoff.delay(self._intensity.recent, self._random)
        generation = self._generation
        event = _Restart(names, generation)
        if delay <= 0:
            self._mailbox.put(event)
            return
        logger.info("supervisor %s: restarting %s in %.3f s", self.name, ", ".join(names), delay)
        self._timers.append(self._timer(delay, lambda: self._mailbox.put(event)))

    def _on_restart(self, event: _Restart) -> None:
        if event.generation != self._generation or self._gave_up is not None:
            return
        for child in self._children:
            if child.name not in event.names or child.state != "restarting":
                continue
            try:
                self._start_child(child)
            except Exception as exc:
                logger.exception("supervisor %s: restart of %s failed", self.name, child.name)
                child.running = None
                self._mailbox.put(
                    _Exited(
                        child.name,
                        child.incarnation,
                        ManagerExit(f"failed to start: {exc}", normal=False),
                    )
                )
                return
            self._publish()

    def _give_up(self, crashed: _Child) -> None:
        error = SupervisorGaveUpError(
            f"supervisor {self.name!r} gave up: more than {self._spec.max_restarts} restart(s) "
            f"within {self._spec.period:g} s (last: {crashed.name!r} {crashed.last_exit})"
        )
        logger.error("%s", error)
        self._cancel_restarts()
        for child in self._children:  # the snapshots published while they stop say why
            child.gave_up = child.gave_up or error
        for child in reversed(self._children):
            if child is crashed or child.running is None:
                dead = child.state != "exited"
                child.state = "stopped"
                self._forget(child, dead=dead)
            else:
                self._stop_child(child, final=True)
        self._gave_up = error  # after the children stopped: waiters then see a settled tree
        self._publish()
        if self._on_gave_up is not None:
            self._on_gave_up(error)


def _left(deadline: float | None) -> float | None:
    """Seconds left until `deadline` (at least `_MIN_STOP`), or `None` without one."""
    if deadline is None:
        return None
    return max(deadline - time.monotonic(), _MIN_STOP)
