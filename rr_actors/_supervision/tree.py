"""What a whole supervision tree shares, finding a child anywhere in it, and its state dir.

```
 Supervisor (public handle) ── owns ──► Tree ◄── shared by ── Node (root) ─► Node (nested) ─► ...
                                         │                      each: children (Child records),
   which_children / child / wait ──► published snapshots        gave_up, giving_up
   (any thread, under tree.cond)         restart counts by name, ids abandoned while down
   a wait (RestartWait) ◄── watchers: each publish looks, a decided wait's future settles
```

What must outlive a nested supervisor's incarnation lives in the `Tree`, keyed by child
name. Every supervisor publishes its children's snapshots under the tree's one condition,
so one waiter (`RestartWait`) watches a child anywhere; nothing is concluded while a
supervisor on its path is giving up. The state directory (`StateDirLock`, `ran_before`):
docs/explanation/failure-semantics.md, "One tree per state directory".
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import logging
import os
import weakref
from collections.abc import Callable, Container, Iterable, Iterator
from typing import TYPE_CHECKING, Any

from rr_actors._core import runtime, wire
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.membership import MEMBERSHIP
from rr_actors._core.replies import FutureReply, Steps
from rr_actors._core.serial import SerialExecutor
from rr_actors._platform import lockfile
from rr_actors._process.control import preload
from rr_actors._process.hearers import HEARERS
from rr_actors._process.spare import SparePool
from rr_actors._registrar import give_back, life
from rr_actors._supervision.children import (
    Child,
    ChildInfo,
    ChildState,
    Level,
    NestedSupervisor,
    ProcessManager,
    ThreadManager,
    is_pool,
    restarts_after,
    snapshot,
)
from rr_actors._supervision.watching import EventRelay
from rr_actors.config import Durability, RegistrarConfig, SupervisorSpec, managers, walk
from rr_actors.config import Steps as ProtocolSteps
from rr_actors.errors import (
    CallTimeoutError,
    ConfigError,
    RegistrarUnavailableError,
    RrError,
    SupervisorGaveUpError,
    UnknownServerError,
    _known_names,
)

if TYPE_CHECKING:
    from rr_actors._process.manager import ManagerProcess
    from rr_actors._transport.messenger import Transport

__all__ = [
    "CONSUMERS",
    "LOCK_NAME",
    "Clock",
    "Found",
    "Level",
    "RestartWait",
    "StateDirLock",
    "Tree",
    "announce_started",
    "comes_back",
    "consumer_down",
    "death_watch_missed",
    "find_child",
    "locate",
    "lost_everything",
    "pool_of",
    "ran_before",
]

logger = logging.getLogger("rr_actors")

POOL_MODULES = ("rr_actors._supervision.policy",)  # a pool's process runs it: preloaded

Clock = Callable[[], float]
"""A monotonic clock in seconds (a tree's, injectable: `Supervisor(clock=)`)."""


class Processes:
    """What the process managers of a tree share while it runs (from `open` to `close`):
    their pickled setups, the carrier, the spares. `network`: `Supervisor(network=)`."""

    def __init__(self, spec: SupervisorSpec, network: Transport | None = None) -> None:
        self.spec = spec
        self.network = network
        self.setups: dict[str, bytes] = {}
        self.system: Transport | None = None
        self.spares: SparePool | None = None
        self.held: list[ManagerProcess] | None = None  # pinged once the ordered start ends
        self._held_lock = runtime.Lock()

    def open(self, spares: int, spare_delay: float) -> None:
        """Raises `ConfigError`: a setup cannot be pickled, or the given carrier was closed."""
        for manager in managers(self.spec):
            if manager.isolation == "process":
                try:
                    self.setups[manager.name] = wire.dumps(manager.setup)
                except Exception as exc:
                    raise ConfigError(
                        f"setup of manager {manager.name!r} is not picklable: {exc}"
                    ) from exc
        for pool, _ in walk(self.spec):  # (a pool's setups are pickled at each of its starts)
            if isinstance(pool, SupervisorSpec) and is_pool(pool):
                preload(POOL_MODULES)  # (once: a pool's restart does not import them)
                try:
                    wire.dumps(pool)
                except Exception as exc:
                    raise ConfigError(
                        f"a setup in pool {pool.name!r} is not picklable: {exc}"
                    ) from exc
        if self.network is not None:
            if self.network.closed:
                raise ConfigError(
                    f"supervisor {self.spec.name!r}: its network was closed (this process "
                    "left that system); give it an open one"
                )
            self.system = self.network
        elif self.spec.has_processes():
            from rr_actors._transport import System  # noqa: PLC0415

            self.system = System.create()  # also attaches this process
        if self.spec.has_processes() and runtime.manager_process is None:  # (real ones)
            self.spares = SparePool(spares, self.spec.name, delay=spare_delay)

    def start_ahead(self, on: bool) -> None:
        """While `on` (the supervisor's start), fork process managers' processes ahead, and
        ping none of those started: their pings begin as it ends, paced (`heartbeat.Pace`; as
        OTP's supervisor hears its children only once `start_children` returns; pinging
        the k started while the next starts made the start's work grow as N²)."""
        if self.spares is not None:
            starts = sum(1 for c, _ in walk(self.spec) if c.isolation == "process")
            self.spares.ahead(starts if on else 0)
        with self._held_lock:
            held, self.held = self.held or [], [] if on else None
        for handle in held:
            handle.beat_from(runtime.monotonic())

    def hold(self, handle: ManagerProcess) -> None:
        """Ping `handle` (held) once the ordered start has ended: at once if it has (a
        start that began before its end, a restart, finished after it)."""
        with self._held_lock:
            if self.held is not None:
                self.held.append(handle)
                return
        handle.beat_from(runtime.monotonic())

    def close_spares(self) -> None:
        if self.spares is not None:
            self.spares.close()

    def close(self) -> None:
        """Release the spares and leave the system it made (a given network stays open)."""
        self.close_spares()
        system, self.system = self.system, None
        if system is not None and system is not self.network:
            with contextlib.suppress(Exception):
                system.close()


class Tree:
    """What every supervisor of one tree shares (made by the root, kept across incarnations)."""

    def __init__(
        self,
        spec: SupervisorSpec,
        *,
        clock: Clock,
        timer: runtime.StartTimer = runtime.thread_timer,
        random: Callable[[], float] | None = None,
        network: Transport | None = None,
        durability: Durability = "process",
        steps: ProtocolSteps | None = None,
    ) -> None:
        self.spec = spec
        self.durability = durability  # the least every backup of the tree gets (rule 14)
        self.steps = ProtocolSteps() if steps is None else steps  # (`Supervisor(steps=)`)
        self.cond = runtime.Condition()  # published snapshots of the whole tree
        # waiters woken at each change, in the order they came (each its number: woken in
        # another order, a simulated seed's history would change at each choice point between)
        self.watchers: dict[Callable[[], object], int] = {}
        self.watches = itertools.count()
        self._version = 0  # changes published so far (`wait_changed`)
        self.specs = {child.name: child for child, _ in walk(spec)}
        self.clock = clock
        self.timer = timer
        self.random = runtime.random if random is None else random
        self.latest: dict[str, ChildInfo] = {}  # the last published snapshot of every child
        self.restarts: dict[str, int] = {}  # starts after the first, across incarnations
        self.started: set[str] = set()
        self.abandon_lock = runtime.Lock()
        self.abandon_later: dict[str, list[tuple[str, str]]] = {}  # name -> (query id, origin)
        self.wait_cursor: dict[str, int] = {}
        self.processes = Processes(spec, network)  # what process managers share
        self.events = EventRelay()  # the tree's events (`Supervisor.subscribe`)
        self.down_since: dict[str, float] = {}  # name -> when its last incarnation ended
        self.restart_due: dict[str, float] = {}  # name -> when its backoff ends (runtime.wall())
        self._mailboxes: weakref.WeakSet[SerialExecutor] = weakref.WeakSet()  # every Node's
        # a pool's tree (`PoolSetup`): its root's give-up ends the process (never returns)
        self.escalate: Callable[[SupervisorGaveUpError], None] | None = None
        # and its parent, told of each manager's (re)start (`announce_started`)
        self.upward: Callable[[str], None] | None = None
        self.ending: Ending | None = None  # the whole tree's stop, while it runs
        self.restarted_here: set[str] = set()  # a pool's, not yet told upward

    def abandon(self, root: Level, name: str, query_id: str, origin: str) -> None:
        """Abandon `query_id` at provider `name`: now if it runs, else at its next start."""
        with self.abandon_lock:
            child = find_child(root, name)
            if child is None or child.state != "running" or child.running is None:
                self.abandon_later.setdefault(name, []).append((query_id, origin))
                return
        give_back(name, query_id, origin)

    def give_back_abandoned(self, name: str) -> None:
        """Send provider `name`, just started, the ids abandoned while it was down."""
        with self.abandon_lock:
            abandoned = self.abandon_later.pop(name, [])
        for query_id, origin in abandoned:
            give_back(name, query_id, origin)

    def durable(self, config: RegistrarConfig) -> RegistrarConfig:
        """`config` at the tree's durability at least (a tree chooses for every manager),
        with the tree's steps unless it names steps of its own (`Supervisor(steps=)`)."""
        if self.steps != ProtocolSteps() and config.steps == ProtocolSteps():
            config = dataclasses.replace(config, steps=self.steps)
        if self.durability == "power" and config.durability != "power":
            return dataclasses.replace(config, durability="power")
        return config

    def add_mailbox(self, mailbox: SerialExecutor) -> None:
        self._mailboxes.add(mailbox)

    def on_a_supervisors_thread(self) -> bool:
        """Whether the calling thread is one of the tree's supervisors' (a thread manager's
        `setup` runs there)."""
        return any(mailbox.on_own_thread() for mailbox in list(self._mailboxes))

    # -- changes: what waiters (wait_restarted, the observer) wait for ----------------------

    def changed(self) -> None:
        """A supervisor published its children's snapshots: wake every waiter (lock held)."""
        self._version += 1
        self.cond.notify_all()
        for wake in sorted(self.watchers, key=self.watchers.__getitem__):
            wake()

    def version(self) -> int:
        return self._version

    def wait_changed(self, since: int, *, timeout: float) -> int:
        """Block until a change after version `since`, `wake`, or `timeout` seconds; return
        the version then."""
        with self.cond:
            if self._version == since:
                self.cond.wait(timeout)
            return self._version

    def wake(self) -> None:
        """Wake every `wait_changed` now (an observer that closes)."""
        with self.cond:
            self.cond.notify_all()

    def count_start(self, name: str) -> None:
        """Note that child `name` started (a restart if it had started before)."""
        if name in self.started:  # a restart: by its supervisor, or of its parent
            self.restarts[name] = self.restarts.get(name, 0) + 1
            if self.upward is not None:  # a pool's: its parent counts it too
                self.restarted_here.add(name)
        self.started.add(name)

    def spec_info(self, name: str, state: ChildState, pid: int | None = None) -> ChildInfo:
        """The snapshot of a child whose supervisor is down (`state`, no pid), or in a
        pool's process (`pid`)."""
        last = self.latest.get(name)
        last_exit = last.last_exit if last is not None else None
        return snapshot(self.specs[name], state, pid, self.restarts.get(name, 0), last_exit)


@dataclasses.dataclass(frozen=True)
class Found:
    """A child found anywhere in the tree.

    `gave_up`: a final give-up on its path; `settling`: a supervisor on its path is giving
    up now; `revivable`: a `transient` child that exited, which a group restart revives.
    """

    info: ChildInfo
    gave_up: SupervisorGaveUpError | None
    settling: bool = False
    revivable: bool = False


def locate(level: Level, tree: Tree, name: str, down: ChildState | None = None) -> Found | None:
    """Find `name` below `level`, whether its supervisor runs or not (the tree's lock held;
    `down`: the state of a supervisor above that is down)."""
    settling = level.giving_up and level.gave_up is None
    child = level.by_name.get(name)  # (names are unique in a tree: looked up, not walked)
    if child is not None:
        info = child.published
        if down is not None:
            return Found(tree.spec_info(name, down), None)
        final = child.gave_up if info.state in ("exited", "stopped") else None
        revivable = (
            info.state == "exited"
            and child.spec.restart == "transient"
            and level.spec.strategy != "one_for_one"
        )
        return Found(info, final, settling, revivable)
    for child in level.nested:
        info = child.published
        if name in child.subtree:
            found = _locate_below(child, tree, name, down if down is not None else info.state)
            if found is not None and settling:
                return dataclasses.replace(found, settling=True)
            return found
    return None


def _locate_below(child: Child, tree: Tree, name: str, state: ChildState) -> Found | None:
    """`locate` in the subtree of nested supervisor `child`, whose state is `state`."""
    running = child.running
    if state == "running" and isinstance(running, NestedSupervisor):
        nested = running.node
        if nested.gave_up is None:
            return locate(nested, tree, name)
        if not restarts_after(child.spec.restart, normal=True):  # no one restarts it
            found = locate(nested, tree, name)
            return None if found is None else Found(found.info, nested.gave_up)
        state = "restarting"  # its parent will restart it (or give up itself)
    elif state == "running" and isinstance(running, ProcessManager):  # a pool: its children
        return Found(tree.spec_info(name, "running", running.pid), None)  # run as it does
    elif state == "running":
        state = "starting"
    final = child.gave_up if state in ("exited", "stopped") else None
    return Found(tree.spec_info(name, state), final)


def find_child(level: Level, name: str) -> Child | None:
    child = level.by_name.get(name)
    if child is not None:
        return child
    for child in list(level.nested):
        running = child.running
        if isinstance(running, NestedSupervisor):
            found = find_child(running.node, name)
            if found is not None:
                return found
    return None


def pool_of(level: Level, name: str) -> Child | None:
    """The running pool (a supervisor in its own process) that holds child `name`."""
    for child in list(level.nested):
        running = child.running
        if name not in child.subtree:
            continue
        if isinstance(running, ProcessManager):
            return child
        if isinstance(running, NestedSupervisor):
            return pool_of(running.node, name)
    return None


def _leaves(level: Level) -> Iterator[Child]:
    """The tree's children below `level` that are not supervisors run here, in start order
    (a nested supervisor's, in its place)."""
    for child in list(level.children):
        running = child.running
        if isinstance(running, NestedSupervisor):
            yield from _leaves(running.node)
        else:
            yield child


def _piped(level: Level) -> set[str]:
    """The registrars the tree's control pipes reach below `level`: its process managers,
    its pools and their managers."""
    reached: set[str] = set()
    for child in _leaves(level):
        if isinstance(child.running, ProcessManager):
            reached.add(child.name)
            reached.update(child.subtree)
    return reached


def _process_handles(level: Level) -> dict[str, ProcessManager]:
    """The tree's living manager processes below `level`, by child name (a pool's by the
    pool's), in start order."""
    return {c.name: c.running for c in _leaves(level) if isinstance(c.running, ProcessManager)}


def _threaded(level: Level) -> set[str]:
    """The tree's living thread managers below `level`."""
    return {c.name for c in _leaves(level) if isinstance(c.running, ThreadManager)}


@dataclasses.dataclass
class Ending:
    """The whole tree's stop: its managers stopped or lost (killed) so far (each told them before
    its own stop, `consumer_down`), and who else hears of a stop, read once as it began (the
    carrier's registrars beyond the tree, its thread managers): one stop walks no tree."""

    beyond: frozenset[str]
    threaded: frozenset[str]
    stopped: list[str] = dataclasses.field(default_factory=list)
    lost: list[str] = dataclasses.field(default_factory=list)

    @classmethod
    def of(cls, root: Level, network: Transport | None) -> Ending:
        names = set() if network is None or network.closed else set(network.names())
        return cls(frozenset(names - _names_below(root)), frozenset(_threaded(root)))


def quiet(root: Level) -> None:
    """The whole tree's stop began: its manager processes are pinged no more."""
    for manager in _process_handles(root).values():
        manager.handle.quiet()


def consumer_down(
    root: Level,
    name: str,
    network: Transport | None = None,
    *,
    stopped: bool = False,
    ending: Ending | None = None,
) -> None:
    """Death watch (rule 19): registrar `name` is gone for good; every living registrar is
    told (`stopped`: it stopped cleanly, what it holds is stale, rule 12). `ending`
    (`Tree.ending`): the tree's managers hear one stopped or lost (killed at its stop's
    bound) only before their own stop, one notice each, not one per pair (issue 69)."""
    if ending is not None:
        life.gone_for_good(name, also=ending.beyond, stopped=stopped, later=ending.threaded)
        (ending.stopped if stopped else ending.lost).append(name)
        return
    living = list(_process_handles(root))  # (the tree's living process managers, and the
    if network is not None and not network.closed:  # registrars of its carrier)
        living.extend(network.names())
    life.gone_for_good(name, also=living, stopped=stopped)


def comes_back(name: str) -> None:
    life.back(name)


def lost_everything(
    root: Level,
    name: str,
    network: Transport | None = None,
    handle: Any = None,
    *,
    upward: Callable[[str], None] | None = None,
) -> None:
    """Registrar `name`, which keeps no backup, restarted empty: it and every registrar of
    the system reconcile (rule 20). `handle`: its `ResourceRegistrar`, if started here;
    `upward`: as `announce_started`."""
    announce_started(root, name, network, here=False, upward=upward)
    life.lost_everything(name, handle=handle)  # (and this process's registrars)


def announce_started(
    root: Level,
    name: str,
    network: Transport | None = None,
    *,
    here: bool = True,
    beyond: Container[str] | None = None,
    origin: str | None = None,
    upward: Callable[[str], None] | None = None,
) -> None:
    """Registrar `name` (re)started: each living registrar of the system that monitors it hears
    so once (`Membership.started`), the manager processes and pools that monitor it on their
    control pipes (`HEARERS`: no other process is woken, none connects to one it has no
    business with), the registrars beyond the tree through the directory.

    `here`: this process's registrars told too. `beyond`: a first start, only registrars
    not in it are told, here and on the network (every name of the tree, `Tree.specs`:
    no walk of the tree at each of its N starts). In a pool's process (`upward`:
    `Tree.upward`, its control pipe) only this process's registrars are told here, and its
    parent tells the rest; `origin`: the pool the announcement came from (told already)."""
    walk = root.has_pipes and beyond is None  # (a tree of threads, a first start: no walk)
    for hearer in HEARERS.announce(name) if walk else ():
        if hearer.name not in (name, origin):  # (the processes that monitor it: issue 69)
            hearer.tell_started(name)
    reached = beyond if beyond is not None else _piped(root) if walk else set()
    if here or beyond is not None:
        MEMBERSHIP.started(name, skip=reached)
    others: set[str] = set()
    if upward is not None:
        upward(name)
    elif network is not None and not network.closed:
        others = set(network.names()) - {peer.name for peer in DIRECTORY.local_peers()}
    for other in sorted(other for other in others if other not in reached):
        life.heard_started(other, name)


def _names_below(level: Level) -> set[str]:
    """Every child name of the tree below `level` (a pool's managers too)."""
    names: set[str] = set()
    for child in list(level.children):
        names.add(child.name)
        names |= child.subtree
    return names


def death_watch_missed(name: str) -> None:
    """Manager `name` (re)started: tell it which registrars are gone for good (it may
    have been down when their death watch went out, and restored their ids)."""
    for gone, stopped in sorted(life.gone().items()):
        if gone == name:
            continue
        try:
            life.tell_gone(name, gone, stopped=stopped)
        except RrError:
            logger.debug("death watch: %s unreachable", name)
            return


class RestartWait:
    """One wait for a child's restart: its condition, checked at each publish, and its outcome."""

    def __init__(
        self, tree: Tree, root: Level, root_name: str, name: str, restarts: int | None
    ) -> None:
        self.tree = tree
        self.root = root
        self.root_name = root_name
        self.name = name
        self.target = restarts if restarts is not None else tree.wait_cursor.get(name, 0) + 1
        self.outcome: list[ChildInfo | RrError] = []

    def settled(self) -> bool:
        tree, root, name = self.tree, self.root, self.name
        found = locate(root, tree, name)
        if found is None:
            self.outcome.append(
                UnknownServerError(
                    f"supervisor {self.root_name!r} has no child named {name!r}"
                    + _known_names(name, tree.specs)
                )
            )
            return True
        info = found.info
        error = root.gave_up or found.gave_up
        if info.state == "running" and info.restarts >= self.target:
            self.outcome.append(info)
        elif found.settling:
            return False  # a supervisor on its path is giving up: wait until it settled
        elif error is not None:
            self.outcome.append(error)
        elif info.state in ("exited", "stopped") and not found.revivable:
            # (down for good, whatever its count: one down when the wait's target was
            # taken waits for the count it had, `retry.restart_after_failure`)
            self.outcome.append(
                RegistrarUnavailableError(
                    f"child {name!r} is {info.state} ({info.last_exit}) and will not be restarted"
                )
            )
        return bool(self.outcome)

    def steps(self, timeout: float) -> Steps[ChildInfo]:
        """Wait until it is decided, at most `timeout` seconds (a watcher of the tree settles
        a future: nothing polls). Raises `CallTimeoutError`, or what it came to."""
        tree = self.tree
        deadline = runtime.monotonic() + timeout
        decided = FutureReply()

        def look() -> None:  # now, and at each publish of the tree (its lock held)
            try:
                if not self.outcome and self.settled():
                    decided.set_result(None)
            except Exception as exc:  # noqa: BLE001 - raised to the waiter, not the publisher
                decided.set_error(exc)

        with tree.cond:
            look()
            tree.watchers[look] = next(tree.watches)
        try:
            if not (yield decided.future, deadline):
                with tree.cond:
                    look()  # (decided at the last moment: as `Condition.wait_for` looks)
                    if not self.outcome:
                        raise self.timed_out(timeout)
        finally:
            with tree.cond:
                tree.watchers.pop(look, None)
        decided.future.get(timeout=0)  # (an error `look` met)
        return self.result()

    def timed_out(self, timeout: float) -> CallTimeoutError:
        found = locate(self.root, self.tree, self.name)
        state = f" (state {found.info.state}, {found.info.restarts} restarts)" if found else ""
        return CallTimeoutError(
            f"child {self.name!r} was not restarted within {timeout:g} s{state}"
        )

    def result(self) -> ChildInfo:
        result = self.outcome[-1]
        if isinstance(result, RrError):
            raise result
        self.tree.wait_cursor[self.name] = result.restarts
        return result


# -- the state directory: one tree per directory, and the registrars it remembers ---------

LOCK_NAME = ".lock"
CONSUMERS = ".consumers"  # marks the registrars without a backup started on it


class StateDirLock:
    """Exclusive locks on some state directories, held until `release`."""

    def __init__(self, fds: list[int]) -> None:
        self._fds = fds

    @classmethod
    def acquire(cls, directories: Iterable[str | os.PathLike[str]]) -> StateDirLock:
        """Create and lock each directory; `ConfigError` if one is locked by another
        supervisor (naming its pid) or cannot be created or locked."""
        fds: list[int] = []
        try:
            unique = sorted({os.path.abspath(os.fspath(d)) for d in directories})
            fds.extend(fd for fd in map(_lock, unique) if fd is not None)
        except BaseException:
            cls(fds).release()
            raise
        return cls(fds)

    def release(self) -> None:
        fds, self._fds = self._fds, []
        for fd in fds:
            lockfile.release(fd)


def _lock(directory: str) -> int | None:
    try:
        os.makedirs(directory, exist_ok=True)
        if not runtime.guards_files():  # (a simulation: its files are its own)
            return None
        return lockfile.claim(os.path.join(directory, LOCK_NAME))
    except lockfile.HeldError as held:
        ours = held.holder == str(os.getpid())  # (a tree this program did not stop)
        then = ", one of this process that is still running: stop it first, or" if ours else ";"
        raise ConfigError(
            f"state_dir {directory!r} is in use by another supervisor (pid {held.holder})"
            f"{then} give each supervisor tree its own state_dir"
        ) from None
    except OSError as exc:
        raise ConfigError(f"state_dir {directory!r} cannot be used: {exc}") from exc


def ran_before(directory: str | os.PathLike[str], name: str) -> bool:
    """Mark that registrar `name`, which keeps no backup, runs on `directory`; whether it
    was marked already. `ConfigError`: the mark cannot be written."""
    folder = os.path.join(os.fspath(directory), CONSUMERS)
    mark = os.path.join(folder, name)
    try:
        os.makedirs(folder, exist_ok=True)
        with open(mark, "x"):
            pass
    except FileExistsError:
        return True
    except OSError as exc:
        raise ConfigError(
            f"state_dir {os.fspath(directory)!r}: cannot mark {mark!r}: {exc}"
        ) from exc
    return False
