"""What a whole supervision tree shares, finding a child anywhere in it, and its state dir.

```
 Supervisor (public handle) ── owns ──► Tree ◄── shared by ── Node (root) ─► Node (nested) ─► ...
                                         │                      each: children (Child records),
   which_children / child / wait ──► published snapshots        gave_up, giving_up
   (any thread, under tree.cond)         restart counts by name
   a wait (RestartWait) ◄── watchers: each publish looks, a decided wait's future settles
```

Nested supervisors are replaced when their parent restarts them; what must outlive an
incarnation lives in the `Tree`, keyed by child name (names are unique in a tree). Every
supervisor of the tree publishes its children's snapshots under the tree's one condition,
so one waiter (`RestartWait`) can watch a child anywhere in the tree. A waiter learns
an outcome only from a settled tree: while a supervisor on the child's path is giving up
(stopping its children), nothing is concluded.

One tree per state directory (`StateDirLock`): two trees sharing one would share their
managers' backups (after a restart each would hold the other's consumer ids). The first
tree to start claims `<state_dir>/.lock` (`_platform.lockfile`: an exclusive `flock`, its
pid written there); a second one (in this process or another) gets `ConfigError` naming
that pid. The lock goes at the tree's stop (the file removed), or when its process dies,
however it dies (a stale `.lock` file left by a dead process is not a lock). Each
manager's backup is claimed the same way on its own (`<backup_path>.lock`), whoever
starts it. A simulation takes no lock (`runtime.guards_files`: its files are its own):
its processes are one OS process, whose lock a killed simulated program would never let go.

The directory also remembers the registrars of the tree that keep no backup and may hold
ids at those that do (`ran_before`): the consumers `registrar()` starts without one, and
the managers whose own config has none (`<state_dir>/.consumers/<name>`, an empty file
each). Their ids are in the other managers' backups, and such a registrar's next start
(in a program started again after a SIGKILL, say) holds none of them: the supervisor
tells it that it lost everything (`lost_everything`), and reconciling releases them (rule
20). The marks stay: a name started once is reconciled at each later start, as a
registrar with a backup reconciles at each of its starts.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import weakref
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

from rr_actors._core import runtime, wire
from rr_actors._core.replies import FutureReply, Steps
from rr_actors._core.serial import SerialExecutor
from rr_actors._platform import lockfile
from rr_actors._process.spare import SparePool
from rr_actors._registrar import life
from rr_actors._supervision.children import (
    Child,
    ChildInfo,
    ChildState,
    Level,
    NestedSupervisor,
    ProcessManager,
    restarts_after,
    snapshot,
)
from rr_actors._supervision.watching import EventRelay
from rr_actors.config import SupervisorSpec, managers, walk
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
    "comes_back",
    "consumer_down",
    "death_watch_missed",
    "find_child",
    "locate",
    "lost_everything",
    "ran_before",
]

logger = logging.getLogger("rr_actors")

Clock = Callable[[], float]
"""A monotonic clock in seconds (a tree's, injectable: `Supervisor(clock=)`)."""


class Processes:
    """What the process managers of a tree share while it runs.

    Their cloudpickled setups, the carrier they join (this process is a member too) and
    the spare processes they start in. Empty until `open` (at the supervisor's start),
    and again after `close`.

    Args:
        spec: the whole tree's specs.
        network: the carrier given to the supervisor (`Supervisor(network=)`), or `None`
            for a private AF_UNIX `System` made at `open` when the tree has process
            managers (and closed at `close`; a given one is left open).
    """

    def __init__(self, spec: SupervisorSpec, network: Transport | None = None) -> None:
        self.spec = spec
        self.network = network
        self.setups: dict[str, bytes] = {}
        self.system: Transport | None = None
        self.spares: SparePool | None = None

    def open(self, spares: int, spare_delay: float) -> None:
        """Pickle the process managers' setups; take the carrier (a given one, or a new
        private system if there are process managers); start the spares.

        Raises:
            ConfigError: a setup cannot be pickled, or the given carrier was closed.
        """
        for manager in managers(self.spec):
            if manager.isolation == "process":
                try:
                    self.setups[manager.name] = wire.dumps(manager.setup)
                except Exception as exc:
                    raise ConfigError(
                        f"setup of manager {manager.name!r} is not picklable: {exc}"
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
        """While `on` (the supervisor's start), fork each process manager's process ahead
        of its start in order (`SparePool.ahead`)."""
        if self.spares is not None:
            starts = sum(1 for m in managers(self.spec) if m.isolation == "process")
            self.spares.ahead(starts if on else 0)

    def close_spares(self) -> None:
        """Release the idle spares and start no more (before the children stop)."""
        if self.spares is not None:
            self.spares.close()

    def close(self) -> None:
        """Release the spares and leave the system it made (its files are removed); a
        network given to the supervisor stays open (its owner closes it)."""
        self.close_spares()
        system, self.system = self.system, None
        if system is not None and system is not self.network:
            with contextlib.suppress(Exception):
                system.close()


class Tree:
    """What every supervisor of one tree shares (made by the root, kept across incarnations).

    Args:
        spec: the root supervisor's spec (the whole tree).
        clock, timer, random: the injectable time and jitter sources of every supervisor
            of the tree (see `Supervisor`).
        network: the carrier the tree's managers are served on (see `Processes`).
    """

    def __init__(
        self,
        spec: SupervisorSpec,
        *,
        clock: Clock,
        timer: runtime.StartTimer = runtime.thread_timer,
        random: Callable[[], float] | None = None,
        network: Transport | None = None,
    ) -> None:
        self.spec = spec
        self.cond = runtime.Condition()  # published snapshots of the whole tree; waiters
        # woken at each change (lock held), in the order they came: a dict, not a set (a
        # set of callbacks iterates in the order of their addresses, which a simulated seed's
        # history would then depend on: a wake is a choice point)
        self.watchers: dict[Callable[[], object], None] = {}
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

    def add_mailbox(self, mailbox: SerialExecutor) -> None:
        """A supervisor of this tree runs its events on `mailbox` (`on_a_supervisors_thread`)."""
        self._mailboxes.add(mailbox)

    def on_a_supervisors_thread(self) -> bool:
        """Whether the calling thread is one of the tree's supervisors' (a thread manager's
        `setup` runs there): a wait for one of them there could wait for itself."""
        return any(mailbox.on_own_thread() for mailbox in list(self._mailboxes))

    # -- changes: what waiters (wait_restarted, the observer) wait for ----------------------

    def changed(self) -> None:
        """A supervisor published its children's snapshots: wake every waiter (lock held)."""
        self._version += 1
        self.cond.notify_all()
        for wake in list(self.watchers):
            wake()

    def version(self) -> int:
        """How many changes were published so far."""
        return self._version

    def wait_changed(self, since: int, *, timeout: float) -> int:
        """Block until a change after version `since` is published, `wake` is called or
        `timeout` seconds pass (whichever first); return the version then."""
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
        self.started.add(name)

    def spec_info(self, name: str, state: ChildState) -> ChildInfo:
        """The snapshot of a child whose supervisor is down: `state`, no pid."""
        last = self.latest.get(name)
        last_exit = last.last_exit if last is not None else None
        return snapshot(self.specs[name], state, None, self.restarts.get(name, 0), last_exit)


@dataclasses.dataclass(frozen=True)
class Found:
    """A child found anywhere in the tree.

    Attributes:
        info: its snapshot (as published).
        gave_up: a give-up on its path that is final (nobody above restarts it).
        settling: a supervisor on its path is giving up right now: its state is not final.
        revivable: it exited (a `transient` child, after a normal exit) but a crash of a
            sibling restarts it with its group (one_for_all, rest_for_one; as in OTP).
    """

    info: ChildInfo
    gave_up: SupervisorGaveUpError | None
    settling: bool = False
    revivable: bool = False


def locate(level: Level, tree: Tree, name: str, down: ChildState | None = None) -> Found | None:
    """Find `name` below `level` by the specs, whether its supervisor runs or not.

    Call with the tree's lock held. `down`: the state of a supervisor above that is down.
    """
    settling = level.giving_up and level.gave_up is None
    for child in level.children:
        info = child.published
        if child.name == name:
            if down is not None:
                return Found(tree.spec_info(name, down), None)
            final = child.gave_up if info.state in ("exited", "stopped") else None
            revivable = (
                info.state == "exited"
                and child.spec.restart == "transient"
                and level.spec.strategy != "one_for_one"
            )
            return Found(info, final, settling, revivable)
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
    elif state == "running":
        state = "starting"
    final = child.gave_up if state in ("exited", "stopped") else None
    return Found(tree.spec_info(name, state), final)


def find_child(level: Level, name: str) -> Child | None:
    """The live `Child` record of `name` below `level` (in running supervisors), if any."""
    for child in list(level.children):
        if child.name == name:
            return child
        running = child.running
        if isinstance(running, NestedSupervisor):
            found = find_child(running.node, name)
            if found is not None:
                return found
    return None


def _process_managers(level: Level) -> list[str]:
    names: list[str] = []
    for child in list(level.children):
        running = child.running
        if isinstance(running, NestedSupervisor):
            names.extend(_process_managers(running.node))
        elif isinstance(running, ProcessManager):
            names.append(child.name)
    return names


def consumer_down(
    root: Level, name: str, network: Transport | None = None, *, stopped: bool = False
) -> None:
    """Death watch: this process's membership records that registrar `name` is gone for
    good, and every living registrar is told.

    Its consumers' ids are released where it held them, and the ids held at it get
    `FATAL` at their consumers (rule 19; `_registrar/life.py`, its presence). With `stopped` (it
    was stopped cleanly and will not be started again), only the first: what it still
    holds anywhere is stale (rule 12).

    `root`: the tree's root supervisor (its living process managers are told too);
    `network`: the tree's carrier, whose registrars (other processes, other hosts) are
    told too. A manager started later hears it at its start (`death_watch_missed`).
    """
    living = _process_managers(root)
    if network is not None and not network.closed:
        living.extend(network.names())
    life.gone_for_good(name, also=living, stopped=stopped)


def comes_back(name: str) -> None:
    """Manager `name` is being started again: it is no longer gone for good."""
    life.back(name)


def lost_everything(
    root: Level, name: str, network: Transport | None = None, handle: Any = None
) -> None:
    """Manager `name`, which keeps no backup, restarted with an empty catalog: every
    registrar of the system that holds ids there reconciles with it, and hears `FATAL`
    for each, and `name` reconciles with every registrar of the system, which releases
    the ids its last run held there (rule 20; a manager with a backup does both itself
    when it serves again).

    `root`: the tree's root supervisor (its living process managers are told too);
    `network`: the tree's carrier, whose registrars are told too; `handle`: `name`'s
    `ResourceRegistrar`, if it was just started here (`life.lost_everything`).
    """
    living = _process_managers(root)
    if network is not None and not network.closed:
        living.extend(network.names())
    life.lost_everything(name, also=living, handle=handle)


def death_watch_missed(name: str) -> None:
    """Manager `name` (re)started: tell it which registrars are gone for good, as this
    process's membership knows them (the death watch records a mark before it sends it).

    It may have been down when their death watch went out (`consumer_down`), and have
    restored their ids from its backup; those are released now, and what it held at
    a lost one is `FATAL`. (One that holds none of their ids releases nothing.) A
    manager of this process heard them already when it started (its membership).
    """
    for gone, stopped in sorted(life.gone().items()):
        if gone == name:
            continue
        try:
            life.tell_gone(name, gone, stopped=stopped)
        except RrError:
            logger.debug("death watch: %s unreachable", name)
            return


class RestartWait:
    """One wait for a child's restart (`Supervisor.wait_restarted`, `await_restarted`,
    `call_with_retry`'s): its condition, checked with the tree's lock held at each
    publish, and its outcome; `steps` waits for it, on a thread or awaited on a loop."""

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
        """Whether it is decided (the tree's lock held)."""
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
        """Wait until it is decided, at most `timeout` seconds (`replies.Steps`: blocking
        with `run_steps`, awaited with `run_steps_async`).

        A watcher of the tree looks at each publish and settles a future once the wait
        is decided: nothing polls, and an awaited wait holds no thread.

        Raises:
            CallTimeoutError: not decided within `timeout` seconds.
            RrError: what it came to (`result`).
        """
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
            tree.watchers[look] = None
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
        """The error of a wait that ran out (the tree's lock held)."""
        found = locate(self.root, self.tree, self.name)
        state = f" (state {found.info.state}, {found.info.restarts} restarts)" if found else ""
        return CallTimeoutError(
            f"child {self.name!r} was not restarted within {timeout:g} s{state}"
        )

    def result(self) -> ChildInfo:
        """The child's snapshot, running; or raise what it came to."""
        result = self.outcome[-1]
        if isinstance(result, RrError):
            raise result
        self.tree.wait_cursor[self.name] = result.restarts
        return result


# -- the state directory: one tree per directory, and the registrars it remembers ---------

LOCK_NAME = ".lock"
"""The lock file's name in a state directory."""

CONSUMERS = ".consumers"
"""The folder of a state directory that marks the registrars without a backup started on it."""


class StateDirLock:
    """Exclusive locks on some state directories, held until `release`."""

    def __init__(self, fds: list[int]) -> None:
        self._fds = fds

    @classmethod
    def acquire(cls, directories: Iterable[str | os.PathLike[str]]) -> StateDirLock:
        """Create each directory if needed and lock it for this supervisor.

        Raises:
            ConfigError: a directory is locked by another supervisor (the message names
                the directory and the holder's pid), or cannot be created or locked.
        """
        fds: list[int] = []
        try:
            unique = sorted({os.path.abspath(os.fspath(d)) for d in directories})
            fds.extend(fd for fd in map(_lock, unique) if fd is not None)
        except BaseException:
            cls(fds).release()
            raise
        return cls(fds)

    def release(self) -> None:
        """Release every lock (idempotent)."""
        fds, self._fds = self._fds, []
        for fd in fds:
            lockfile.release(fd)


def _lock(directory: str) -> int | None:
    try:
        os.makedirs(directory, exist_ok=True)
        if not runtime.guards_files():  # (a simulation: see the module's docstring)
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
    """Mark that registrar `name`, which keeps no backup, runs on state directory
    `directory`; return whether it was marked already (a registrar of that name ran
    there before: its ids may still be held in the managers' backups).

    Raises:
        ConfigError: the mark cannot be written (the message names the file).
    """
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
