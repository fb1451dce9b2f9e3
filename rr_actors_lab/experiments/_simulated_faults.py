"""The injector of a simulated run: a plan's faults on simulated processes and links.

```
 fault_schedule(plan, S): timed ─► the agenda (a heap of (virtual time, n, action)) ◄─┐
                          `after` ─► Triggered (_agenda.py) ◄─ on_event (the run's    │
                                     subscriber): the n-th match ─► at its due time ───┘
 the thread "rr-simulated-faults": each action at its time, in order
   kill_manager ──────► simulation.kill(pid, SIGKILL)
   hang_manager ──────► SIGSTOP; `for` later SIGCONT (unless it was killed meanwhile)
   cut_connections ───► SimulatedNetwork.cut_connections(pid)
   load_error ────────► Supervisor.run_in(manager, arm_load_error), a thread of its own
   cut, partition ────► SimulatedNetwork.partition of the hosts' processes; `for` s later
                        healed; one at a time
   duplicate_delivery ► SimulatedNetwork.duplicate_first      (plan.SIMULATION_KINDS)
   kill_before_answer ► SimulatedNetwork.kill_at_answer
   kill_before_commit ► run_in(arm_commit_fault): at its registrar's next turn commit,
                        before the write (COMMIT_FAULTS), the longest frame delay, then
                        SIGKILL (what it sent before arrives, as a socket's buffer)
   kill_in_setup ─────► SIGKILL now and inside its restart's setup (SETUP_FAULTS)
   partition_serving ─► SIGKILL; its restart cut off as it serves (on_serve), healed
   split_brain ───────► its process cut off; a second server of its name beyond the cut
                        ("beyond-<n>"); healed `for` s later, not before it serves
                        (_HealOnceServed): rule 22 decides
   deaf_manager ──────► SimulatedNetwork.deafen, `for` s later `hear`
   kill_program ──────► the program's process SIGKILLed (its managers too), started again
                        at once on the same state_dir
   corrupt_backup ────► SIGKILL, then its backup damaged (`_backup_faults.damage`) before
                        its restart; a restart that refuses it (`ChildExited`, on_event):
                        the file quarantined, as the docs tell an operator
 stop ─► hung managers continued, deaf ones hear; what never fired recorded as skipped
 close (after the tree's stop) ─► the supervisors of second servers stop
```

What each kind does: docs/reference/plan.md. Every time is virtual and every choice the
scheduler's, so the same seed injects the same faults at the same instants.
"""

from __future__ import annotations

import contextlib
import functools
import heapq
import itertools
import signal
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import msgspec

import rr_actors as rr
from rr_actors import events, simulation
from rr_actors._core import runtime
from rr_actors_lab.experiments._agenda import FaultLog, Triggered
from rr_actors_lab.experiments._backup_faults import CORRUPT, NOISE_BYTES, REFUSED, damage
from rr_actors_lab.experiments._instrument import (
    COMMIT_FAULTS,
    SETUP_FAULTS,
    arm_commit_fault,
    arm_load_error,
)
from rr_actors_lab.experiments.plan import Plan
from rr_actors_lab.experiments.results import FaultRecord
from rr_actors_lab.experiments.runner import EVENT_QUEUE, _child_spec
from rr_actors_lab.experiments.schedule import ScheduledFault

__all__ = ["Program", "SimulatedFaults"]


class Program(Protocol):
    """The run's program in a simulated process of its own (`simulate._SimulatedProgram`)."""

    pid: int

    def kill(self) -> int:
        """SIGKILL it (its managers' processes with it); its pid."""
        ...

    def start(self) -> rr.Supervisor:
        """Start it again on its `state_dir`; its tree once it serves (raising what the tree
        raised)."""
        ...


RUN_IN_TIMEOUT = 2.0
"""Virtual seconds `load_error` waits for its manager to take the switch (as for real)."""

DUPLICATE_FOR = 1.0
"""Seconds a `duplicate_delivery` without `for` duplicates the first frame of new links."""


class SimulatedFaults:
    """Fires a simulated run's faults on its own simulated thread (see the diagram).

    Args:
        sup: the run's running supervisor.
        plan: the plan (its faults' `for`, `server`, `loads`, `message`).
        network: the run's simulated carrier.
        schedule: the run's fault schedule.
        t0: `runtime.monotonic()` at the workload's start (the schedule's time 0).
        wall_t0: `runtime.wall()` then (events' times are on it).
        on_event: what the run's events go to (a second server's supervisor's too).
        state_dir: where second servers keep their backups (`None`: in memory).
        backups: the tree's state directory (`corrupt_backup`'s files; `None`: in memory).
        hosts: with `[hosts]`, the pid of each other host's process.
        trees: with `[hosts]`, each other host's tree (where its managers' processes are).
        program: the run's program when it runs in a process of its own (`kill_program`).
    """

    def __init__(
        self,
        sup: rr.Supervisor,
        plan: Plan,
        network: simulation.SimulatedNetwork,
        schedule: tuple[ScheduledFault, ...],
        t0: float,
        wall_t0: float,
        *,
        on_event: Callable[[events.Event], None] | None = None,
        state_dir: Path | None = None,
        hosts: dict[str, int] | None = None,
        trees: dict[str, rr.Supervisor] | None = None,
        program: Program | None = None,
        backups: Path | None = None,
    ) -> None:
        self.sup = sup
        self._backups = backups
        self._refused: dict[str, Path] = {}  # manager -> its damaged backup, not refused yet
        self._program = program
        self._restarting = False  # the program was killed and is starting again
        self._hosts = dict(hosts or {})  # another host's name -> the pid of its process
        self._trees = dict(trees or {})  # another host's name -> its tree
        self._cut: str | None = None  # the fault between hosts in force (its target)
        self._on_event = on_event
        self._state_dir = state_dir
        self._beyond: list[tuple[rr.Supervisor, Any]] = []  # second servers' (sup, events)
        self.plan = plan
        self.network = network
        self.t0 = t0
        self.log = FaultLog()
        self._agenda: list[tuple[float, int, Callable[[], None]]] = []
        self._order = itertools.count()
        self._wake = runtime.Condition()
        self._stopped = False
        self._hung: dict[int, str] = {}  # pid -> manager
        self._deaf: set[int] = set()  # pids that do not hear their router now
        self._armed: dict[tuple[int, int], tuple[ScheduledFault, float]] = {}  # not fired yet
        self._due: dict[int, tuple[ScheduledFault, float]] = {}  # on the agenda, by number
        self._open: dict[tuple[int, int], Callable[[], None]] = {}  # recorded once they end
        self._helpers: list[Any] = []  # load errors', split brains', program restarts' threads
        self._triggered = Triggered((f for f in schedule if f.at is None), wall_t0)
        # The timed faults put on the agenda without its lock (no thread sees it yet): a
        # lock taken is a choice point of the scheduler, so that taking it once per
        # injection would make the run before the first one depend on how many come
        # later, and a shorter run (a shrink's cut) would not begin as the longer one.
        for fault in schedule:
            if fault.at is not None:
                n = next(self._order)
                self._due[n] = (fault, fault.at)
                action = functools.partial(self._fire, fault, fault.at)
                self._agenda.append((self.t0 + fault.at, n, action))
        heapq.heapify(self._agenda)
        SETUP_FAULTS.clear()  # (the simulation's alone: nothing arms it in a real run)
        COMMIT_FAULTS.clear()
        self._thread = runtime.Thread(target=self._run, name="rr-simulated-faults", daemon=True)

    @property
    def records(self) -> list[FaultRecord]:
        """Every fault fired or skipped so far."""
        return self.log.records

    def start(self) -> None:
        """Start firing."""
        self._thread.start()

    def on_event(self, event: events.Event) -> None:
        """Look at one event of the run (the subscriber's thread); fire what it triggers."""
        for fault, at in self._triggered.matched(event):
            self._push(fault, at)
        if isinstance(event, events.ChildExited) and CORRUPT in event.reason:
            file = self._refused.pop(event.child, None)
            if file is not None and file.exists():  # (refused: what an operator does)
                rr.quarantine_backup(file)

    def stop(self) -> None:
        """Stop firing; continue hung managers; record what never fired as skipped."""
        with self._wake:
            self._stopped = True
            left, self._agenda = self._agenda, []
            self._wake.notify()
        self._thread.join()
        for thread in self._helpers:
            thread.join()
        for pid in sorted(self._hung):
            simulation.kill(pid, signal.SIGCONT)
        self._hung.clear()
        for key in list(self._open):
            self._close(key)
        self.network.heal()  # (a partition_serving, or a cut between hosts, still on)
        self._cut = None
        for pid in sorted(self._deaf):
            self.network.hear(pid)
        self._deaf.clear()
        for fault, _ in self._armed.values():
            SETUP_FAULTS.pop(fault.target or "", None)
        COMMIT_FAULTS.clear()  # (one run at a time: only its own are armed)
        for fault in self._triggered.take():
            self.log.record(
                fault, None, None, "its trigger did not happen in the run", skipped=True
            )
        dues = sorted((at - self.t0, n) for at, n, _ in left)
        for fault, at in [self._due.pop(n) for _, n in dues if n in self._due]:
            self.log.record(fault, at, None, "due after the run ended", skipped=True)
        for fault, at in self._armed.values():
            self.log.record(fault, at, None, f"armed: {self._aim(fault)} never came", skipped=True)
        self._armed.clear()

    def close(self) -> None:
        """Stop the supervisors of second servers (after the tree's stop: the end of the
        run), once their events are delivered; each, though one before it raised (the
        first error is raised)."""
        beyond, self._beyond = self._beyond, []
        with contextlib.ExitStack() as cleanup:
            for sup, subscription in reversed(beyond):  # (the stack: last in, first out)
                if subscription is not None:
                    cleanup.callback(subscription.close)
                    cleanup.callback(subscription.wait_delivered)
                cleanup.callback(sup.stop)

    # -- the agenda ----------------------------------------------------------------------

    def _push(self, fault: ScheduledFault, at: float) -> None:
        """Fire `fault` at `at` seconds from t0."""
        self._at(self.t0 + at, functools.partial(self._fire, fault, at), (fault, at))

    def _at(
        self, when: float, action: Callable[[], None], fault: tuple[ScheduledFault, float] | None
    ) -> None:
        with self._wake:
            if self._stopped:
                if fault is not None:
                    self.log.record(*fault, None, "due after the run ended", skipped=True)
                return
            n = next(self._order)
            if fault is not None:
                self._due[n] = fault
            heapq.heappush(self._agenda, (when, n, action))
            self._wake.notify()

    def _run(self) -> None:
        while True:
            with self._wake:
                while not self._stopped:
                    if self._agenda and self._agenda[0][0] <= runtime.monotonic():
                        break
                    wait = self._agenda[0][0] - runtime.monotonic() if self._agenda else None
                    self._wake.wait(wait)
                if self._stopped:
                    return
                _, n, action = heapq.heappop(self._agenda)
                self._due.pop(n, None)
            action()

    # -- the faults ----------------------------------------------------------------------

    def _now(self) -> float:
        return runtime.monotonic() - self.t0

    def _fire(self, fault: ScheduledFault, at: float) -> None:
        if fault.kind in ("cut", "partition"):
            self._cut_hosts(fault, at)
        elif self._restarting:  # (its tree is the one of a killed program)
            self.log.record(fault, at, None, "the program was starting again", skipped=True)
        elif fault.kind == "kill_program":
            self._kill_program(fault, at)
        else:
            self._fire_at_manager(fault, at)

    def _fire_at_manager(self, fault: ScheduledFault, at: float) -> None:
        helper = {
            "load_error": (self._load_error, "rr-simulated-load"),
            "split_brain": (self._split_brain, "rr-simulated-split"),
            "kill_before_commit": (self._kill_before_commit, "rr-simulated-commit"),
        }.get(fault.kind)
        if helper is not None:  # (it takes virtual time: a thread of its own)
            target, name = helper
            thread = runtime.Thread(target=target, args=(fault, at), name=name, daemon=True)
            self._helpers.append(thread)
            thread.start()
            return
        assert fault.target is not None
        info = (tree := self._tree(fault.target)).child(fault.target)  # (its host's)
        if info.state != "running":
            detail = f"{fault.target} was not running ({info.state})"
            self.log.record(fault, at, None, detail, skipped=True)
            return
        if info.pid is None:  # a thread manager (reading allows only kill_manager, load_error)
            from rr_actors.testing import crash  # noqa: PLC0415 - as _manager_faults

            crash(tree.run_in(fault.target, lambda registrar: registrar))
            self.log.record(fault, at, self._now(), f"crashed the registrar of {fault.target}")
            return
        pid, kind = info.pid, fault.kind
        done_by = {
            "deaf_manager": self._deafen,
            "duplicate_delivery": self._duplicate,
            "corrupt_backup": self._corrupt_backup,
        }.get(kind)
        if done_by is not None:
            done_by(fault, at, pid)
        elif kind == "kill_manager":
            simulation.kill(pid, signal.SIGKILL)
            self.log.record(fault, at, self._now(), f"SIGKILL pid {pid}")
        elif kind == "hang_manager":
            simulation.kill(pid, signal.SIGSTOP)
            self._hung[pid] = fault.target
            self.log.record(fault, at, self._now(), f"SIGSTOP pid {pid}")
            for_s = self.plan.faults[fault.fault].for_s or 0.0
            self._at(runtime.monotonic() + for_s, functools.partial(self._resume, pid), None)
        elif kind == "cut_connections":
            self.network.cut_connections(pid)
            self.log.record(fault, at, self._now(), f"cut pid {pid}'s connections")
        elif kind == "kill_before_answer":
            self._arm(fault, at)
            self.network.kill_at_answer(pid, functools.partial(self._fired, fault, at, pid))
        elif kind == "kill_in_setup":
            self._arm(fault, at)
            SETUP_FAULTS[fault.target] = functools.partial(self._kill_in_setup, fault, at, pid)
            simulation.kill(pid, signal.SIGKILL)
        elif kind == "partition_serving":
            self._arm(fault, at)
            self.network.on_serve(fault.target, functools.partial(self._partition, fault, at, pid))
            simulation.kill(pid, signal.SIGKILL)
        else:  # (check_simulable refuses the others)
            raise AssertionError(f"fault kind {kind!r} is not simulated")

    def _duplicate(self, fault: ScheduledFault, at: float, pid: int) -> None:
        """Cut its connections; for `for` s each new link to it delivers its first frame twice."""
        assert fault.target is not None
        for_s = self.plan.faults[fault.fault].for_s or DUPLICATE_FOR
        count = self.network.duplicate_first(fault.target, simulation.now() + for_s)
        self.network.cut_connections(pid)
        key = (fault.fault, fault.n)
        self._open[key] = functools.partial(self._duplicated, fault, at, self._now(), pid, count)
        self._at(runtime.monotonic() + for_s, functools.partial(self._close, key), None)

    def _corrupt_backup(self, fault: ScheduledFault, at: float, pid: int) -> None:
        """SIGKILL the target, then damage its backup before its restart (`how`)."""
        assert fault.target is not None
        how = self.plan.faults[fault.fault].how
        simulation.kill(pid, signal.SIGKILL)
        file = None if self._backups is None else self._backups / f"{fault.target}.db"
        if file is None or not file.is_file():
            self.log.record(fault, at, self._now(), f"SIGKILL pid {pid}; no backup to damage")
            return
        what = damage(file, how, runtime.urandom(NOISE_BYTES))
        if how in REFUSED:
            self._refused[fault.target] = file
        self.log.record(fault, at, self._now(), f"SIGKILL pid {pid}, then {what}")

    def _tree(self, manager: str) -> rr.Supervisor:
        """The tree `manager` is a child of: its host's (`[hosts]`), else the run's."""
        return self._trees.get(self.plan.host_of(manager) or "", self.sup)

    def _cut_hosts(self, fault: ScheduledFault, at: float) -> None:
        """`cut` or `partition`: one side's hosts' processes cut off (`SimulatedNetwork.partition`),
        healed `for` s later; one due while another is in force is skipped (one partition at
        most)."""
        plan = self.plan.faults[fault.fault]
        assert self.plan.hosts is not None
        names, home = self.plan.hosts.names, self.plan.hosts.home
        for_s = plan.for_s or 0.0
        if fault.kind == "cut":
            assert plan.link is not None
            one, other = plan.link
            side, target = {one, other} - {home}, f"{one}-{other}"  # (two hosts only)
            what = f"link {one}-{other} down for {for_s:g} s"
        else:
            side, target = set(plan.hosts), "+".join(plan.hosts)
            what = f"{target} cut from the other hosts for {for_s:g} s"
        if home in side:  # (the other side: the run's own process is the simulation's root)
            side = set(names) - side
        if self._cut is not None:
            detail = (
                f"{self._cut} was still cut (the simulated network holds one partition at a time)"
            )
            self.log.record(fault, at, None, detail, target=target, skipped=True)
            return
        self._cut = target
        self.network.partition(sorted(self._hosts[name] for name in side), started_by=True)
        self.log.record(fault, at, self._now(), what, target=target)
        self._at(runtime.monotonic() + for_s, self._heal_hosts, None)

    def _heal_hosts(self) -> None:
        """The fault between hosts in force is over: every host hears the others again."""
        if self._cut is not None:
            self._cut = None
            self.network.heal()

    def _duplicated(
        self, fault: ScheduledFault, at: float, injected: float, pid: int, count: list[int]
    ) -> None:
        """A duplicate_delivery's `for` is over (or the run): record it, with its count."""
        detail = f"cut pid {pid}'s connections; {count[0]} first frame(s) of new links twice"
        self.log.record(fault, at, injected, detail)

    def _close(self, key: tuple[int, int]) -> None:
        record = self._open.pop(key, None)
        if record is not None:
            record()

    def _resume(self, pid: int) -> None:
        if self._hung.pop(pid, None) is not None:
            simulation.kill(pid, signal.SIGCONT)  # (a process killed meanwhile: left alone)

    def _deafen(self, fault: ScheduledFault, at: float, pid: int) -> None:
        """Its process cannot hear its router; `for` s later it hears again."""
        for_s = self.plan.faults[fault.fault].for_s or 0.0
        self.network.deafen(pid)
        self._deaf.add(pid)
        self.log.record(
            fault, at, self._now(), f"pid {pid} cannot hear its router, for {for_s:g} s"
        )
        self._at(runtime.monotonic() + for_s, functools.partial(self._hear, pid), None)

    def _hear(self, pid: int) -> None:
        if pid in self._deaf:
            self._deaf.discard(pid)
            self.network.hear(pid)

    def _aim(self, fault: ScheduledFault) -> str:
        return {
            "kill_before_answer": f"an answer of {fault.target}",
            "kill_before_commit": f"a commit of {fault.target}",
            "kill_in_setup": f"a restart of {fault.target}",
            "partition_serving": f"{fault.target} serving again",
        }[fault.kind]

    def _arm(self, fault: ScheduledFault, at: float) -> None:
        self._armed[fault.fault, fault.n] = (fault, at)

    def _fired(self, fault: ScheduledFault, at: float, pid: int, detail: str = "") -> None:
        """An armed fault reached its point: record it (the struck process's thread)."""
        if self._armed.pop((fault.fault, fault.n), None) is None:
            return
        detail = detail or f"SIGKILL pid {pid} at its answer (after the commit)"
        self.log.record(fault, at, self._now(), detail)

    def _kill_before_commit(self, fault: ScheduledFault, at: float) -> None:
        """Arm a SIGKILL at the target's registrar's next turn commit (a thread of its own:
        arming asks the manager, `run_in`, which takes virtual time)."""
        assert fault.target is not None
        tree = self._tree(fault.target)
        info = tree.child(fault.target)
        if info.state != "running" or info.pid is None:
            detail = f"{fault.target} was not running ({info.state})"
            self.log.record(fault, at, None, detail, skipped=True)
            return
        pid = info.pid
        self._arm(fault, at)
        COMMIT_FAULTS[pid] = functools.partial(self._kill_at_commit, fault, at, pid)
        try:
            tree.run_in(fault.target, arm_commit_fault, timeout=RUN_IN_TIMEOUT)
        except rr.RrError as exc:  # (it died meanwhile, of this fault or another)
            COMMIT_FAULTS.pop(pid, None)
            if self._armed.pop((fault.fault, fault.n), None) is not None:
                self.log.record(fault, at, None, f"{fault.target}: {exc}", skipped=True)

    def _kill_at_commit(self, fault: ScheduledFault, at: float, pid: int) -> None:
        """At a turn's commit, before its write (the registrar's actor thread): the frames
        the process sent before reach their receivers (the longest delay of a frame, as a
        killed process's socket buffers are still read), then SIGKILL it there."""
        detail = (
            f"SIGKILL pid {pid} at a commit of its registrar's turn, before the write "
            f"(what it had sent arrived first)"
        )
        self._fired(fault, at, pid, detail)
        simulation.sleep(self.network.delay[1])
        simulation.kill(pid, signal.SIGKILL)  # (never returns)

    def _kill_in_setup(self, fault: ScheduledFault, at: float, killed: int) -> None:
        """In the restarted manager's setup (its own thread): SIGKILL it there."""
        pid = simulation.pid()
        detail = f"SIGKILL pid {killed}, then pid {pid} inside its setup"
        self._fired(fault, at, pid, detail)
        simulation.kill(pid, signal.SIGKILL)  # (never returns)

    def _partition(self, fault: ScheduledFault, at: float, killed: int, pid: int) -> None:
        """The restarted manager serves (its thread): cut it off, heal `for` s later."""
        for_s = self.plan.faults[fault.fault].for_s or 0.0
        self.network.partition([pid])
        detail = f"SIGKILL pid {killed}; pid {pid} cut off as it serves, for {for_s:g} s"
        self._fired(fault, at, pid, detail)
        self._at(runtime.monotonic() + for_s, self.network.heal, None)

    def _split_brain(self, fault: ScheduledFault, at: float) -> None:
        """Cut the target's process off the others, start a second server of its name
        beyond the cut, heal `for` s after the cut (a thread of its own: the start takes
        virtual time)."""
        assert fault.target is not None
        for_s = self.plan.faults[fault.fault].for_s or 0.0
        host = self.plan.host_of(fault.target)
        if host is not None:  # (`[hosts]`: its whole host cut off; the second on the run's)
            if self._cut is not None:
                detail = f"{self._cut} was still cut (one partition at a time)"
                self.log.record(fault, at, None, detail, skipped=True)
                return
            self._cut = host
            pid = self._hosts[host]
            self.network.partition([pid], started_by=True)
            heal = _HealOnceServed(self._heal_hosts)
            cut = f"host {host}"
        else:
            info = self.sup.child(fault.target)
            if info.state != "running" or info.pid is None:
                detail = f"{fault.target} was not running ({info.state})"
                self.log.record(fault, at, None, detail, skipped=True)
                return
            pid = info.pid
            self.network.partition([pid])
            heal = _HealOnceServed(self.network.heal)
            cut = f"pid {pid}"
        injected = self._now()
        self._at(runtime.monotonic() + for_s, heal.due, None)
        [manager] = [m for m in self.plan.managers() if m.name == fault.target]
        name = f"beyond-{len(self._beyond) + 1}"
        state = None if self._state_dir is None else self._state_dir / name
        beyond = rr.Supervisor(
            _child_spec(msgspec.structs.replace(manager, restart="temporary"), self.plan.base_dir),
            state_dir=state,
            network=self.network,
            name=name,
        )
        on_event = self._on_event
        subscription = None if on_event is None else beyond.subscribe(on_event, maxsize=EVENT_QUEUE)
        self._beyond.append((beyond, subscription))
        try:
            beyond.start()
        except rr.RrError as exc:
            detail = f"cut {cut} off; a second {fault.target} did not start: {exc}"
            self.log.record(fault, at, injected, detail)
            heal.served()
            return
        second = beyond.child(fault.target).pid
        detail = (
            f"cut {cut} off, for {for_s:g} s; a second {fault.target} serves beyond "
            f"the cut (pid {second}, supervisor {name})"
        )
        if heal.overdue:
            detail += (
                f"; healed as it served, {self._now() - injected:g} s after the cut (its "
                f"start outlasted the {for_s:g} s)"
            )
        self.log.record(fault, at, injected, detail)
        heal.served()

    def _kill_program(self, fault: ScheduledFault, at: float) -> None:
        """SIGKILL the run's program (its managers' processes die with it), then start it
        again on the same `state_dir` on a thread of its own (its start takes virtual
        time; the manager faults due meanwhile are skipped, saying so)."""
        assert self._program is not None  # (`simulate` runs such a plan's program so)
        killed = self._program.kill()
        self._restarting = True
        thread = runtime.Thread(
            target=self._start_program,
            args=(fault, at, self._now(), killed),
            name="rr-simulated-program",
            daemon=True,
        )
        self._helpers.append(thread)
        thread.start()

    def _start_program(
        self, fault: ScheduledFault, at: float, injected: float, killed: int
    ) -> None:
        assert self._program is not None
        try:
            self.sup = self._program.start()
        except Exception as exc:  # noqa: BLE001 - recorded; the run's next ask raises
            detail = f"SIGKILL pid {killed} (the program); it did not start again: {exc}"
        else:
            detail = (
                f"SIGKILL pid {killed} (the program: its tree, its managers' processes and "
                f"its clients); started again as pid {self._program.pid} on its state_dir"
            )
            self._restarting = False
        self.log.record(fault, at, injected, detail)

    def _load_error(self, fault: ScheduledFault, at: float) -> None:
        assert fault.target is not None
        plan = self.plan.faults[fault.fault]
        arm = functools.partial(
            arm_load_error, fault.target, plan.server, plan.loads, plan.for_s, plan.message
        )
        try:
            self._tree(fault.target).run_in(fault.target, arm, timeout=RUN_IN_TIMEOUT)
        except rr.RrError as exc:
            self.log.record(fault, at, None, f"{fault.target}: {exc}", skipped=True)
            return
        what = f"for {plan.for_s:g} s" if plan.for_s is not None else f"{plan.loads} load(s)"
        server = f"/{plan.server}" if plan.server else ""
        self.log.record(fault, at, self._now(), f"loads of {fault.target}{server} raise, {what}")


class _HealOnceServed:
    """A `split_brain`'s heal: due `for` s after the cut and not before the second server serves
    (or failed to start). Its flags need no lock (one OS thread; a lock would be a choice point)."""

    def __init__(self, heal: Callable[[], None]) -> None:
        self.heal = heal
        self.started = False
        self.overdue = False  # its time came before the second server served

    def due(self) -> None:
        """Its time came (the agenda's thread)."""
        if self.started:
            self.heal()
        else:
            self.overdue = True

    def served(self) -> None:
        """The second server serves, or did not start (the fault's own thread)."""
        self.started = True
        if self.overdue:
            self.heal()
