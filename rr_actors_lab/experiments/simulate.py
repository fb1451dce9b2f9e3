"""A plan run on the simulation: its tree, workload and faults in virtual time, one seed a run.

```
 simulate(plan, seeds) ─► per seed: run_seed(plan, seed)
   simulation.run(world, seed=S) ─ one OS thread, greenlets, a virtual clock ─────┐
     world(): SimulatedNetwork; build_tree (the runner's, managers simulated);     │
              subscribe ─► _EventLog; sup.start(); other hosts (_SimulatedHost);   │
              the Clients; the injector (fault_schedule(plan, S), `after` ones);  │
              sleep(duration); faults stop; settle; flush; sup.stop()             │
   ◄── the events, the fault records, t0 ◄────────────────────────────────────────┘
   history = events.jsonl's text (`at` in virtual seconds, `seed` = S) + fault lines
   hash = sha256(history); verdict = check.check(check.numbered(events))
 ◄── SimulatedRun(seed, hash, verdict, findings, history, ...)
```

The same seed gives the same history byte for byte, in any process started with the same
`PYTHONHASHSEED` (`rr-actors experiment --simulate` runs under `PYTHONHASHSEED=0`).
Simulated: the manager faults, the kinds only a simulation can aim (`plan.SIMULATION_KINDS`),
`[compare]` (its first value), `[hosts]` (each other host a simulated process, `cut` and
`partition` on the simulated network) and `kill_program`; what is not simulated is refused
with a `PlanError` (`check_simulable`), never skipped silently.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import functools
import gc
import hashlib
import json
import os
import shutil
import signal
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import rr_actors as rr
from rr_actors import events
from rr_actors._core import runtime
from rr_actors._store import read_backup
from rr_actors._transport.resolve import RESOLVE_STRATEGIES
from rr_actors.config import Steps
from rr_actors.errors import CatalogCorruptError, ConfigError
from rr_actors.events.kinds import set_host
from rr_actors.events.lines import to_lines
from rr_actors_lab.experiments import _backup_faults, check
from rr_actors_lab.experiments.plan import SIMULATION_KINDS, Plan, PlanError
from rr_actors_lab.experiments.reading import import_object
from rr_actors_lab.experiments.results import FaultRecord
from rr_actors_lab.experiments.runner import (
    EVENT_QUEUE,
    _EventLog,
    build_tree,
    count_entries,
    fault_line,
    wait_all_serving,
)
from rr_actors_lab.experiments.schedule import fault_schedule
from rr_actors_lab.experiments.workload import Client

if TYPE_CHECKING:
    from rr_actors import simulation
    from rr_actors_lab.experiments._simulated_faults import SimulatedFaults

__all__ = [
    "SIMULATED_KINDS",
    "SimulatedRun",
    "check_simulable",
    "history_hash",
    "run_seed",
    "scratch_parent",
    "simulate",
]

SIMULATED_KINDS = frozenset(
    {"kill_manager", "hang_manager", "cut_connections", "load_error", "cut", "partition"}
    | SIMULATION_KINDS
)
"""The fault kinds a simulated run injects (`_simulated_faults.py`; the others: `PlanError`)."""

NOT_SIMULATED = {
    "kill_resource": "a resource's own OS process (a program the mission's ERM starts) is "
    "not a simulated process",
    "freeze": "it stops a host's Zenoh router process, and the simulated hosts have no "
    "router (their processes reach each other on the simulated network)",
    "kill_router": "it kills a host's Zenoh router process, and the simulated hosts have no "
    "router (their processes reach each other on the simulated network)",
}
"""Why a fault kind outside `SIMULATED_KINDS` is not simulated."""

NOT_WITH_HOSTS = {
    "partition_serving": "it cuts its manager off with the simulated network's one "
    "partition, which the plan's cuts between hosts use",
    "kill_program": "the run's own host's part is the simulation's root process there, "
    "which cannot be killed",
}
"""Why a fault kind is not simulated in a plan with `[hosts]`."""

NOT_SIMULATED_SETUPS = {
    "rr_actors_lab.mission.managers:erm_setup": "the mission's ERM starts real OS programs and "
    "watches them from real threads, which a simulation can neither schedule nor kill",
}
"""Setups a simulated run refuses, and why (a setup is user code: these are the shipped
ones known to start real processes or threads)."""

RUN = 1
"""The `run` of every line of a simulated run's history (one run a seed)."""

CRASH_LINE = "Crashed"
"""The `type` of a crashed run's last history line: the exception its system raised
(`error_type`, `message`), when (`virtual_s`) and at which step of the scheduler."""

PREEMPT = 0.05
"""The probability that a simulated thread yields at a choice point (`simulation.run`)."""

RAM_DIR = "/dev/shm"  # noqa: S108 - a private folder is made in it (mkdtemp)
"""Where a run's folder (its managers' SQLite backups) is made: tmpfs if there is one and
`TMPDIR` does not choose another (a simulated kill keeps the files anyway)."""


SCRATCH = "<run>"
"""What a history says for its run's folder (random: naming it would make each replay differ)."""


@dataclasses.dataclass(frozen=True)
class SimulatedRun:
    """One seed of a plan on the simulation: its history, hash and verdict.

    Attributes:
        seed: the seed.
        hash: the SHA-256 of `history` (hex): the same for the same plan and seed.
        verdict: `check`'s verdict: `"held"`, `"violated"`, `"unverifiable"`; or `"crashed"`:
            the system raised once it served (a `findings` line names the exception, its
            virtual time and step; the history ends with a `CRASH_LINE` line).
        violations: how many findings are violations.
        unverifiable: how many findings are unverifiable.
        findings: the verdict's lines (`check.format_verdict`, without its first).
        history: the run's `events.jsonl` text (its events, then its fault lines).
        events: how many events it recorded.
        faults: how many faults it injected (skipped ones not counted).
        calls_ok: the workload's calls answered.
        calls_failed: the workload's calls that failed.
        entries_left: rows left in the catalogs at the end (settled).
        virtual_s: the virtual seconds the run took, setup and shutdown included.
        cpu_s: the CPU seconds it took (not part of the history).
        errors: exceptions that ended simulated threads (`name: Type: message`).
    """

    seed: int
    hash: str
    verdict: str
    violations: int
    unverifiable: int
    findings: tuple[str, ...]
    history: str = dataclasses.field(repr=False)
    events: int
    faults: int
    calls_ok: int
    calls_failed: int
    entries_left: int
    virtual_s: float
    cpu_s: float
    errors: tuple[str, ...]


def check_simulable(plan: Plan) -> None:
    """Refuse what the simulation does not model, naming it and why.

    A `[compare]` plan runs with its first value (simulate another with `plan.variants[i][1]`).
    With `[hosts]`, each host is a simulated process on one simulated network with the plan's
    `lease`; `cut` and `partition` use `SimulatedNetwork.partition`.

    Raises:
        PlanError: a fault kind not in `SIMULATED_KINDS` (`kill_resource`, `freeze`,
            `kill_router`), a setup of `NOT_SIMULATED_SETUPS`; with `[hosts]`: a kind of
            `NOT_WITH_HOSTS`, or a `cut` between more than two hosts.
    """
    source = plan.source or "<plan>"
    hosts = plan.hosts
    for index, fault in enumerate(plan.faults):
        where = f"faults[{index}].kind"
        if fault.kind not in SIMULATED_KINDS:
            why = NOT_SIMULATED.get(fault.kind, "the simulation does not model it")
            raise PlanError(source, 0, where, f"{fault.kind!r} is not simulated: {why}")
        if hosts is None:
            continue
        if fault.kind in NOT_WITH_HOSTS:
            why = NOT_WITH_HOSTS[fault.kind]
            raise PlanError(
                source, 0, where, f"{fault.kind!r} is not simulated with [hosts]: {why}"
            )
        if fault.kind == "cut" and len(hosts.names) > 2:
            raise PlanError(
                source,
                0,
                where,
                "'cut' is simulated between two hosts only: with more, the link's two "
                "ends still reach each other through another host, and the simulated "
                "network cuts one side off the rest (use 'partition')",
            )
    for manager in plan.managers():
        refused = NOT_SIMULATED_SETUPS.get(manager.setup)
        if refused is not None:
            raise PlanError(
                source,
                0,
                f"tree.children.{manager.name}.setup",
                f"{manager.setup} is not simulated: {refused}",
            )


def history_hash(history: str) -> str:
    """The SHA-256 (hex) of a history's text: what `replay` compares."""
    return hashlib.sha256(history.encode("utf-8")).hexdigest()


def simulate(
    plan: Plan,
    seeds: Iterable[int],
    *,
    on_run: Callable[[SimulatedRun], None] | None = None,
) -> list[SimulatedRun]:
    """Run `plan` on the simulation once per seed; each run's history, hash and verdict.

    An exception the system raises once its tree served (an assertion of the catalog, a
    deadlock) is that seed's result, verdict `"crashed"`: the next seed runs.

    Args:
        plan: the plan (`check_simulable` must accept it).
        seeds: the seeds, in the order to run them.
        on_run: called with each run as it finishes (in the caller's thread).

    Returns:
        The runs, in the order of `seeds`.

    Raises:
        PlanError: what `check_simulable` refuses.
        RrError: the tree did not start (a setup raised), or a client could not build
            a request; with the seed in a note.
        SimulationError: a run blocked for real.
    """
    check_simulable(plan)
    runs = []
    for seed in seeds:
        result = run_seed(plan, seed)
        runs.append(result)
        if on_run is not None:
            on_run(result)
    return runs


_STEPS: contextvars.ContextVar[Steps] = contextvars.ContextVar("rr_actors_lab.steps")
"""The steps `steps_in_place` put in place for this thread's runs (`run_seed`)."""


@contextlib.contextmanager
def steps_in_place(steps: Steps) -> Iterator[Steps]:
    """Inside the block, this thread's `run_seed` runs that name no `steps` run with `steps`
    (`rr_actors_lab.teach.replaced_step`'s block); the steps."""
    token = _STEPS.set(steps)
    try:
        yield steps
    finally:
        _STEPS.reset(token)


def steps_now() -> Steps:
    """The steps a `run_seed` that names none runs with here (`steps_in_place`)."""
    return _STEPS.get(Steps())


def run_seed(plan: Plan, seed: int, *, steps: Steps | None = None) -> SimulatedRun:
    """Run `plan` on the simulation with `seed` (see `simulate`, whose errors it raises).

    `steps`: the protocol steps the run's registrars and supervisors run instead of their
    own (`rr_actors.config.Steps`, handed to its `Supervisor`s; `None`: those
    `steps_in_place` put in place here, else their own).
    """
    check_simulable(plan)
    started = time.process_time()
    with _own_garbage():
        run = _run_seed(plan, seed, started, steps_now() if steps is None else steps)
    return dataclasses.replace(run, cpu_s=time.process_time() - started)


@contextlib.contextmanager
def _own_garbage() -> Iterator[None]:
    """Collect the block's garbage at its end, in one full collection that skips the older heap.

    Uses `gc.freeze` (if nothing is frozen already), with the collector off meanwhile: a seed's
    world is all cyclic garbage, and walking the whole heap doubled its cost.
    """
    freeze = getattr(gc, "freeze", None)
    if freeze is None or gc.get_freeze_count() > 0:
        yield
        return
    collecting = gc.isenabled()
    gc.disable()
    freeze()
    try:
        yield
    finally:
        gc.collect()
        gc.unfreeze()
        if collecting:
            gc.enable()


def _run_seed(plan: Plan, seed: int, started: float, steps: Steps) -> SimulatedRun:
    """`run_seed`'s work (what it made is garbage once it returned)."""
    from rr_actors import simulation  # noqa: PLC0415 - the simulation extra (greenlet)

    progress = _Progress(steps=steps)
    folder = Path(tempfile.mkdtemp(prefix="rr-sim-run-", dir=scratch_parent()))
    try:  # (a Ctrl-C or a SIGTERM made one: the run is cancelled, then its folder goes)
        until = plan.duration + plan.recovery_timeout + 600.0
        ran = simulation.run(
            lambda: _world(plan, seed, folder, progress), seed=seed, preempt=PREEMPT, until=until
        )
        unreadable = _unreadable(folder / "state")
    except Exception as exc:
        if not progress.serving or type(exc) is simulation.SimulationError:
            raise  # (the tree did not start, a client's request, the simulation itself)
        return _crashed(seed, exc, progress, _unplaced(folder), started)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    seen, records, wall_t0, calls = ran.value
    unplaced = _unplaced(folder)
    history = unplaced(_history(seen, records, seed, wall_t0))
    resolve = plan.hosts.resolve if plan.hosts is not None else "first_served"
    backoff_s = max(
        (s.backoff.max for s in plan.tree.supervisors() if s.backoff.initial > 0), default=0.0
    )
    default = rr.RegistrarConfig("a").call_timeout  # (the runner gives managers no config)
    timeouts = {m.name: default for m in plan.tree.managers()}
    timeouts.update({f"client-{i}": plan.workload.timeout for i in plan.workload.callers()})
    damaged = _backup_faults.damaged(plan, records)
    verdict = check.check(
        check.numbered(seen),
        resolve,
        backoff_s,
        timeouts,
        damaged,
        unreadable=unreadable,
        heard_from_start=plan.listen == "before_start",
        plain_requests=check.plain_plan(
            ((c.request, c.factory) for c in plan.workload.calls),
            ((m.setup, m.options) for m in plan.managers()),
        ),
    )
    return SimulatedRun(
        seed=seed,
        hash=history_hash(history),
        verdict=verdict.verdict,
        violations=verdict.violations,
        unverifiable=verdict.unverifiable,
        findings=tuple(map(unplaced, check.format_verdict(RUN, verdict)[1:])),
        history=history,
        events=len(seen),
        faults=sum(1 for r in records if not r.skipped),
        calls_ok=calls[0],
        calls_failed=calls[1],
        entries_left=calls[2],
        virtual_s=ran.elapsed,
        cpu_s=time.process_time() - started,
        errors=tuple(map(unplaced, ran.errors)),
    )


def _unreadable(state: Path) -> dict[str, str]:
    """The backups the run left (`<manager>.db`, after its stop) that `read_backup` refuses,
    as `rr-actors observe --state` would: manager -> why (`check`'s `backup-readable`)."""
    found: dict[str, str] = {}
    for file in sorted(state.glob("*.db")):  # (no state folder: none)
        try:
            read_backup(file, unpickle=False)
        except (CatalogCorruptError, ConfigError) as exc:
            found[file.stem] = str(exc)
    return found


def _history(
    seen: list[events.Event], records: list[FaultRecord], seed: int, wall_t0: float
) -> str:
    """A run's history: its events' lines, then its faults'."""
    return to_lines(seen, {"run": RUN, "seed": seed}) + "".join(
        json.dumps(fault_line(r, run=RUN, seed=seed, wall_t0=wall_t0)) + "\n" for r in records
    )


def _crashed(
    seed: int,
    exc: Exception,
    progress: _Progress,
    unplaced: Callable[[str], str],
    started: float,
) -> SimulatedRun:
    """A seed's run whose system raised `exc` once it served: verdict `"crashed"`, a `CRASH_LINE`
    last."""
    at_s, step = getattr(exc, "simulated_at", (0.0, 0))
    seen = list(progress.log.seen) if progress.log is not None else []
    records = list(progress.faults.records) if progress.faults is not None else []
    crash = {
        "type": CRASH_LINE,
        "error_type": type(exc).__name__,
        "message": unplaced(str(exc)),
        "virtual_s": at_s,
        "step": step,
        "run": RUN,
        "seed": seed,
    }
    history = unplaced(_history(seen, records, seed, progress.wall_t0)) + json.dumps(crash) + "\n"
    calls = [c for client in progress.clients for c in client.calls]
    ok = sum(1 for c in calls if c.ok)
    finding = (
        f"  crashed: {crash['error_type']}: {crash['message']} (at {at_s:.6f} virtual s, "
        f"step {step})"
    )
    return SimulatedRun(
        seed=seed,
        hash=history_hash(history),
        verdict="crashed",
        violations=0,
        unverifiable=0,
        findings=(finding,),
        history=history,
        events=len(seen),
        faults=sum(1 for r in records if not r.skipped),
        calls_ok=ok,
        calls_failed=len(calls) - ok,
        entries_left=0,
        virtual_s=at_s,
        cpu_s=time.process_time() - started,
        errors=(),
    )


def scratch_parent() -> str | None:
    """Where a run's folder is made: `RAM_DIR` unless `TMPDIR` chooses (or it is not a
    writable folder): then the OS's temporary folder (`None`)."""
    if os.environ.get("TMPDIR"):
        return None
    return RAM_DIR if os.path.isdir(RAM_DIR) and os.access(RAM_DIR, os.W_OK) else None


def _unplaced(folder: Path) -> Callable[[str], str]:
    """What replaces `folder` (as given, resolved, JSON-escaped) with `SCRATCH` in a run's text."""
    forms = {str(folder), os.path.realpath(folder)}
    forms |= {json.dumps(form)[1:-1] for form in forms}
    ordered = sorted(forms, key=len, reverse=True)  # (a longer form holds a shorter)

    def unplaced(text: str) -> str:
        for form in ordered:
            text = text.replace(form, SCRATCH)
        return text

    return unplaced


@dataclasses.dataclass
class _Progress:
    """How far a run got, for a crash's result (`_crashed`): set by `_world` as it goes."""

    serving: bool = False  # the tree started: an exception from here on is the system's
    log: _EventLog | None = None
    faults: SimulatedFaults | None = None
    wall_t0: float = 0.0
    clients: list[Client] = dataclasses.field(default_factory=list)
    steps: Steps = dataclasses.field(default_factory=Steps)  # (the run's: `run_seed(steps=)`)


def _close_injector(injector: SimulatedFaults, progress: _Progress) -> None:
    """Close the run's injector; if that fails, the run failed (the tool's error, not
    a crash of the system: `_crashed`)."""
    try:
        injector.close()
    except BaseException:
        progress.serving = False
        raise


def _injector(
    sup: rr.Supervisor,
    plan: Plan,
    network: simulation.SimulatedNetwork,
    seed: int,
    seen: Callable[[events.Event], None],
    folder: Path,
    progress: _Progress,
    **where: Any,
) -> tuple[SimulatedFaults, float]:
    """The run's fault injector, made as its workload starts, and that `t0` (monotonic seconds)."""
    from rr_actors_lab.experiments._simulated_faults import SimulatedFaults  # noqa: PLC0415 - greenlet

    t0, wall_t0 = runtime.monotonic(), runtime.wall()
    progress.wall_t0 = wall_t0
    faults = SimulatedFaults(
        sup,
        plan,
        network,
        fault_schedule(plan, seed),
        t0,
        wall_t0,
        on_event=seen,
        state_dir=folder / "beyond" if plan.state else None,
        **where,
    )
    progress.faults = faults
    return faults, t0


def _listen(
    sup: rr.Supervisor, seen: Callable[[events.Event], None], plan: Plan, *, serving: bool
) -> rr.Subscription[events.Event] | None:
    """`seen` subscribed to the tree if this is when the plan's `listen` says (before the
    start, or once it serves: then the running managers' processes are switched on to
    forward, `EventRelay`); else `None`."""
    if serving != (plan.listen == "after_start"):
        return None
    return sup.subscribe(seen, maxsize=EVENT_QUEUE)


def _world(
    plan: Plan, seed: int, folder: Path, progress: _Progress
) -> tuple[list[events.Event], list[FaultRecord], float, tuple[int, int, int]]:
    """The run, in the simulation's main thread: the runner's steps on simulated seams."""

    if any(fault.kind == "kill_program" for fault in plan.faults):
        return _program_world(plan, seed, folder, progress)
    network = _network_of(plan)
    work = folder / "work"
    work.mkdir()
    state = folder / "state" if plan.state else None
    sup = build_tree(plan, state, seed=seed, network=network, steps=progress.steps)
    hosts: list[_SimulatedHost] = []  # the other hosts (with `[hosts]`), once started
    log = progress.log = _EventLog()
    injector: list[SimulatedFaults] = []  # (set once the workload starts)

    def seen(event: events.Event) -> None:
        log(event)
        for faults in injector:
            faults.on_event(event)

    subscription = _listen(sup, seen, plan, serving=False)
    records: list[FaultRecord] = []
    try:
        sup.start()
        subscription = _listen(sup, seen, plan, serving=True) or subscription
        _start_hosts(plan, folder, seed, network, seen, hosts, progress.steps)
        clients = [Client(i, sup, plan, seed, run_dir=work) for i in plan.workload.callers()]
        progress.serving, progress.clients = True, clients
        faults, t0 = _injector(
            sup,
            plan,
            network,
            seed,
            seen,
            folder,
            progress,
            hosts={h.name: h.pid for h in hosts},
            trees={h.name: h.sup for h in hosts if h.sup is not None},
            backups=state,
        )
        injector.append(faults)
        faults.start()
        for client in clients:
            client.start(t0=t0, deadline=t0 + plan.duration)
        runtime.sleep(plan.duration)
        faults.stop()
        records = faults.records
        managers = _wait_serving(sup, plan, hosts)
        for client in clients:
            client.stop(timeout=plan.workload.timeout)
        failed = next((c.failure for c in clients if c.failure is not None), None)
        if failed is not None:
            progress.serving = False  # (a client's request could not be made: no result)
            raise failed
        # (the runner's settling, too; then each other host's)
        left = count_entries(sup, managers, clients)[0] + _ask_each(hosts, "count")
        sup.flush_events()
        _ask_each(hosts, "flush")
    finally:
        # Each step of the cleanup runs though one before it raised (the first error is
        # raised, the others chained): a network left open would refuse the next seed's.
        with contextlib.ExitStack() as cleanup:
            cleanup.callback(network.close)
            if subscription is not None:  # (`listen = "after_start"`: none if the start failed)
                cleanup.callback(subscription.close)
                cleanup.callback(subscription.wait_delivered)
            for opened in injector:  # (second servers' supervisors: to the end of the run)
                cleanup.callback(_close_injector, opened, progress)
            cleanup.callback(functools.partial(sup.stop, parallel=plan.stop == "parallel"))
            cleanup.callback(_stop_each, hosts)  # (before the run's own host's tree, as for real)
    calls = [c for client in clients for c in client.calls]
    ok = sum(1 for c in calls if c.ok)
    return list(log.seen), records, progress.wall_t0, (ok, len(calls) - ok, left)


def _program_world(
    plan: Plan, seed: int, folder: Path, progress: _Progress
) -> tuple[list[events.Event], list[FaultRecord], float, tuple[int, int, int]]:
    """`_world` for a `kill_program` plan: the tree and clients in a `_SimulatedProgram`."""
    from rr_actors import simulation  # noqa: PLC0415 - the simulation extra (greenlet)

    network = simulation.SimulatedNetwork()  # (check_simulable refuses it with [hosts])
    work = folder / "work"
    work.mkdir()
    log = progress.log = _EventLog()
    injector: list[SimulatedFaults] = []  # (set once the workload starts)

    def seen(event: events.Event) -> None:
        log(event)
        for faults in injector:
            faults.on_event(event)

    program = _SimulatedProgram(
        plan, folder / "state" if plan.state else None, seed, network, seen, work, progress.steps
    )
    records: list[FaultRecord] = []
    try:
        sup = program.start()
        progress.serving, progress.clients = True, program.clients
        faults, t0 = _injector(sup, plan, network, seed, seen, folder, progress, program=program)
        injector.append(faults)
        program.go(t0, t0 + plan.duration)  # (before a fault can kill it: `ask` would wait)
        faults.start()
        runtime.sleep(plan.duration)
        faults.stop()
        records = faults.records
        program.ask("wait_serving", plan.recovery_timeout)
        program.ask("stop_clients")
        failed = next((c.failure for c in program.clients if c.failure is not None), None)
        if failed is not None:
            progress.serving = False  # (a client's request could not be made: no result)
            raise failed
        left = program.ask("count")  # (the runner's settling, in the program)
        program.ask("flush")
    finally:
        with contextlib.ExitStack() as cleanup:  # (as `_world`'s)
            cleanup.callback(network.close)
            for opened in injector:
                cleanup.callback(_close_injector, opened, progress)
            cleanup.callback(program.stop)
    calls = [c for client in program.clients for c in client.calls]
    ok = sum(1 for c in calls if c.ok)
    return list(log.seen), records, progress.wall_t0, (ok, len(calls) - ok, left)


class _SimulatedProgram:
    """The program of a `kill_program` plan: a simulated process of its own that builds its tree
    on `state_dir`, makes the clients, then runs what `ask` sends; `kill` ends it as SIGKILL
    does (its managers with it), `start` starts it again on the same `state_dir`."""

    def __init__(
        self,
        plan: Plan,
        state_dir: Path | None,
        seed: int,
        network: object,
        on_event: Callable[[events.Event], None],
        work: Path,
        steps: Steps,
    ) -> None:
        self.plan = plan
        self._steps = steps
        self._state_dir = state_dir
        self._seed = seed
        self._network = network
        self._on_event = on_event
        self._work = work
        self.pid = 0  # its process now (0: not started)
        self.sup: rr.Supervisor | None = None  # its tree now
        self.clients: list[Client] = []  # every life's clients, in the order made
        self._workload: tuple[float, float] | None = None  # (t0, deadline), once begun
        self._commands: runtime.SimpleQueue[tuple[str, float]] = runtime.SimpleQueue()
        self._replies: runtime.SimpleQueue[object] = runtime.SimpleQueue()
        self._serving = False  # its main thread takes commands

    def start(self) -> rr.Supervisor:
        """Start a life of the program; its tree once it serves and its clients are made."""
        from rr_actors import simulation  # noqa: PLC0415 - the simulation extra (greenlet)

        self._commands, self._replies = runtime.SimpleQueue(), runtime.SimpleQueue()
        self.pid = simulation.start_process(
            functools.partial(self._main, self._commands, self._replies), name="program"
        )
        reply = self._replies.get()
        if isinstance(reply, BaseException):
            raise reply
        self._serving = True
        assert self.sup is not None
        return self.sup

    def kill(self) -> int:
        """SIGKILL its process (its managers' with it); its pid."""
        from rr_actors import simulation  # noqa: PLC0415 - the simulation extra (greenlet)

        self._serving = False
        simulation.kill(self.pid, signal.SIGKILL)
        return self.pid

    def go(self, t0: float, deadline: float) -> None:
        """Its clients start calling, from `t0` until `deadline` (monotonic seconds)."""
        self._workload = (t0, deadline)
        self.ask("go")

    def ask(self, op: str, timeout: float = 0.0) -> int:
        """Run `op` (`"go"`, `"wait_serving"`, `"stop_clients"`, `"count"`, `"flush"`); the count,
        or 0.

        Raises:
            RrError: the program is not running, or what `op` raised there.
        """
        if not self._serving:
            raise rr.RrError("the run's program is not running (it did not start again)")
        self._commands.put((op, timeout))
        reply = self._replies.get()
        if isinstance(reply, BaseException):
            raise reply
        return reply if isinstance(reply, int) else 0

    def stop(self) -> None:
        """Stop its tree once its events are delivered (nothing if it is not running)."""
        if self._serving:
            self._serving = False
            self._commands.put(("stop", 0.0))
            reply = self._replies.get()
            if isinstance(reply, BaseException):
                raise reply

    def _main(
        self,
        commands: runtime.SimpleQueue[tuple[str, float]],
        replies: runtime.SimpleQueue[object],
    ) -> None:
        plan = self.plan
        subscription: rr.Subscription[events.Event] | None = None
        try:
            sup = build_tree(
                plan, self._state_dir, seed=self._seed, network=self._network, steps=self._steps
            )
            subscription = sup.subscribe(self._on_event, maxsize=EVENT_QUEUE)
            sup.start()
            clients = [
                Client(i, sup, plan, self._seed, run_dir=self._work)
                for i in plan.workload.callers()
            ]
        except Exception as exc:  # noqa: BLE001 - the thread that started it raises it
            if subscription is not None:
                subscription.close()
            replies.put(exc)
            return
        self.sup = sup
        self.clients.extend(clients)
        if self._workload is not None:  # (started again: its clients call at once)
            self._go(clients, runtime.monotonic())
        replies.put("ready")
        while True:
            op, timeout = commands.get()
            try:
                reply = self._command(op, timeout, sup, clients, subscription)
            except Exception as exc:  # noqa: BLE001 - the run's thread raises it
                reply = exc
            replies.put(reply)
            if op == "stop":
                return

    def _command(
        self,
        op: str,
        timeout: float,
        sup: rr.Supervisor,
        clients: list[Client],
        subscription: rr.Subscription[events.Event],
    ) -> object:
        """Run one command of `ask` (or `stop`) on this life's tree and clients."""
        plan = self.plan
        managers = [m.name for m in plan.managers()]
        if op == "go":
            assert self._workload is not None
            self._go(clients, self._workload[0])
        elif op == "wait_serving":
            wait_all_serving(sup, managers, timeout)
        elif op == "stop_clients":
            for client in clients:
                client.stop(timeout=plan.workload.timeout)
        elif op == "count":
            return count_entries(sup, managers, clients)[0]
        elif op == "flush":
            sup.flush_events()
        else:  # "stop"
            with contextlib.ExitStack() as cleanup:
                cleanup.callback(subscription.close)
                cleanup.callback(subscription.wait_delivered)
                cleanup.callback(sup.stop)
        return None

    def _go(self, clients: list[Client], t0: float) -> None:
        """Start `clients` calling from `t0` (a life started again: its start, so that its
        clients' first calls come one gap after it, not all at once to catch up)."""
        assert self._workload is not None
        for client in clients:
            client.start(t0=t0, deadline=self._workload[1])


def _network_of(plan: Plan) -> simulation.SimulatedNetwork:
    """The run's simulated network: with `[hosts]`, the plan's lease, this process named the run's
    host."""
    from rr_actors import simulation  # noqa: PLC0415 - the simulation extra (greenlet)

    if plan.hosts is None:
        return simulation.SimulatedNetwork()
    set_host(plan.hosts.home)
    resolve = plan.hosts.resolve
    if resolve not in RESOLVE_STRATEGIES:  # (a user's function: `reading` imported it)
        resolve = import_object(resolve, base_dir=plan.base_dir)
    return simulation.SimulatedNetwork(lease=plan.hosts.lease, resolve=resolve)


def _wait_serving(sup: rr.Supervisor, plan: Plan, hosts: list[_SimulatedHost]) -> list[str]:
    """Wait until the run's own host's managers serve, then the others'; the own host's names.

    Raises:
        RrError: a manager of the run's own host did not serve in time.
    """
    home = plan.hosts.home if plan.hosts is not None else None
    managers = [m.name for m in plan.managers() if plan.host_of(m.name) == home]
    wait_all_serving(sup, managers, plan.recovery_timeout)
    _ask_each(hosts, "wait_serving", plan.recovery_timeout)
    return managers


def _stop_each(hosts: list[_SimulatedHost]) -> None:
    """Stop the other hosts' trees, the last started first; each, though one before it
    raised (the first error is raised)."""
    with contextlib.ExitStack() as cleanup:
        for host in hosts:
            cleanup.callback(host.stop)


def _ask_each(hosts: list[_SimulatedHost], op: str, timeout: float = 0.0) -> int:
    """`op` on each other host, one after another (`_SimulatedHost.ask`): the sum of
    their counts."""
    return sum(host.ask(op, timeout) for host in hosts)


def _start_hosts(
    plan: Plan,
    folder: Path,
    seed: int,
    network: object,
    on_event: Callable[[events.Event], None],
    hosts: list[_SimulatedHost],
    steps: Steps,
) -> None:
    """With `[hosts]`: start each other host (in `hosts` as it starts, so that the run's
    cleanup stops it) and wait until its tree serves, one after another."""
    for name in plan.hosts.names[1:] if plan.hosts is not None else ():
        state = folder / f"state-{name}" if plan.state else None
        hosts.append(_SimulatedHost(plan, name, state, seed, network, on_event, steps))
        hosts[-1].ask("start")


class _SimulatedHost:
    """Another host of a `[hosts]` plan: a simulated process that builds its part of the tree
    (`build_tree(host=)`) then runs what `ask` sends, as `_host_child` does for real."""

    def __init__(
        self,
        plan: Plan,
        name: str,
        state_dir: Path | None,
        seed: int,
        network: object,
        on_event: Callable[[events.Event], None],
        steps: Steps,
    ) -> None:
        from rr_actors import simulation  # noqa: PLC0415 - the simulation extra (greenlet)

        self.plan = plan
        self.name = name
        self._steps = steps
        self._state_dir = state_dir
        self._seed = seed
        self._network = network
        self._on_event = on_event
        self._commands: runtime.SimpleQueue[tuple[str, float]] = runtime.SimpleQueue()
        self._replies: runtime.SimpleQueue[object] = runtime.SimpleQueue()
        self._serving = False  # its main thread takes commands
        self.sup: rr.Supervisor | None = None  # its tree, once built (a fault's target's)
        self.pid = simulation.start_process(self._main, name=f"host-{name}")

    def ask(self, op: str, timeout: float = 0.0) -> int:
        """Run `op` (`"start"`, `"wait_serving"`, `"count"`, `"flush"`) on the host; the count, or
        0."""
        if op != "start":
            self._commands.put((op, timeout))
        reply = self._replies.get()
        if isinstance(reply, BaseException):
            raise reply
        self._serving = True
        return reply if isinstance(reply, int) else 0

    def stop(self) -> None:
        """Stop its tree once its events are delivered (nothing if it never served)."""
        if self._serving:
            self._serving = False
            self._commands.put(("stop", 0.0))
            reply = self._replies.get()
            if isinstance(reply, BaseException):
                raise reply

    def _main(self) -> None:
        plan, name = self.plan, self.name
        set_host(name)  # (its events', and its managers' processes' as they start)
        subscription: rr.Subscription[events.Event] | None = None
        try:
            sup = build_tree(
                plan,
                self._state_dir,
                seed=self._seed,
                host=name,
                network=self._network,
                steps=self._steps,
            )
            subscription = sup.subscribe(self._on_event, maxsize=EVENT_QUEUE)
            sup.start()
            self.sup = sup
        except Exception as exc:  # noqa: BLE001 - the run's thread raises it
            if subscription is not None:  # (a start that failed leaves no subscriber)
                subscription.close()
            self._replies.put(exc)
            return
        managers = [m.name for m in plan.managers() if plan.host_of(m.name) == name]
        self._replies.put("ready")
        while True:
            op, timeout = self._commands.get()
            reply: object = None
            try:
                if op == "wait_serving":
                    with contextlib.suppress(rr.RrError):
                        wait_all_serving(sup, managers, timeout)
                elif op == "count":
                    reply = count_entries(sup, managers, [])[0]
                elif op == "flush":
                    sup.flush_events()
                else:  # "stop"
                    with contextlib.ExitStack() as cleanup:
                        cleanup.callback(subscription.close)
                        cleanup.callback(subscription.wait_delivered)
                        cleanup.callback(sup.stop)
            except Exception as exc:  # noqa: BLE001 - the run's thread raises it
                reply = exc
            self._replies.put(reply)
            if op == "stop":
                return
