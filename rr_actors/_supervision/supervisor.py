"""Supervision trees of managers, after Erlang/OTP's `supervisor` (design principles, sup_princ).

A [`Supervisor`][rr_actors.Supervisor] starts its children (managers, or nested
supervisors) in order and restarts them by strategy (`one_for_one`, `one_for_all`,
`rest_for_one`), restart type (`permanent`, `transient`, `temporary`) and restart
intensity (more than `max_restarts` within `period` seconds: it gives up, and its parent
sees a child that exited with OTP's `shutdown`); plus what OTP lacks, an exponential
[`Backoff`][rr_actors.Backoff] with jitter. Who does what:

```
 Supervisor (this module: the public handle; owns the transport, spares, state-dir lock)
   ├─ TreeWatch (watching.py: subscribe, flush_events, observe, graph)
   └─ Node (policy.py, after OTP's supervisor.erl: one supervisor's record + mailbox, on
        │    its own thread, and its restart policy: children started in start order,
        │    stopped in reverse order (the death watch); a watcher's Exited: restart or
        │    not (restart type), which siblings (strategy), intensity, backoff, give up)
        ├─ children.py: Child records, restart types; ThreadManager / ProcessManager /
        │    NestedSupervisor
        └─ tree.py: what the tree shares; lookups and the restart wait; death watch
   retry.py: call_with_retry's steps (run here, awaited by aio.py)
   aio.py: the awaitable twins (AsyncSupervision, this class's base)
```

The supervisor is a thread with a mailbox: one event at a time, never polling (a watcher
thread blocks on each child's end). Time goes through an injectable `clock` and `timer`.
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import os
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from rr_actors import _moved, events
from rr_actors._core import runtime
from rr_actors._core.bus import DEFAULT_MAXSIZE, Subscription
from rr_actors._core.exit import SUPERVISORS, stop_at_exit
from rr_actors._core.replies import Steps, run_steps
from rr_actors._platform import forkserver
from rr_actors._registrar import Registrar, ResourceRegistrar, Served, start_registrar
from rr_actors._registrar.handle import blocking
from rr_actors._supervision import retry
from rr_actors._supervision.aio import AsyncSupervision
from rr_actors._supervision.children import (
    ChildCounts,
    ChildInfo,
    ProcessManager,
    ThreadManager,
)
from rr_actors._supervision.policy import Node, RestartIntensity, left, registrar_names
from rr_actors._supervision.tree import (
    Clock,
    Ending,
    RestartWait,
    StateDirLock,
    Tree,
    announce_started,
    find_child,
    locate,
    lost_everything,
    pool_of,
    quiet,
    ran_before,
)
from rr_actors._supervision.watching import TreeWatch
from rr_actors._types import Query, StatusCallback
from rr_actors.config import (
    Backoff,
    Durability,
    ManagerSpec,
    RegistrarConfig,
    Strategy,
    SupervisorSpec,
    check_choice,
    check_seconds,
    walk,
)
from rr_actors.config import Steps as ProtocolSteps
from rr_actors.errors import (
    ConfigError,
    RegistrarUnavailableError,
    RrError,
    SupervisorGaveUpError,
    UnknownServerError,
    _known_names,
)

if TYPE_CHECKING:
    import socket

    from rr_actors._supervision.watching import Page
    from rr_actors._transport.messenger import Transport

__all__ = [
    "Backoff",
    "ChildCounts",
    "ChildInfo",
    "ManagerSpec",
    "RestartIntensity",
    "Supervisor",
    "SupervisorSpec",
]

_SUPERVISOR_NAMES = itertools.count(1)

SPARE_PROCESSES = 2
"""Idle manager processes a tree with process managers keeps ready (see `SparePool`)."""

SPARE_DELAY = 0.1
"""Seconds from a process manager's (re)start to the start of the spare replacing the one
it used."""


class Supervisor(AsyncSupervision):
    """Starts managers in order, restarts them by policy, stops them in reverse order.

    Erlang/OTP's supervisor (strategies, restart types, restart intensity with
    escalation), plus exponential backoff with jitter. A context manager, or call
    [`start`][rr_actors.Supervisor.start] and [`stop`][rr_actors.Supervisor.stop]; from an
    event loop, `async with sup:` and the awaitable twins (`astart`, `astop`, ...).

    Args:
        children: `ManagerSpec` and `SupervisorSpec` values, started in this order (one
            spec alone: a tree of that one child).
        strategy: `"one_for_one"` (restart the crashed child), `"one_for_all"` (restart
            every child) or `"rest_for_one"` (restart it and the children started after it).
        max_restarts: at most this many restarts within `period` seconds; one more and the
            supervisor gives up.
        period: the intensity window, in seconds.
        backoff: delay before restarts (default: none).
        state_dir: directory for the managers' catalogs (`<state_dir>/<name>.db`,
            `save_on_modify=True`) unless a spec gives its own `config`. `start` locks it
            (`<state_dir>/.lock`, the holder's pid) until `stop` or the process's death.
            It remembers the registrars started without a backup
            (`<state_dir>/.consumers/`), whose next start releases what their last run held.
        durability: what every backup of the tree, nested supervisors' too, survives
            (rule 14): `"process"` a kill of its process, `"power"` also an OS crash or
            power loss. The least each manager gets: a spec's own `config` with
            `"process"` (the field's default) is raised to a `"power"` tree's.
        name: this supervisor's name (for logs and thread names).
        clock: monotonic clock in seconds for the intensity window (`None`:
            `time.monotonic`).
        timer: `timer(delay, fn)` that runs `fn` after `delay` seconds; a zero delay
            restarts without a timer.
        random: float in `[0, 1)` for the backoff jitter (`None`: `random.random`).
        network: the carrier (`Transport`: an AF_UNIX `System`, a `ZenohNetwork`) the
            tree's managers and `registrar()`s are served on; its owner closes it after
            `stop`. Default: a private AF_UNIX system, made at `start` when the tree has
            process managers, closed at `stop`.
        steps: the protocol steps the tree's supervisors, and the managers and
            `registrar()`s they start whose config names none, run instead of their own
            (`rr_actors.config.Steps`; default: none replaced).

    Raises:
        ConfigError: an argument is invalid; the message names it.
    """

    def __init__(
        self,
        children: Sequence[ManagerSpec | SupervisorSpec] | ManagerSpec | SupervisorSpec,
        *,
        strategy: Strategy = "one_for_one",
        max_restarts: int = 3,
        period: float = 5.0,
        backoff: Backoff | None = None,
        state_dir: str | os.PathLike[str] | None = None,
        durability: Durability = "process",
        name: str | None = None,
        clock: Clock | None = None,
        timer: runtime.StartTimer = runtime.thread_timer,
        random: Callable[[], float] | None = None,
        network: Transport | None = None,
        steps: ProtocolSteps | None = None,
    ) -> None:
        _check_network(network)
        if steps is not None and not isinstance(steps, ProtocolSteps):
            raise ConfigError(f"steps must be an rr_actors.config.Steps, got {steps!r}")
        check_choice("durability", durability, ("process", "power"))
        if isinstance(children, ManagerSpec | SupervisorSpec):
            children = [children]  # one child: a list of one (it is not iterable)
        elif not isinstance(children, Sequence | tuple | list) or isinstance(children, str):
            raise ConfigError(
                "children must be a list of ManagerSpec and SupervisorSpec values "
                f"(or one of them), got {children!r}"
            )
        self._spec = SupervisorSpec(
            name=name or f"supervisor-{next(_SUPERVISOR_NAMES)}",
            children=tuple(children),
            strategy=strategy,
            max_restarts=max_restarts,
            period=period,
            backoff=backoff if backoff is not None else Backoff(),
            state_dir=state_dir,
        )
        self._tree = Tree(
            self._spec,
            clock=runtime.monotonic if clock is None else clock,
            timer=timer,
            random=random,
            network=network,
            durability=durability,
            steps=steps,
        )
        self._node = Node(self._spec, self._tree)
        self._lock: StateDirLock | None = None
        self._registrars: list[ResourceRegistrar] = []
        self._started = False
        self._stopped = False
        self._watch = TreeWatch(
            self,
            self._tree,
            running=lambda: self._started and not self._stopped,
            registrars=lambda: list(self._registrars),
        )

    # -- properties -------------------------------------------------------------------

    @property
    def gave_up(self) -> SupervisorGaveUpError | None:
        """The error it gave up with (restart intensity exceeded), or `None`."""
        return self._node.gave_up

    @property
    def system(self) -> Transport | None:
        """The carrier its managers are served on while it runs (`None`: none)."""
        return self._tree.processes.system

    @property
    def name(self) -> str:
        """This supervisor's name."""
        return self._spec.name

    # -- life cycle -------------------------------------------------------------------

    def start(self) -> Supervisor:
        """Start every child in order; return once all are running (serving).

        Raises:
            SupervisorGaveUpError: a child failed to start; those started were stopped
                again, in reverse order. The cause is chained (a backup that cannot be
                read: `CatalogCorruptError` with its `path`, see `quarantine_backup`).
            ConfigError: a process manager's `setup` cannot be pickled; the supervisor is
                running or was stopped (it starts once: make a new one, its managers'
                catalogs are restored); a `state_dir` of the tree is locked by another
                supervisor (the message names its pid); or this process was forked from
                one whose state a child cannot use (a Zenoh session).
        """
        forkserver.check_usable(f"supervisor {self.name!r}")
        if self._stopped:
            raise ConfigError(
                f"supervisor {self.name!r} was stopped, and a supervisor cannot be restarted: "
                "make a new one (rr.Supervisor(...)) with the same specs"
            )
        if self._started:
            raise ConfigError(f"supervisor {self.name!r} is already started (it is running)")
        self._started = True
        try:
            self._lock = StateDirLock.acquire(_state_dirs(self._spec))
            self._tree.processes.open(SPARE_PROCESSES, SPARE_DELAY)
            self._tree.processes.start_ahead(True)
            try:
                self._node.start()
            finally:
                self._tree.processes.start_ahead(False)
        except BaseException:
            self._stopped = True
            self._release()
            raise
        stop_at_exit(
            SUPERVISORS,
            f"supervisor {self.name!r}",
            lambda: not self._stopped,
            lambda timeout: self.stop(timeout=timeout),
            provides=registrar_names(self._spec),
        )
        return self

    def stop(self, *, timeout: float | None = None, parallel: bool = False) -> None:
        """Stop the registrars from `registrar()`, then every child in reverse start order.

        Each child gets its spec's `shutdown` seconds to stop cleanly before it is killed
        (`ManagerSpec.shutdown`). A process manager's stop is done once its registrar
        reports stopped (its catalog saved, what it held released): the next child's
        stop begins then, while its process exits; every exit is awaited before `stop()`
        returns, and a process not gone within its `shutdown` (counted from its stop's
        start) is killed, as OTP's `brutal_kill` after the shutdown. Idempotent.

        Args:
            timeout: an overall bound in seconds (`None`: every child gets its full
                `shutdown`): a child still running when it ran out gets what is left (at
                least 1 ms), then is killed. It starts once the supervisor's thread takes
                up the stop (after a child start under way).
            parallel: stop the children at once where no dependency orders them, in
                every supervisor of the tree, instead of one after the other (OTP's
                order). A dependency is live: a manager whose registrar holds a query at
                another manager's depends on it, and it stops (its stop has ended)
                before that provider's stop begins; a manager that cannot be asked is
                taken to depend on every child started before it, and a cycle is
                broken in reverse start order. Each stop runs on a worker thread of the
                supervisor's (at most 16 at once).

        Raises:
            ConfigError: `timeout` is not a positive number of seconds, or it was called
                on one of the tree's supervisors' threads (a thread manager's `setup`),
                where it would wait for itself: nothing was stopped.
        """
        if timeout is not None:
            check_seconds("timeout", timeout)
        if self._started and not self._stopped and self._tree.on_a_supervisors_thread():
            raise ConfigError(
                f"supervisor {self.name!r}: stop() was called on one of its own threads (a "
                "thread manager's setup runs there), where it would wait for itself; nothing "
                "was stopped: call stop() from another thread"
            )
        deadline = None if timeout is None else runtime.monotonic() + timeout
        if not self._started:
            self._watch.close_observers()  # opened on a supervisor that never started
        if not self._started or self._stopped:
            return
        for registrar in reversed(self._registrars):
            with contextlib.suppress(RrError):
                registrar.stop(timeout=left(deadline))
        self._registrars.clear()
        self._tree.processes.close_spares()  # no new spare while the children stop
        self._watch.last_look()  # a page kept after the stop shows the catalogs as they end
        self._tree.ending = self._tree.ending or Ending.of(self._node, self._tree.processes.system)
        quiet(self._node)  # (each manager hears the stops before its own, unpinged)
        self._node.stop(deadline=deadline, parallel=parallel)
        self._stopped = True
        self._release()

    def __enter__(self) -> Supervisor:
        return self.start()

    def __exit__(self, exc_type: object, *_: object) -> None:
        self.stop()
        if exc_type is None and self._node.gave_up is not None:
            raise self._node.gave_up

    def _release(self) -> None:
        self._tree.processes.close()
        if self._lock is not None:
            self._lock.release()
        self._watch.close_observers()  # last: their pages saw the tree stop

    # -- introspection ----------------------------------------------------------------

    def which_children(self) -> tuple[ChildInfo, ...]:
        """Immutable snapshots of the children, in start order (OTP's `which_children`)."""
        with self._tree.cond:
            return tuple(child.published for child in self._node.children)

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

        A child of a nested supervisor that is down has that supervisor's state and no
        pid; after `stop` every child is `"stopped"`, with no pid.

        Raises:
            UnknownServerError: no child of that name in this tree.
            ConfigError: `name` is not a str, or the supervisor is not started yet.
        """
        info = self.snapshot(name)  # an unknown name first: it is wrong started or not
        if not self._started:
            raise ConfigError(
                f"supervisor {self.name!r} is not started: its child {name!r} is not "
                "running yet (start it first: `with sup:` or sup.start())"
            )
        return info

    def snapshot(self, name: str) -> ChildInfo:
        """`child(name)` at any time, before `start` too (every child `"stopped"` then).

        Raises:
            UnknownServerError: no child of that name in this tree.
            ConfigError: `name` is not a str.
        """
        _check_child_name(name)
        with self._tree.cond:
            found = locate(self._node, self._tree, name)
        if found is None:
            raise UnknownServerError(
                f"supervisor {self.name!r} has no child named {name!r}"
                + _known_names(name, self._tree.specs)
            )
        return found.info

    def wait_restarted(
        self, name: str, *, timeout: float, restarts: int | None = None
    ) -> ChildInfo:
        """Wait until child `name` (anywhere in the tree) was restarted and is running again.

        A child of a nested supervisor counts as restarted also when its supervisor was
        (escalation): restart counts are kept per name.

        Args:
            name: the child's name.
            timeout: seconds to wait at most.
            restarts: wait until it was restarted at least this many times in total.
                Default: one more than the previous `wait_restarted` for this child
                returned (1 the first time), so "kill, wait, kill, wait" works.

        Returns:
            The child's snapshot, running.

        Raises:
            CallTimeoutError: not restarted within `timeout` seconds.
            SupervisorGaveUpError: its supervisor gave up and none above restarts that
                one; raised once the one that gave up stopped all its children.
            RegistrarUnavailableError: it exited for good (temporary, or transient after a
                normal exit under `one_for_one`) or its supervisor was stopped.
            UnknownServerError: no child of that name.
            ConfigError: `name` is not a str, `timeout` not a positive number of seconds,
                or `restarts` neither an int nor `None`.
        """
        return run_steps(self._restart_wait(name, timeout, restarts))

    def _restart_wait(self, name: str, timeout: float, restarts: int | None) -> Steps[ChildInfo]:
        """`wait_restarted`'s steps, its arguments checked (also awaited: `aio`, `retry`)."""
        _check_child_name(name)
        check_seconds("timeout", timeout)
        if restarts is not None and (isinstance(restarts, bool) or not isinstance(restarts, int)):
            raise ConfigError(
                f"restarts must be an int (a restart count) or None, got {restarts!r}"
            )
        return RestartWait(self._tree, self._node, self.name, name, restarts).steps(timeout)

    # -- registrars, calls, manager access ----------------------------------------------

    def registrar(self, config: RegistrarConfig | str) -> ResourceRegistrar:
        """Start a consumer registrar in this process, served on this supervisor's carrier.

        Not supervised; the supervisor stops it first when it stops. Its events go to
        the supervisor's subscribers too. With a `state_dir` and no backup of its own,
        its name is remembered there: started again on that `state_dir`, it reconciles
        with every registrar, which releases the ids its last run held (rule 20).

        Args:
            config: a `RegistrarConfig` (its `durability` raised to the tree's) or a name.

        Raises:
            DuplicateNameError: a registrar of that name runs in this process.
            ConfigError: the configuration is invalid, the supervisor is not running, or
                the name cannot be remembered in the `state_dir` (the message names the
                file).
        """
        if not self._started:
            raise ConfigError(
                f"supervisor {self.name!r} is not running yet: start it first (`with sup:` "
                "or `sup.start()`), then call `registrar()`"
            )
        if self._stopped:
            raise ConfigError(
                f"supervisor {self.name!r} was stopped: call `registrar()` while it runs "
                "(inside `with sup:`, or between `sup.start()` and `sup.stop()`)"
            )
        if isinstance(config, str):
            config = RegistrarConfig(name=config)
        if isinstance(config, RegistrarConfig):  # (with the tree's durability and steps)
            config = self._tree.durable(config)
        backup = config.backup_path if isinstance(config, RegistrarConfig) else None
        restored = backup is not None and os.path.exists(backup)
        registrar = start_registrar(config, upstream=self._tree.events.publisher, announced=True)
        system = self._tree.processes.system
        try:
            if system is not None:
                system.serve(Served(registrar))
            self._reconcile_last_run(registrar, restored=restored)
        except BaseException:
            registrar.stop()
            raise
        self._registrars.append(registrar)
        return registrar

    def _reconcile_last_run(self, registrar: ResourceRegistrar, *, restored: bool) -> None:
        """If one of its name ran on this `state_dir` before, it lost everything (rule 20);
        `restored` (from a backup an earlier run left): who has business with it is told."""
        system = self._tree.processes.system
        if registrar.config.backup_path is not None:
            if restored:
                announce_started(self._node, registrar.name, system)
            return
        state_dir = self._spec.state_dir
        if state_dir is None:
            return
        if ran_before(state_dir, registrar.name):
            lost_everything(self._node, registrar.name, system, handle=registrar)

    def run_in(
        self, name: str, fn: Callable[[ResourceRegistrar], Any], *, timeout: float = 10.0
    ) -> Any:
        """Run `fn(registrar)` against manager `name`'s registrar, where it lives.

        For a process manager, or a manager of a pool (`SupervisorSpec(isolation=
        "process")`), `fn` is cloudpickled and runs on a fresh thread of that process (its
        result must pickle); for a thread manager, on the calling thread.

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
            ConfigError: `name` is not a str, `fn` not callable, `timeout` not a positive
                number of seconds, or `fn` cannot be pickled (process manager).
            RrError: the result cannot be pickled (process manager).
            Exception: whatever `fn` raised.
        """
        _check_child_name(name)
        if not callable(fn):
            raise ConfigError(f"fn must be callable as fn(registrar), got {fn!r}")
        check_seconds("timeout", timeout)
        spec = self._tree.specs.get(name)
        if not isinstance(spec, ManagerSpec):
            if spec is not None:
                raise UnknownServerError(
                    f"supervisor {self.name!r}: {name!r} is a supervisor, not a manager"
                )
            managers = (n for n, s in self._tree.specs.items() if isinstance(s, ManagerSpec))
            raise UnknownServerError(
                f"supervisor {self.name!r}: {name!r} is not in the tree"
                + _known_names(name, managers)
            )
        child = find_child(self._node, name)
        running = child.running if child is not None else None
        if isinstance(running, ThreadManager):
            return fn(running.registrar)
        system = self._tree.processes.system
        in_pool = child is None and pool_of(self._node, name) is not None
        if (in_pool or isinstance(running, ProcessManager)) and system is not None:
            return system.run(name, fn, timeout=timeout)
        raise RegistrarUnavailableError(f"manager {name!r} is not running")

    def call_with_retry(
        self,
        consumer: Registrar,
        target_rr: str,
        server: str,
        request: Any = retry.MISSING,
        *,
        on_status: StatusCallback | None = None,
        timeout: float | None = None,
        query_id: str | None = None,
    ) -> Query:
        """`consumer.call(...)`, waiting out a restart of `target_rr` and retrying.

        Every attempt uses the same caller-generated query id, so the provider's restored
        catalog recognises a retry of a call it answered before it died (never loaded
        twice, no second consumer id). If the wait runs out or is interrupted (cancelled, or
        ended by an error), the id is abandoned at the provider (now, or when it comes back):
        nothing leaks; `consumer` publishes the call's `CallWithdrawn` (reason `"timeout"` or
        `"interrupted"`, with its trace context) wherever it lives.

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
            ConfigError: `consumer` is not a registrar, `request` is missing, `timeout`
                not a positive number of seconds, or as for `ResourceRegistrar.call`;
                nothing was sent. Also on rr_actors' own event loop (await
                `acall_with_retry` there).
        """
        return blocking(
            self._retry(consumer, target_rr, server, request, on_status, timeout, query_id)
        )

    def _retry(
        self,
        consumer: Registrar,
        target_rr: str,
        server: str,
        request: Any,
        on_status: StatusCallback | None,
        timeout: float | None,
        query_id: str | None,
    ) -> Steps[Query]:
        abandon = functools.partial(self._tree.abandon, self._node)
        return retry.call_with_retry(
            self, abandon, consumer, target_rr, server, request, on_status, timeout, query_id
        )

    # -- watching the tree (watching.py) ----------------------------------------------

    def subscribe(
        self,
        callback: Callable[[events.Event], object],
        *,
        maxsize: int = DEFAULT_MAXSIZE,
    ) -> Subscription[events.Event]:
        """Call `callback(event)` for every event of the tree from now on, until closed.

        Events (`rr_actors.events`) of every supervisor and registrar of the tree, in
        threads or processes; subscribe before `start` to see the children start. The
        callback runs on a subscriber thread of its own, one event at a time, in the
        order they reached this process; past `maxsize` queued events new ones are
        dropped, counted (`Subscription.dropped`) and reported by one `EventsDropped`.

        Args:
            callback: `callback(event)`; what it raises is logged.
            maxsize: events queued for it before new ones are dropped.

        Returns:
            The subscription; `close()` it, or use it as a context manager
            (`with sup.subscribe(cb): ...`).

        Raises:
            ConfigError: `callback` is not callable, `maxsize` not a positive int, or the
                supervisor was stopped (no event would come).
        """
        if self._stopped:
            raise ConfigError(f"supervisor {self.name!r} was stopped: no event will come")
        return self._watch.subscribe(callback, maxsize=maxsize)

    def flush_events(self, *, timeout: float = 5.0) -> bool:
        """Bring the events of every manager process that happened before the call here.

        Returns once each running manager process handed what it had to this process's
        subscriptions; `Subscription.wait_delivered` then waits for the callbacks.

        Args:
            timeout: the longest wait, in seconds.

        Returns:
            Whether every manager process answered within `timeout`.

        Raises:
            ConfigError: `timeout` is not a positive number of seconds.
        """
        return self._watch.flush_events(timeout=timeout)

    def observe(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        allow_faults: bool = False,
        allow_remote: bool = False,
        keep_serving: bool = False,
        across_hosts: bool | None = None,
        sock: socket.socket | None = None,
    ) -> Page:
        """Deprecated (goes in the next release): `rr_actors_lab.observe.observe(sup, ...)`.

        Warns with a `DeprecationWarning`, then opens the observer's page as the lab's
        `observe(self, host, port, ...)` does (same arguments, returns and errors).

        Raises:
            MissingExtraError: the lab (its `observe` extra) is not installed.
        """
        _moved.warn("sup.observe()", "rr_actors_lab.observe.observe(sup)")
        page: Page = _moved.lab("observe", "sup.observe()", "observe").observe(
            self,
            host,
            port,
            allow_faults=allow_faults,
            allow_remote=allow_remote,
            keep_serving=keep_serving,
            across_hosts=across_hosts,
            sock=sock,
        )
        return page

    def graph(self, format: str = "mermaid") -> str:
        """Deprecated (goes in the next release): `rr_actors_lab.observe.graph(sup, format)`.

        Warns with a `DeprecationWarning`, then draws as the lab's `graph` does.

        Raises:
            MissingExtraError: the lab is not installed.
            ConfigError: `format` is neither `"mermaid"` nor `"dot"`.
        """
        _moved.warn("sup.graph()", "rr_actors_lab.observe.graph(sup)")
        text: str = _moved.lab("observe", "sup.graph()", "observe").graph(self, format)
        return text


def tree_watch(sup: Supervisor, *, observing: bool = False) -> TreeWatch:
    """The event stream and observers of `sup`'s tree (what the lab's observer reads).

    Raises:
        ConfigError: `observing` and `sup` was stopped (nothing to observe).
    """
    if observing and sup._stopped:
        raise ConfigError(f"supervisor {sup.name!r} was stopped: nothing to observe")
    return sup._watch


def _check_child_name(name: object) -> None:
    if not isinstance(name, str):
        raise ConfigError(f"name must be a child's name (a str), got {name!r}")


def _check_network(network: object) -> None:
    if network is None:
        return
    needed = ("serve", "run", "names", "resolve", "close")
    missing = [n for n in needed if not callable(getattr(network, n, None))]
    if missing or not hasattr(network, "address"):
        raise ConfigError(
            f"network must be a carrier's Transport (an AF_UNIX System, a ZenohNetwork) or "
            f"None, got {network!r}"
        )


def _state_dirs(spec: SupervisorSpec) -> list[Any]:
    """Every state directory a tree's managers use by default."""
    dirs = [spec.state_dir] if spec.state_dir is not None else []
    for child, path in walk(spec):
        if isinstance(child, SupervisorSpec):
            own = next((s.state_dir for s in (child, *path[::-1]) if s.state_dir is not None), None)
            if own is not None:
                dirs.append(own)
    return dirs
