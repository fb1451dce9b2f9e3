"""The simulated carrier: the in-memory network between simulated processes, with delays,
order per link, cuts and heals.

```
 process A: Remote.tell ─► messenger ─► hub.route(name) ─► A's link to name (one per
   sending process and served registrar; made at A's first send, dialed until its first
   frame arrives: what A sent on it is lost if A dies before)
   hub.send(link, frame) ─► its wire to B: after a seeded delay, in order (FIFO per link),
   on a thread of B's (`_Wire`) ─► the messenger: unpickle, tell the registrar
 B's answer ─► hub.answer(link) ─► the link's wire back, likewise ─► link.pending.answered
 partition(pids) ─► links across fail what waits; sends across raise; the wire dropped
 serve(endpoint) ─► refused while another live process on its side serves the name
 heal() ─► links work again; a name served on both sides: rule 22 keeps one (`kept`);
   every process hears the names across reachable again (rule 20)
 a process ends ─► what it served ends; a name gone unclean that nobody else serves:
   lost for every process (rule 19) unless its speaker is heard (then awaited)
 deafen(pid) / hear(pid) ─► a process that cannot hear its router, then rejoined
```

All of it: docs/explanation/simulation.md, "The simulated network". The faults a plan
aims at it: `SimulatedNetwork`'s docstring. Naming, replies, stand-ins,
sizes and compensation are the messenger's. A kill drops what is on the wire to the killed
process; what it sent on a link dialed before it died still arrives, as a socket's buffered
bytes do; on a link still dialing, it dies with it, as frames queued behind a connect do.
"""

from __future__ import annotations

import functools
import logging
import pickle
import sys
from collections.abc import Callable, Iterable
from typing import Any

from rr_actors._core.directory import DIRECTORY
from rr_actors._core.hlc import CLOCK, from_seconds
from rr_actors._transport.codec import Claim, split_frame
from rr_actors._transport.messenger import (
    Endpoint,
    Lost,
    Messenger,
    Route,
    run_lost,
)
from rr_actors._transport.resolve import Resolution, Resolve, Sided
from rr_actors.errors import RegistrarStoppedError, RegistrarUnavailableError, RrError
from rr_actors.simulation import _primitives as sim
from rr_actors.simulation._processes import Process
from rr_actors.simulation._run import running_scheduler
from rr_actors.simulation._scheduler import Scheduler
from rr_actors.testing.memory import MemoryNetwork, _Hub, _Route, _Served

__all__ = ["SimulatedNetwork"]

logger = logging.getLogger("rr_actors")

DELAY = (0.0005, 0.005)
"""Seconds a frame takes on a link, at least and at most (each drawn from the seed)."""


class SimulatedNetwork(MemoryNetwork):
    """An in-memory network between simulated processes (made inside a simulated run):
    each frame after a seeded delay, in order per link; `partition` and `heal`.

    The fault hooks a plan aims (rr_actors_lab.experiments, on the simulation):
    `cut_connections(pid)` shuts every link of the process down (what was sent arrives,
    then what waits fails; the next send dials again); `duplicate_first(name, until)` puts
    the first frame of each link made to `name` before `until` on the wire twice;
    `kill_at_answer(pid, fire)` SIGKILLs the process at its next non-error answer (after
    the commit), `fire()` first; `on_serve(name, fire)` calls `fire(pid)` (on that
    process's thread) when a process next serves `name`.

    Args:
        system: its name (`MemoryAddress` finds it by that name).
        delay: `(least, most)` seconds a frame takes on a link.
        lease: seconds a stopped process is heard (a liveliness lease) before what it
            serves cannot be reached (reachable again once it runs); `None`: for ever.
        resolve: which of two servers of one name is kept after a heal (rule 22), as
            `rr.ZenohNetwork`'s `resolve`: `"first_served"` (default), `"majority"` or a
            function of two `rr.Claimant`s (a server's `side`: the live processes its
            process heard as it began to serve).

    Raises:
        ConfigError: `resolve` is none of those.
    """

    def __init__(
        self,
        system: str = "simulated",
        *,
        delay: tuple[float, float] = DELAY,
        lease: float | None = None,
        resolve: Resolve = "first_served",
    ) -> None:
        self.delay = delay
        self.lease = lease
        resolution = Resolution(resolve)  # (checked before the network is made)
        super().__init__(system)
        self.resolution = resolution

    def partition(self, side: Iterable[int], *, started_by: bool = False) -> None:
        """Cut the processes of pids `side` off the others (both ways) until `heal`.

        Args:
            side: the pids of the processes cut off (a process made during the cut is on its
                parent's side).
            started_by: with each process of `side`, every live one it started, recursively
                (a host's processes).
        """
        hub = self._simulated()
        pids = set(side)
        if started_by:
            for process in hub.sched.processes:  # (in pid order: a parent before its child)
                if process.parent in pids and process.alive:
                    pids.add(process.pid)
        hub.partition(frozenset(pids))

    def heal(self, *, unheard: Iterable[int] = ()) -> None:
        """Join every process again; each hears the names across as reachable again.

        Args:
            unheard: pids of processes that do not hear the others' servers after the heal (a
                link that heals one way, as Zenoh's presence would leave it).
        """
        self._simulated().heal(frozenset(unheard))

    def cut_connections(self, pid: int) -> int:
        """Close every link from or to process `pid` (what waits on them fails; the next
        send makes a new one): a real process's connections shut down. How many closed."""
        return self._simulated().cut_connections(pid)

    def duplicate_first(self, name: str, until: float) -> list[int]:
        """Each link made to registrar `name` before virtual time `until` delivers its
        first frame twice, the copy right behind it. Returns a one-item list that counts
        the frames put on the wire twice."""
        count = [0]
        self._simulated().duplicate[name] = (until, count)
        return count

    def kill_at_answer(self, pid: int, fire: Callable[[], object]) -> None:
        """At process `pid`'s next answer that is not an error, run `fire()` and SIGKILL
        it before the answer leaves (from its own thread: never returns there)."""
        self._simulated().kill_answer[pid] = fire

    def on_serve(self, name: str, fire: Callable[[int], object]) -> None:
        """When a process next serves `name`, run `fire(its pid)` on its thread."""
        self._simulated().serving[name] = fire

    def deafen(self, pid: int) -> None:
        """Process `pid` cannot hear its router until `hear(pid)`: what waits on its links fails,
        its
        sends raise `RegistrarUnavailableError`, it serves no name, and every name across is lost
        for it (its own judged by rule 19 for the others)."""
        self._simulated().deafen(pid)

    def hear(self, pid: int) -> None:
        """Process `pid` hears its router again: as a heal for it (rule 22 decides a name
        served on both sides; each side hears the names across as reachable, rule 20)."""
        self._simulated().hear(pid)

    def _simulated(self) -> _SimulatedHub:
        hub = self._hub
        assert isinstance(hub, _SimulatedHub)
        return hub


class _Wire:
    """Frames one way on one link: each after its delay, in order, on a thread of the
    receiving process (started at the first frame)."""

    __slots__ = ("_hub", "_last", "_name", "_queue", "_thread", "process")

    def __init__(self, hub: _SimulatedHub, process: Process, name: str) -> None:
        self._hub = hub
        self.process = process
        self._name = name
        self._queue = sim.SimpleQueue(hub.sched)
        self._last = 0.0  # (the last frame's arrival: none overtakes it)
        self._thread: sim.Thread | None = None

    def put(self, deliver: Callable[[], object]) -> float:
        """Put `deliver` on the wire; when it arrives (virtual seconds)."""
        hub = self._hub
        sched = hub.sched
        least, most = hub.delay
        due = max(sched.now + sched.data.uniform(least, most), self._last)
        self._last = due
        self._queue.put((due, deliver))
        if self._thread is None:
            self._thread = sim.Thread(
                sched, target=self._run, name=self._name, daemon=True, process=self.process
            )
            self._thread.start()
        return due

    def _run(self) -> None:
        sched = self._hub.sched
        while True:
            due, deliver = self._queue.get()
            if due > sched.now:
                sim.sleep(sched, due - sched.now)
            try:
                deliver()
            except Exception:
                logger.exception("%s: a delivery failed", self._name)


class _Told(Route):
    """Rule 22's way to the other server of `name`, in process `who` (`route(name,
    server)`): the kept one's `Claim` sent on it goes as `_SimulatedHub.send` says."""

    __slots__ = ("name", "who")

    def __init__(self, name: str, who: str) -> None:
        super().__init__(sys.maxsize)
        self.name, self.who = name, who


class _Link(_Route):
    """The way from one simulated process to one served registrar: a wire there, a wire
    back for the answers."""

    __slots__ = ("_back", "_hub", "_there", "closed", "dialed", "sender", "severed", "twice")

    def __init__(self, hub: _SimulatedHub, sender: Process, served: _Served) -> None:
        super().__init__(served, hub.messenger)
        self._hub = hub
        self.sender = sender
        self.closed = False
        self.severed = False  # shut down by a cut: what is on its wires still arrives
        self.twice: list[int] | None = None  # its first frame twice, counted (`duplicate_first`)
        # when its dial ends: as its first frame arrives (that frame's delay stands for the
        # connect); what its sender sent before is held in the sender until then
        self.dialed = sys.float_info.max
        receiver = served_by(served)
        name = served.endpoint.name
        self._there = _Wire(hub, receiver, f"rr-link-{sender.pid}-to-{name}")
        self._back = _Wire(hub, sender, f"rr-link-{name}-to-{sender.pid}")

    def put(self, data: bytes) -> bool:
        served, hub = self.served, self._hub
        if self.closed or served.cut or served.gone or hub.apart(self):
            return False
        endpoint, messenger = served.endpoint, hub.messenger
        token, payload = split_frame(data)
        due = self._there.put(lambda: self._arrive(messenger, endpoint, token, payload))
        self.dialed = min(self.dialed, due)
        if self.twice is not None:
            self.twice[0] += 1
            self.twice = None
            self._there.put(lambda: self._arrive(messenger, endpoint, token, payload))
        return True

    def _arrive(self, messenger: Messenger, endpoint: Endpoint, token: int, payload: Any) -> None:
        if self._hub.apart(self):  # lost on the wire
            return
        if self.closed and not self.severed:  # (its process ended)
            return
        sender = self.sender
        if not sender.alive and sender.ended_at < self.dialed:  # died dialing: lost with it
            return
        messenger.message(endpoint, self, token, payload)

    def answer(self, data: bytes, on_lost: Lost | None) -> bool:
        if on_lost is not None:  # (an answer, not an error: what it changed committed)
            self._hub.answering(served_by(self.served))
        if self.closed or not self.sender.alive or self._hub.apart(self):
            return False
        self._back.put(lambda: self._answered(data, on_lost))
        return True

    def _answered(self, data: bytes, on_lost: Lost | None) -> None:
        if self._hub.apart(self):  # lost on the wire: its compensation runs
            if on_lost is not None:
                run_lost([on_lost])
            return
        self.pending.answered(*split_frame(data))

    def close(self, error: RrError) -> None:
        self.closed = True
        self.pending.fail(None, error)

    def sever(self) -> None:
        """A cut shut it down, as `shutdown()` a socket: what was sent arrives, then waiters
        fail."""
        self.closed = self.severed = True
        error = RegistrarUnavailableError(
            f"registrar {self.served.endpoint.name!r}: the connection was cut"
        )
        self._back.put(lambda: self.pending.fail(None, error))


def served_by(served: _Served) -> Process:
    process: Process = getattr(served, "process")  # noqa: B009 - set by `serve`
    return process


class _Server(_Served):
    """A registrar served on the simulated network: its process, who speaks for it when
    its process dies (rule 19), the stamp of when it began to serve (`Sided`, rule 22)."""

    def __init__(
        self, hub: _SimulatedHub, endpoint: Endpoint, process: Process, speaker: int | None
    ) -> None:
        self.process = process  # (before the delivery thread: it is the process's)
        self.speaker = speaker  # the pid that restarts it or says it is lost (rule 19)
        self.how = ""  # how it ended ("unavailable": not cleanly), once it did (`end`)
        super().__init__(hub, endpoint, hub.messenger)
        # its process's clock read (on its thread), not ticked: a reading is no event, and
        # the histories of runs without a second server stay as they were
        self.stamp = max(CLOCK.last, from_seconds(CLOCK.wall()))
        # its side as it began to serve (`Sided`, the `majority` strategy): every live
        # process is a member here; those its process hears are on its side
        live = [one.pid for one in hub.sched.processes if one.alive]
        self.members = len(live)
        self.side = sum(not hub._divided(pid, process.pid) for pid in live)

    @property
    def who(self) -> str:
        """Its process: the simulated pid."""
        return str(self.process.pid)

    @property
    def rank(self) -> tuple[int, int]:
        """Its place in rule 22's order (`resolve.Sided.rank`: the pid for a tie)."""
        return (self.stamp, self.process.pid)


class _SimulatedHub(_Hub):
    """The hub of a `SimulatedNetwork`: links per sending process, wires, partitions."""

    def __init__(self, messenger: Messenger) -> None:
        super().__init__(messenger)
        assert isinstance(messenger, SimulatedNetwork)
        self.sched: Scheduler = running_scheduler()
        self.delay = messenger.delay
        self.network = messenger
        self._links: dict[tuple[int, str], _Link] = {}  # (sender's pid, name) -> its link
        self._aside: list[_Link] = []  # links left for another server of their name, open
        self._servers: dict[str, list[_Server]] = {}  # name -> its servers: one a side
        self._side: frozenset[int] | None = None  # the pids cut off the others
        self._cut_at = 0.0  # (virtual seconds) when the partition began
        self._cut_last = 0  # the last pid made before it (later ones: their parent's side)
        self._beyond_of: dict[int, bool] = {}  # pid -> on the cut-off side (found once)
        self._cut_judged = False  # the names across were judged once the lease passed
        self._silent: set[str] = set()  # names served by a process silent past its lease
        self._deaf: set[int] = set()  # pids that cannot hear their router (`deafen`)
        self._awaiting: dict[str, int] = {}  # name gone unclean -> its speaker's pid (rule 19)
        # a name served across a cut past the lease -> its speaker's pid and the pids on
        # the speaker's side that await it (lost for them if the speaker goes)
        self._awaited_across: dict[str, tuple[int, list[int]]] = {}
        self._watched: set[int] = set()  # speakers whose end is watched (`at_end`)
        self._ending: set[int] = set()  # servers' processes whose end is watched
        # the faults armed (`SimulatedNetwork`'s methods of the same names)
        self.duplicate: dict[str, tuple[float, list[int]]] = {}  # name -> (until, count)
        self.kill_answer: dict[int, Callable[[], object]] = {}  # pid -> what to run first
        self.serving: dict[str, Callable[[int], object]] = {}  # name -> what to run
        if messenger.lease is not None:
            sim.Thread(
                self.sched, target=self._presence, name="rr-sim-presence", daemon=True
            ).start()

    def _sender(self) -> Process:
        task = self.sched.current_or_none()
        return self.sched.root if task is None else task.process

    def served(self, endpoint: Endpoint) -> _Server:
        # its process set before `serve` publishes it: a thread that runs while it
        # starts (a seam may switch) and routes to the name finds it whole
        process = self._sender()
        return _Server(self, endpoint, process, self._speaker(endpoint.name, process))

    def _speaker(self, name: str, process: Process) -> int | None:
        """Who speaks for `name` in `process` if it dies (rule 19): its `supervised_by`, else itself
        while `DIRECTORY.restart_expected(name)`, else nobody."""
        member = self.network.address.attach()
        supervisor: int | None = getattr(member, "supervisor", None)
        if supervisor is not None:
            return supervisor
        return process.pid if DIRECTORY.restart_expected(name) else None

    def serve(self, endpoint: Endpoint) -> _Served:
        """Serve `endpoint` in its process (one its own process served is let go first).

        Raises:
            DuplicateNameError: another process on its side of a partition serves that name.
            RegistrarUnavailableError: the one that serves it is silent past its lease, or this
                process is deaf (as Zenoh's `wait_turn` cannot tell the name is free).
            RegistrarStoppedError: the network was closed.
        """
        name = endpoint.name
        if self._sender().pid in self._deaf:  # (`Presence.wait_turn` of a process whose
            # router went: no full answer of who serves it, so it does not serve it)
            raise RegistrarUnavailableError(
                f"cannot tell whether another process of system {self.system!r} serves a "
                f"registrar named {name!r}, so this process does not serve it: this "
                f"process's router does not answer: this process has no link to the rest "
                f"of the system and hears nothing of it"
            )
        server = self.served(endpoint)
        process = server.process
        with self._lock:
            before = self._servers.get(name, [])
            near = [other for other in before if not self._across(other, process)]
            rival = next((other for other in near if other.process is not process), None)
            if not self.closed and rival is None:
                self._servers[name] = [*(o for o in before if o not in near), server]
                self._served[name] = server
                self._gone.pop(name, None)
                self._awaiting.pop(name, None)
                self._awaited_across.pop(name, None)  # (served again: no longer awaited)
        if self.closed or rival is not None:
            server.inbox.close(timeout=0)
            if self.closed:
                raise RegistrarStoppedError("the in-memory network was closed")
            assert rival is not None
            if name in self._silent:
                raise RegistrarUnavailableError(
                    f"registrar {name!r} is served by process {rival.process.pid}, silent "
                    f"past its lease: not lost (it may run again), so process "
                    f"{process.pid} does not serve that name"
                )
            raise self.duplicate_error(name, f"process {rival.process.pid}")
        for old in near:
            self.end(old, "unavailable")
        if process.pid not in self._ending:  # (the kernel's part: its end ends them)
            self._ending.add(process.pid)
            process.at_end.append(functools.partial(self._ended, process))
        fire = self.serving.pop(name, None)
        if fire is not None:
            fire(server.process.pid)
        return server

    def _ended(self, process: Process) -> None:
        """`process` ended: what it still served ends (a manager's carrier cut it first)."""
        for servers in list(self._servers.values()):
            for server in servers:
                if server.process is process:
                    self.end(server, "unavailable")

    def _across(self, server: _Server, process: Process) -> bool:
        """Whether the partition, or a deaf process, divides `process` from `server`'s."""
        return self._divided(server.process.pid, process.pid)

    def _divided(self, one: int, other: int) -> bool:
        """Whether processes `one` and `other` cannot hear each other: the partition
        divides them, or one of them cannot hear its router (`deafen`)."""
        if one == other:
            return False
        if one in self._deaf or other in self._deaf:
            return True
        return self._side is not None and self._beyond(one) != self._beyond(other)

    def _beyond(self, pid: int) -> bool:
        """Whether process `pid` is on the cut-off side of the partition: one of its
        pids, or made after the cut by a process there (a restart by a supervisor
        beyond the cut stays beyond it, as a host's processes do)."""
        side = self._side
        assert side is not None
        if pid in side or pid <= self._cut_last:
            return pid in side
        found = self._beyond_of.get(pid)
        if found is None:
            process = self._process(pid)
            parent = None if process is None else process.parent
            found = self._beyond_of[pid] = parent is not None and self._beyond(parent)
        return found

    def route(self, name: str, server: Sided | None = None) -> Route:
        """The link from this process to the server of `name` it reaches: the one on its
        side of a partition; of two it sees (after a heal), the one kept (rule 22). To
        `server` (the other one, `Messenger._claim`): a `_Told`, whatever is seen."""
        if server is not None:
            return _Told(name, server.who)
        servers = [one for one in self._servers.get(name, []) if not (one.cut or one.gone)]
        if not servers:
            raise self.gone_error(name)
        sender = self._sender()
        near = [one for one in servers if not self._across(one, sender)]
        served = self._kept(name, near or servers)
        assert served is not None
        link = self._links.get((sender.pid, name))
        if link is None or link.served is not served or link.closed:
            if link is not None and not link.closed:  # (to the other server of the name,
                self._aside.append(link)  # which serves on: what waits on it waits on)
            link = self._links[sender.pid, name] = _Link(self, sender, served)
            until, count = self.duplicate.get(name, (-1.0, None))
            link.twice = count if self.sched.now < until else None
        if name in self._silent:
            raise RegistrarUnavailableError(
                f"registrar {name!r} cannot be reached (its process is silent past its lease)"
            )
        if sender.pid in self._deaf:
            raise RegistrarUnavailableError(
                f"registrar {name!r} cannot be reached (this process cannot hear its router: "
                f"it hears nothing of the rest of the system)"
            )
        if served.process.pid in self._deaf:
            raise RegistrarUnavailableError(
                f"registrar {name!r} cannot be reached (its process cannot hear its router)"
            )
        if self.apart(link):
            raise RegistrarUnavailableError(
                f"registrar {name!r} cannot be reached (the network between processes "
                f"{sender.pid} and {served.process.pid} is cut)"
            )
        return link

    def _kept(self, name: str, servers: list[_Server]) -> _Server | None:
        """The server of `name` kept of `servers` (rule 22, by the network's `resolve`)."""
        return self.network.resolution.kept(name, servers)

    def apart(self, link: _Link) -> bool:
        """Whether `link` crosses the partition, leads to a process silent past its
        lease, or from or to a process that cannot hear its router."""
        if link.served.endpoint.name in self._silent:
            return True
        return self._divided(link.sender.pid, served_by(link.served).pid)

    def answer(self, process: Any, data: bytes, on_lost: Lost | None) -> bool:
        if self.closed:
            return False
        link: _Link = process
        return link.answer(data, on_lost)

    def end(self, served: _Served, how: str, error: RrError | None = None) -> None:
        if served.gone:
            return
        name = served.name
        if isinstance(served, _Server):
            served.how = how  # (`_served_elsewhere` reads it)
        # (first, and without a lock: no choice point lets a `serve` see it served)
        rest = [one for one in self._servers.pop(name, []) if one is not served]
        if rest:
            self._servers[name] = rest
        super().end(served, how, error)
        rest = self._servers.get(name, [])
        if rest and not self.closed:  # (served on: by the one beyond a cut, kept, or new)
            self._served[name] = rest[-1]
            self._gone.pop(name, None)
        failed = error or self.gone_error(name)
        for link in self._every_link():
            if link.served is served and not link.closed:
                link.close(failed)
        self._aside = [link for link in self._aside if not link.closed]
        if how == "unavailable" and not rest and not self.closed and isinstance(served, _Server):
            self._judge(name, served)  # (its process died, or it crashed: not stopped)

    def leave(self) -> None:
        """The network closes: every server of a name ends, the one beyond a cut too
        (the hub's own `leave` ends the newest of each name)."""
        super().leave()
        error = RegistrarStoppedError("the in-memory network was closed")
        while self._servers:
            servers = next(iter(self._servers.values()))
            self.end(servers[-1], "stopped", error)

    def _every_link(self) -> list[_Link]:
        return [*self._links.values(), *self._aside]

    def cut_connections(self, pid: int) -> int:
        cut = 0
        for link in self._every_link():
            if link.closed or pid not in (link.sender.pid, served_by(link.served).pid):
                continue
            link.sever()
            cut += 1
        return cut

    def answering(self, process: Process) -> None:
        """`process` answers a call (not with an error): a `kill_at_answer` fires here."""
        fire = self.kill_answer.pop(process.pid, None)
        if fire is not None:
            fire()
            self.sched.end(process, -9)  # (SIGKILL; from its own thread: never returns)

    def partition(self, side: frozenset[int]) -> None:
        self._side = side
        self._cut_at = self.sched.now
        self._cut_last = max(process.pid for process in self.sched.processes)
        self._beyond_of = {}
        self._cut_judged = False
        self._awaited_across = {}
        for link in self._every_link():
            if not link.closed and self.apart(link):
                name = link.served.endpoint.name
                link.close(RegistrarUnavailableError(f"registrar {name!r} cannot be reached (cut)"))

    def heal(self, unheard: frozenset[int] = frozenset()) -> None:
        if self._side is None:
            return
        side = frozenset(one.pid for one in self.sched.processes if self._beyond(one.pid))
        self._side = None
        self._awaited_across = {}
        self._rejoin(side, unheard)

    def deafen(self, pid: int) -> None:
        """Process `pid` no longer hears its router (see `SimulatedNetwork.deafen`)."""
        if pid in self._deaf:
            return
        self._deaf.add(pid)
        logger.warning(
            "system %s: process %s lost its link to its router: it hears nothing of the "
            "rest of the system, and serves no registrar from now on (rule 22)",
            self.system,
            pid,
        )
        error = RegistrarUnavailableError(
            f"process {pid} cannot hear its router: the registrar cannot be reached"
        )
        for link in self._every_link():
            if not link.closed and pid in (link.sender.pid, served_by(link.served).pid):
                link.close(error)
        mine: list[tuple[str, _Server]] = []  # what it serves, gone for the others
        theirs: list[str] = []  # what the others serve, gone for it (every token went)
        for name, servers in self._servers.items():
            one = self._kept(name, servers)
            if one is not None and one.process.pid == pid:
                mine.append((name, one))
            elif one is not None and name not in self._silent:
                theirs.append(name)
        for name, server in mine:
            self._judge(name, server)
        self._speakers_gone()
        process = self._process(pid)
        if theirs and process is not None and process.alive:
            self._tell("lost", theirs, [process])

    def hear(self, pid: int) -> None:
        """Process `pid` hears its router again: a healed link for it."""
        if pid in self._deaf:
            self._deaf.discard(pid)
            self._rejoin(frozenset({pid}))

    def _rejoin(self, side: frozenset[int], unheard: frozenset[int] = frozenset()) -> None:
        """The processes of `side` and the others hear each other again: a name served
        on both is decided (rule 22), and each process hears every name across that it
        hears now as reachable again (rule 20)."""
        pids: dict[str, int] = {}  # name -> the pid of its server kept
        for name, servers in list(self._servers.items()):
            one = self._kept(name, servers)
            if one is None:
                continue
            pids[name] = one.process.pid
            if len(servers) > 1 and not self._apart_servers(servers):
                self._two_servers(name, servers, unheard)

        def across(process: Process, name: str) -> bool:
            there = pids[name]
            return (there in side) != (process.pid in side) and not self._divided(
                there, process.pid
            )

        self._tell_reachable(list(pids), across)

    def _apart_servers(self, servers: list[_Server]) -> bool:
        """Whether two of `servers` still cannot hear each other."""
        return any(
            self._divided(one.process.pid, other.process.pid)
            for one in servers
            for other in servers
        )

    # -- lost for good (rule 19) ------------------------------------------------------

    def _judge(self, name: str, server: _Server) -> None:
        """`name`'s server went unclean and nobody serves it on: lost, or awaited while its speaker
        lives."""
        speaker = server.speaker
        if speaker is not None and speaker != server.process.pid and self._heard(speaker):
            self._awaiting[name] = speaker
            self._watch(speaker)
            return
        self._awaiting.pop(name, None)
        self._lost(name, server.process.pid)

    def _judge_across(self) -> None:
        """A partition outlasted the lease: each side hears the other's names lost or awaited (rule
        19)."""
        for process in self.sched.processes:
            if not process.alive or process.pid in self._deaf:
                continue
            lost = []
            for name, servers in self._servers.items():
                if name in self._silent or any(
                    not self._divided(one.process.pid, process.pid) for one in servers
                ):
                    continue  # (judged at its silence, or served on its side)
                one = self._kept(name, servers)
                speaker = None if one is None else one.speaker
                if one is None or speaker is None or speaker == one.process.pid:
                    lost.append(name)  # (nobody speaks for it)
                elif self._heard(speaker) and not self._divided(speaker, process.pid):
                    awaiting = self._awaited_across.setdefault(name, (speaker, []))[1]
                    awaiting.append(process.pid)  # (its supervisor, on its side, may
                    self._watch(speaker)  # restart it: lost if that one goes)
                else:
                    lost.append(name)
            if lost:
                self._tell("lost", lost, [process])

    def _process(self, pid: int) -> Process | None:
        return next((one for one in self.sched.processes if one.pid == pid), None)

    def _heard(self, pid: int) -> bool:
        """Whether process `pid` is heard on the network: alive, not silent past a lease,
        hearing its router."""
        process = self._process(pid)
        if process is None or not process.alive or pid in self._deaf:
            return False
        lease = self.network.lease
        return not (
            lease is not None and process.stopped and self.sched.now - process.stopped_at > lease
        )

    def _watch(self, pid: int) -> None:
        """Judge the names `pid` speaks for again when its process ends."""
        process = self._process(pid)
        if process is not None and pid not in self._watched:
            self._watched.add(pid)
            process.at_end.append(self._speakers_gone)

    def _speakers_gone(self) -> None:
        """The names awaited on a speaker no longer heard are lost."""
        for name, speaker in list(self._awaiting.items()):
            if not self._heard(speaker):
                del self._awaiting[name]
                self._lost(name, None)
        for name, (speaker, pids) in list(self._awaited_across.items()):
            if not self._heard(speaker):  # (awaited beside it, across a cut)
                del self._awaited_across[name]
                hearers = [one for one in self.sched.processes if one.pid in pids and one.alive]
                self._tell("lost", [name], hearers)

    def _lost(self, name: str, pid: int | None) -> None:
        """Every process that hears the network, but `pid`, hears `name` is lost."""
        if self.closed:
            return
        hearers = [
            process
            for process in self.sched.processes
            if process.alive and process.pid != pid and process.pid not in self._deaf
        ]
        self._tell("lost", [name], hearers)

    def _two_servers(
        self, name: str, servers: list[_Server], unheard: frozenset[int] = frozenset()
    ) -> None:
        """A name served on both sides of the healed cut: each of its processes (but those
        of `unheard`) hears of the others, on a thread of its own, as Zenoh's presence
        tells its carrier; the messenger there decides whether its own gives way (rule 22)."""
        for server in servers:
            if server.process.pid in unheard:
                continue
            rivals = [other for other in servers if other is not server]
            self._on_thread(server.process, "rival", self._served_elsewhere, name, rivals)

    def send(self, route: Route, data: bytes) -> None:
        """A `_Told`'s `Claim` (rule 22): the kept server's process tells the other server
        of the name's process (`route.who`, which may not hear it), as Zenoh's carrier puts
        it on the name's key: on a thread of that process, unless the network between is
        cut; sent nowhere else. Any other route: `_Hub.send`."""
        if not isinstance(route, _Told):
            super().send(route, data)
            return
        sender, name = self._sender(), route.name
        for one in self._servers.get(name, []):
            there = one.process
            if one.who == route.who and there.alive and not self._divided(sender.pid, there.pid):
                claim = pickle.loads(split_frame(data)[1])
                self._on_thread(there, "claim", self._claimed, name, claim)
                return

    def _claimed(self, name: str, claim: Claim) -> None:
        """In a process serving `name`: another process's server of it is kept (`Claim`)."""
        member = self.network.address.attach()
        assert isinstance(member, Messenger)
        member.served_elsewhere(name, claim)

    def _served_elsewhere(self, name: str, rivals: list[_Server]) -> None:
        """In a process serving `name`: the others serve it too (rule 22)."""
        member = self.network.address.attach()
        assert isinstance(member, Messenger)
        for rival in rivals:
            member.served_elsewhere(name, rival)
            if rival.how == "unavailable" and not self._servers.get(name) and not self.closed:
                # it died before this process gave way to it, or as it did, when this one
                # still served the name (so its end judged nothing): Zenoh's presence
                # applies its token's end after the yield, and judges it then (rule 19)
                self._judge(name, rival)

    def _presence(self) -> None:
        """Every quarter lease: a stopped process silent past its lease is gone for the
        others; one that runs again is back (as after a heal)."""
        lease = self.network.lease
        assert lease is not None
        sched = self.sched
        while not self.closed:
            sim.sleep(sched, lease / 4)
            back = []
            for name, served in list(self._served.items()):
                process = served_by(served)
                silent = process.stopped and sched.now - process.stopped_at > lease
                if silent and name not in self._silent:
                    self._silent.add(name)
                    error = RegistrarUnavailableError(
                        f"registrar {name!r} cannot be reached (its process is silent past "
                        f"its lease, {lease:g} s)"
                    )
                    for link in self._every_link():
                        if link.served is served and not link.closed:
                            link.close(error)
                    if isinstance(served, _Server) and process.pid not in self._deaf:
                        self._judge(name, served)  # (its tokens went, as for real)
                elif not silent and name in self._silent:
                    self._silent.discard(name)
                    back.append(name)
            self._silent &= set(self._served)
            self._speakers_gone()  # (a speaker silent past its lease: its token went)
            cut = self._side is not None and not self._cut_judged
            if cut and sched.now - self._cut_at > lease:  # (its tokens went)
                self._cut_judged = True
                self._judge_across()
            if back:
                self._tell_reachable(back, lambda process, name: True)

    def _tell_reachable(self, names: list[str], across: Callable[[Process, str], bool]) -> None:
        """Each live process hears the names of `names` it is `across` from as reachable
        again, on a thread of its own."""
        for process in self.sched.processes:
            if not process.alive:
                continue
            heard = [name for name in names if across(process, name)]
            if heard:
                self._tell("reachable", heard, [process])

    def _tell(self, what: str, names: list[str], processes: list[Process]) -> None:
        """Each of `processes` hears `names` are `what` ("lost" for good, rule 19;
        "reachable" again, rule 20), as its carrier tells its messenger: on a thread of
        its own."""
        for process in processes:
            self._on_thread(process, what, self._heard_of, what, names)

    def _on_thread(self, process: Process, kind: str, target: Any, *args: Any) -> None:
        """Run `target(*args)` in `process` on a daemon thread of its own, named
        `rr-<kind>-<pid>`: what a carrier's thread tells its messenger."""
        sim.Thread(
            self.sched,
            target=target,
            args=args,
            name=f"rr-{kind}-{process.pid}",
            daemon=True,
            process=process,
        ).start()

    def _heard_of(self, what: str, names: list[str]) -> None:
        """In a process: its messenger hears `names` are `what` (`Messenger.lost`,
        `Messenger.reachable`)."""
        member = self.network.address.attach()
        assert isinstance(member, Messenger)
        hear = member.lost if what == "lost" else member.reachable
        for name in names:
            hear(name)


SimulatedNetwork._hub_class = _SimulatedHub
