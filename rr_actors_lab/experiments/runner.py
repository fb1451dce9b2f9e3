"""One run, inside its own run process: build the tree, drive the workload, inject, measure.

    execute(spec)
      ├─ the managers' forkserver preloads the setups' modules (preload_setups)
      ├─ Supervisor(the plan's tree; every setup wrapped by _instrument.instrumented_setup)
      ├─ subscribe ─► _EventLog: keeps every event, feeds the injector's triggers
      ├─ start the tree; clients (workload.py); t0; injector (inject.py) and clients go
      ├─ wait `duration` (or until told to stop: SIGTERM from the experiment)
      ├─ stop the injector (hung managers resumed); wait until every manager serves again
      ├─ clients unload everything; count what the catalogs still hold
      ├─ stop the tree; events.jsonl (+ run, seed); processes of this run still alive
      │  are leaks (then killed)
      └─ metrics.py ─► RunResult

The run process is started by `rr_actors_lab.experiments.experiment` with `python -m
rr_actors_lab.experiments._child RUN_DIR`; `execute` is also callable in-process (tests).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import logging
import os
import random
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec

import rr_actors as rr
from rr_actors import events
from rr_actors._core import runtime
from rr_actors._process import control as process_control
from rr_actors.config import Steps
from rr_actors.events.lines import to_lines
from rr_actors.testing import catalog_snapshot
from rr_actors_lab.experiments import _hosts, _procs, check, metrics
from rr_actors_lab.experiments._instrument import instrumented_setup
from rr_actors_lab.experiments._netns import PORT, HostNetwork
from rr_actors_lab.experiments.inject import Injector
from rr_actors_lab.experiments.plan import HOST_KINDS, ManagerPlan, Plan, SupervisorPlan
from rr_actors_lab.experiments.results import FaultRecord, RunResult
from rr_actors_lab.experiments.schedule import fault_schedule
from rr_actors_lab.experiments.workload import Client

__all__ = [
    "RunSpec",
    "build_tree",
    "execute",
    "fault_line",
    "preload_setups",
]

logger = logging.getLogger("rr_actors.experiments")

SWITCH_INTERVAL = 0.001
"""Seconds between forced thread switches in a run process (Python's default is 0.005):
the injector's thread gets the interpreter within a millisecond of its wake-up."""

LEAK_GRACE = 1.0
"""Seconds the processes of a stopped tree get to exit before they count as leaked."""

EVENT_QUEUE = 200_000
"""Events the run's subscription may queue before it drops (and counts) new ones."""

SETTLE_TIMEOUT = 2.0
"""Seconds the catalogs get, at the end of a run, to reach no rows before the rows left are
counted: a registrar restored near the end reconciles with the others after it serves
again (rule 20), and a consumer id released then was never a leak. A row still there
after this is counted."""


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """What one run process is asked to do.

    Attributes:
        plan: the plan, for one compared value.
        setting: the compared setting (`""` without `compare`).
        value: the compared value (`None` without `compare`).
        run: the run's number in the experiment (1, 2, ...).
        repeat: its number among the runs of its value (1, 2, ...).
        seed: its seed.
        record_events: subscribe to the tree and write `events.jsonl` (off: to measure it).
        observe: serve the live observer page (`Supervisor.observe`) during the run.
        trace: make OpenTelemetry spans of the tree (`otel.Exporting`, by `OTEL_*`).
        token: the value of `RR_ACTORS_EXPERIMENT` that marks this run's processes.
    """

    plan: Plan
    setting: str
    value: Any
    run: int
    repeat: int
    seed: int
    record_events: bool = True
    observe: bool = False
    token: str = ""
    trace: bool = False


def build_tree(
    plan: Plan,
    state_dir: Path | None,
    *,
    seed: int = 0,
    host: str | None = None,
    network: Any = None,
    steps: Steps | None = None,
) -> rr.Supervisor:
    """The plan's supervision tree as an (unstarted) `Supervisor`, every setup instrumented.

    Args:
        plan: the plan.
        state_dir: the directory of the managers' durable catalogs (`None`: in memory).
        seed: the run's seed (the tree's backoff jitter draws from it).
        host: with `[hosts]`, the host whose part of the tree this is; `None`: the run's own.
        network: the carrier the tree is served on (`None`: this machine's AF_UNIX one).
        steps: the protocol steps its registrars and supervisors run instead of their own
            (`Supervisor(steps=)`; `None`: their own).

    Raises:
        ConfigError: the tree is not a valid supervision tree (only for a plan built by hand).
    """
    top = plan.tree
    if plan.hosts is not None:
        top = _on_host(plan, top, host or plan.hosts.home) or msgspec.structs.replace(
            top, children=()
        )
    jitter = random.Random(f"rr-actors/{seed}/backoff")  # noqa: S311 - not for secrets
    return rr.Supervisor(
        [_child_spec(child, plan.base_dir) for child in top.children],
        strategy=top.strategy,
        max_restarts=top.max_restarts,
        period=top.period,
        backoff=top.backoff,
        state_dir=state_dir,
        name=top.name if host is None or plan.hosts is None else f"{top.name}-{host}",
        random=jitter.random,
        network=network,
        steps=steps,
    )


PRELOAD_MODULE = "rr_actors_lab.experiments._preload"
"""What a run's forkserver preloads: it imports the setups' modules (by name: see there)."""


def preload_setups(plan: Plan) -> None:
    """Start the managers' forkserver now, importing the plan's setups' modules once, so a
    manager (re)start does not import them after its fork; before the first manager starts."""
    modules = [m.setup.partition(":")[0] for m in plan.managers()]
    named = {"base_dir": plan.base_dir, "modules": modules}
    os.environ[_procs.PRELOAD_VARIABLE] = json.dumps(named)
    try:
        process_control.preload([PRELOAD_MODULE])
        process_control.start_forkserver()
    finally:
        del os.environ[_procs.PRELOAD_VARIABLE]


def _on_host(plan: Plan, node: SupervisorPlan, host: str) -> SupervisorPlan | None:
    """The part of `node` on `host`: its managers there, and the supervisors above them."""
    children: list[ManagerPlan | SupervisorPlan] = []
    for child in node.children:
        if isinstance(child, SupervisorPlan):
            part = _on_host(plan, child, host)
            if part is not None:
                children.append(part)
        elif plan.host_of(child.name) == host:
            children.append(child)
    return msgspec.structs.replace(node, children=tuple(children)) if children else None


def _child_spec(
    child: ManagerPlan | SupervisorPlan, base_dir: str | None
) -> rr.ManagerSpec | rr.SupervisorSpec:
    if isinstance(child, SupervisorPlan):
        return rr.SupervisorSpec(
            name=child.name,
            children=tuple(_child_spec(c, base_dir) for c in child.children),
            strategy=child.strategy,
            max_restarts=child.max_restarts,
            period=child.period,
            backoff=child.backoff,
            restart=child.restart,
        )
    return rr.ManagerSpec(
        child.name,
        setup=functools.partial(instrumented_setup, child.setup, dict(child.options), base_dir),
        isolation=child.isolation,
        restart=child.restart,
        heartbeat=child.heartbeat,
        heartbeat_timeout=child.heartbeat_timeout,
        shutdown=child.shutdown,
        start_timeout=child.start_timeout,
    )


def fault_line(record: FaultRecord, *, run: int, seed: int, wall_t0: float) -> dict[str, Any]:
    """A fault as a line of `events.jsonl` (`"type": "FaultInjected"` or `"FaultSkipped"`)."""
    at = record.injected_s if record.injected_s is not None else record.scheduled_s
    return {
        "type": "FaultSkipped" if record.skipped else "FaultInjected",
        "fault": record.fault,
        "n": record.n,
        "kind": record.kind,
        "target": record.target,
        "detail": record.detail,
        "scheduled_s": record.scheduled_s,
        "injected_s": record.injected_s,
        "recovery_s": record.recovery_s,
        "at": None if at is None else wall_t0 + at,
        "run": run,
        "seed": seed,
    }


class _EventLog:
    """The run's subscriber: keeps every event (JSON is written after the tree stopped) and
    feeds the injector's triggers."""

    def __init__(self) -> None:
        self.seen: list[events.Event] = []
        self.injector: Injector | None = None

    def __call__(self, event: events.Event) -> None:
        self.seen.append(event)
        injector = self.injector
        if injector is not None:
            injector.on_event(event)

    @property
    def dropped(self) -> int:
        """Events lost to a full queue, from the `EventsDropped` notices (which count the
        subscription's own drops too: do not add `Subscription.dropped`)."""
        return sum(e.count for e in self.seen if isinstance(e, events.EventsDropped))

    def write(self, path: Path, run: int, seed: int) -> None:
        """Write every event as a JSON line with `run` and `seed` (`events.jsonl`)."""
        path.write_text(to_lines(self.seen, {"run": run, "seed": seed}), encoding="utf-8")


def _catalog_size(registrar: rr.ResourceRegistrar) -> int:
    """Rows in a registrar's catalog (run where the registrar lives, via `run_in`)."""
    view = catalog_snapshot(registrar)
    return len(view.resources) + len(view.clients)


def wait_all_serving(sup: rr.Supervisor, names: list[str], timeout: float) -> None:
    """Wait (bounded) until every manager runs again with the restarts it counted (not one more);
    skip those that will not come back."""
    deadline = runtime.monotonic() + timeout
    for name in names:
        info = sup.child(name)
        while info.state != "running":
            left = deadline - runtime.monotonic()
            if left <= 0 or sup.gave_up is not None:
                return  # nothing more comes back
            if info.state in ("exited", "stopped"):
                break  # this one stays down (temporary, or its nested supervisor gave up)
            try:
                info = sup.wait_restarted(name, timeout=left, restarts=info.restarts)
            except rr.RrError:
                break  # it will not come back; the next may


def _leaked(token: str) -> int:
    """Processes of this run still alive after its tree stopped (killed, and counted)."""
    if not token:
        return 0
    me = os.getpid()
    alive = [
        pid
        for pid in _procs.processes_with(token, exclude=frozenset({me, os.getppid()}))
        # This process's forkserver and resource tracker end with it. (Manager processes
        # also show the forkserver's command line, but they are its children, not ours.)
        if not (_procs.parent(pid) == me and "multiprocessing" in _procs.cmdline(pid))
    ]
    left = _procs.wait_gone(alive, LEAK_GRACE)
    _procs.kill(left)
    return len(left)


@dataclasses.dataclass
class _Drive:
    """One run while its tree runs: the clients, the injector and what they measured."""

    clients: list[Client] = dataclasses.field(default_factory=list)
    injector: Injector | None = None
    wall_t0: float = 0.0
    end_s: float = 0.0  # the end of the workload (seconds from t0)
    until_s: float = 0.0  # the last instant measured, just before the tree's shutdown
    entries: int = 0
    unread: int = 0  # managers whose catalog could not be read at the end
    hosts: list[_hosts.HostProcess] = dataclasses.field(default_factory=list)  # the others
    network: HostNetwork | None = None  # with `[hosts]`: the namespaces
    # with `--trace`: what each step (a client's call, unload..., a fault) runs under
    step_span: Callable[..., contextlib.AbstractContextManager[object]] | None = None


def execute(spec: RunSpec, run_dir: Path, *, stop: threading.Event | None = None) -> RunResult:
    """Run one run of `spec` in this process; return its result.

    Args:
        spec: what to run.
        run_dir: a fresh directory for the run's files (`events.jsonl`, `state/`, `work/`).
        stop: set it to end the run early (the result is then incomplete).

    Returns:
        The run's result (its `leaked_processes` counts what this process could see).

    Raises:
        RrError: the tree did not start (`ManagerStartError`) or could not be built
            (`ConfigError`), or a client could not build a request (`ConfigError` naming
            `workload.calls[i]`, the key and the cause). What the plan's own code raises
            otherwise comes out as it was raised.
    """
    stop = stop if stop is not None else threading.Event()
    sys.setswitchinterval(SWITCH_INTERVAL)
    plan = spec.plan
    if plan.base_dir is not None and plan.base_dir not in sys.path:
        sys.path.insert(0, plan.base_dir)  # the plan's modules, here and in its managers
    preload_setups(plan)
    (run_dir / "work").mkdir(parents=True, exist_ok=True)
    drive = _Drive()
    log = _EventLog()
    with contextlib.ExitStack() as stack:
        network = _hosts_of(plan, run_dir, spec.seed, log, stack, drive)
        state_dir = run_dir / "state" if plan.state else None
        sup = build_tree(plan, state_dir, seed=spec.seed, network=network)
        late = plan.listen == "after_start"  # (after `sup.start()`, below)
        subscription = (
            sup.subscribe(log, maxsize=EVENT_QUEUE) if spec.record_events and not late else None
        )
        if spec.trace:
            from rr_actors_lab import otel  # noqa: PLC0415 - only tracing needs it

            exporting = stack.enter_context(otel.Exporting())  # (closed after the stop)
            exporting.trace(sup)
            drive.step_span = exporting.root_span  # each step a trace of its own
        try:
            sup.start()
            if spec.record_events and late:
                subscription = sup.subscribe(log, maxsize=EVENT_QUEUE)
            try:
                _start_hosts(drive, network, plan)
                _drive(sup, spec, log, run_dir / "work", stop, drive)
            finally:
                if drive.injector is not None:
                    drive.injector.stop()
                sup.stop(parallel=plan.stop == "parallel")
                for host in drive.hosts:
                    host.stop(timeout=LEAK_GRACE + 5.0)
            if subscription is not None:
                subscription.wait_delivered()
        finally:
            if subscription is not None:
                subscription.close()
    log.write(run_dir / "events.jsonl", spec.run, spec.seed)
    leaked = _leaked(spec.token)
    assert drive.injector is not None
    result = _result(spec, log, drive, leaked=leaked, run_dir=run_dir)
    if not spec.record_events:
        return result
    return _checked(result, run_dir / "events.jsonl", heard_from_start=plan.listen != "after_start")


def _hosts_of(
    plan: Plan,
    run_dir: Path,
    seed: int,
    log: _EventLog,
    stack: contextlib.ExitStack,
    drive: _Drive,
) -> Any:
    """With `[hosts]`: make the namespaces (deleted when `stack` closes), move this thread
    into the first host's, and prepare the other hosts' processes (in `drive.hosts`);
    return the run's own host's `ZenohNetwork` (its router). Without: `None`."""
    if plan.hosts is None:
        return None
    from rr_actors_lab._tools import certs as certs_tool  # noqa: PLC0415 - needs the zenoh extra

    names = plan.hosts.names
    net = drive.network = HostNetwork(names)
    stack.callback(net.close)
    certs = run_dir / "certs"
    certs.mkdir(mode=0o700)
    ca, _ = certs_tool.init_ca(certs, _hosts.SYSTEM)
    specs = []
    for index, name in enumerate(names):
        pem, key = certs_tool.issue_cert(certs, name, net.addresses[name])
        tls = {"ca": str(ca), "cert": str(pem), "key": str(key), "members": list(names)}
        state = run_dir / f"state-{name}" if plan.state and index else None
        specs.append(
            _hosts.HostSpec(
                plan=plan,
                host=name,
                listen=tuple(f"tls/{a}:{PORT}" for a in net.addresses[name]),
                connect=tuple(f"tls/{net.peers[name][b]}:{PORT}" for b in names[:index]),
                lease=plan.hosts.lease,
                tls=tls,
                state_dir=None if state is None else str(state),
                seed=seed,
                namespace=net.namespaces[name],
            )
        )
    net.enter(names[0])
    drive.hosts = [
        _hosts.HostProcess(
            spec,
            run_dir / f"host-{spec.host}.pickle",
            on_event=log,
            log=run_dir / f"host-{spec.host}.log",
        )
        for spec in specs[1:]
    ]
    return _hosts.network(specs[0])


def _start_hosts(drive: _Drive, network: Any, plan: Plan) -> None:
    """Start the other hosts; wait (bounded) until the run's host sees every manager."""
    if plan.hosts is None:
        return
    for host in drive.hosts:
        host.start(timeout=plan.hosts.start_timeout)
    names = {m.name for m in plan.managers()}
    deadline = time.monotonic() + plan.hosts.start_timeout
    while not names <= set(network.names()):
        if time.monotonic() > deadline:
            missing = ", ".join(sorted(names - set(network.names())))
            raise rr.RrError(f"the run's host does not see {missing} over the network")
        time.sleep(0.05)  # a poll of the network's directory (no event says "all joined")


def _checked(result: RunResult, path: Path, *, heard_from_start: bool) -> RunResult:
    """The run's result with its verdict (`check.py`, over the run's `events.jsonl`)."""
    started = time.perf_counter()
    verdicts = check.check_file(path, heard_from_start=heard_from_start)
    verdict = verdicts.get(result.run, check.check([]))
    return dataclasses.replace(
        result,
        verdict=verdict.verdict,
        violations=verdict.violations,
        unverifiable=verdict.unverifiable,
        findings=tuple(check.format_verdict(result.run, verdict)[1:]),
        check_s=time.perf_counter() - started,
    )


def _drive(
    sup: rr.Supervisor,
    spec: RunSpec,
    log: _EventLog,
    work: Path,
    stop: threading.Event,
    drive: _Drive,
) -> None:
    """The run itself, on a started tree: workload and faults, then unload and count."""
    plan = spec.plan
    home = plan.hosts.home if plan.hosts is not None else None
    managers = [m.name for m in plan.managers() if plan.host_of(m.name) == home]
    if spec.observe:
        from rr_actors_lab.observe import observe  # noqa: PLC0415 - its extra's

        observer = observe(sup, host="127.0.0.1", port=0)
        print(json.dumps({"observe": observer.url}), flush=True)  # noqa: T201 - to the experiment
    drive.clients = [
        Client(
            i, sup, plan, spec.seed, run_dir=work, on_failure=stop.set, step_span=drive.step_span
        )
        for i in plan.workload.callers()
    ]
    t0, drive.wall_t0 = time.monotonic(), time.time()
    injector = drive.injector = Injector(
        sup,
        plan,
        fault_schedule(plan, spec.seed),
        t0=t0,
        wall_t0=drive.wall_t0,
        hosts=(drive.network, {h.name: h for h in drive.hosts}),
        step_span=drive.step_span,
    )
    log.injector = injector
    for client in drive.clients:
        client.start(t0=t0, deadline=t0 + plan.duration)
    injector.start()
    stop.wait(plan.duration)
    drive.end_s = time.monotonic() - t0
    injector.stop()
    if not stop.is_set():
        wait_all_serving(sup, managers, plan.recovery_timeout)
        for host in drive.hosts:
            with contextlib.suppress(rr.RrError):
                host.ask(
                    "wait_serving",
                    within=plan.recovery_timeout + 5.0,
                    timeout=plan.recovery_timeout,
                )
    for client in drive.clients:
        client.stop(timeout=0.5 if stop.is_set() else plan.workload.timeout)
    failed = next((c.failure for c in drive.clients if c.failure is not None), None)
    if failed is not None:  # a request a client could not build: the run fails with it
        raise failed
    drive.entries, drive.unread = count_entries(sup, managers, drive.clients)
    for host in drive.hosts:
        try:
            entries, unread = host.ask("count", within=10.0)
        except rr.RrError:
            entries, unread = (
                0,
                sum(1 for m in plan.managers() if plan.host_of(m.name) == host.name),
            )
        drive.entries, drive.unread = drive.entries + entries, drive.unread + unread
    if spec.record_events:
        sup.flush_events()
        for host in drive.hosts:
            with contextlib.suppress(rr.RrError):
                host.ask("flush", within=10.0)
    drive.until_s = time.monotonic() - t0


def count_entries(
    sup: rr.Supervisor,
    managers: list[str],
    clients: list[Client],
    settle: float = SETTLE_TIMEOUT,
) -> tuple[int, int]:
    """Rows left in the catalogs that can be read; how many managers' could not be.

    Counted again until no row is left or `settle` seconds passed (`SETTLE_TIMEOUT`):
    what reconciling releases after a late restart is not counted as left.
    """
    deadline = runtime.monotonic() + settle
    while True:
        total, unread = _count_once(sup, managers, clients)
        if total == 0 or runtime.monotonic() >= deadline:
            return total, unread
        runtime.sleep(0.05)  # a poll of the catalogs (no event says "reconciled")


def _count_once(sup: rr.Supervisor, managers: list[str], clients: list[Client]) -> tuple[int, int]:
    total = unread = 0
    for name in managers:
        try:
            total += int(sup.run_in(name, _catalog_size))
        except rr.RrError:
            unread += 1  # not running (a temporary one killed, a gave-up subtree)
    for client in clients:
        total += _catalog_size(client.registrar)
    return total, unread


def _result(
    spec: RunSpec,
    log: _EventLog,
    drive: _Drive,
    *,
    leaked: int,
    run_dir: Path,
) -> RunResult:
    plan = spec.plan
    injector, clients = drive.injector, drive.clients
    assert injector is not None
    wall_t0, end_s, until_s = drive.wall_t0, drive.end_s, drive.until_s
    seen = log.seen
    managers = [m.name for m in plan.managers()]
    records = sorted(
        injector.records,
        key=lambda r: (r.scheduled_s if r.scheduled_s is not None else float("inf"), r.fault),
    )
    down = metrics.down_intervals(seen, managers, wall_t0, records, injector.resumed, until=until_s)
    calls = sorted((c for client in clients for c in client.calls), key=lambda c: c.start_s)
    client_recoveries = [r for client in clients for r in client.recoveries]
    finished = [
        dataclasses.replace(
            record,
            recovery_s=metrics.recovery_time(
                record,
                down,
                seen,
                wall_t0,
                client_recoveries,
                load_error_until=_load_error_until(record, plan, seen, wall_t0),
            ),
        )
        for record in records
    ]
    if plan.hosts is not None:
        finished = [_between_hosts(record, plan, seen, wall_t0) for record in finished]
    heard = sorted(t for client in clients for t in client.heard)
    finished = [_unheld(record, heard, plan.workload.timeout) for record in finished]
    with (run_dir / "events.jsonl").open("a", encoding="utf-8") as out:
        for record in finished:
            line = fault_line(record, run=spec.run, seed=spec.seed, wall_t0=wall_t0)
            out.write(json.dumps(line) + "\n")
    recoveries = [f.recovery_s for f in finished if f.recovery_s is not None]
    restarts, supervisor_restarts = metrics.restarts(seen, managers)
    restart_times = {
        name: tuple(
            e.at - wall_t0 for e in seen if isinstance(e, events.ChildRestarted) and e.child == name
        )
        for name in managers
    }
    return RunResult(
        plan=plan.name,
        setting=spec.setting,
        value=spec.value,
        run=spec.run,
        repeat=spec.repeat,
        seed=spec.seed,
        version=rr.__version__,
        started_at=wall_t0,
        duration_s=end_s,
        calls_ok=sum(1 for c in calls if c.ok),
        calls_failed=sum(1 for c in calls if not c.ok),
        calls_retried=sum(1 for c in calls if c.retried),
        unavailable_s=metrics.unavailable(down, end_s),
        restarts=restarts,
        gave_up=any(
            isinstance(e, events.SupervisorGaveUp) and e.supervisor == plan.tree.name for e in seen
        ),
        recovery_median_s=metrics.percentile(recoveries, 50),
        recovery_p90_s=metrics.percentile(recoveries, 90),
        unrecovered=sum(
            1 for f in finished if not f.skipped and f.recovery_s is None and UNHELD not in f.detail
        ),
        leaked_processes=leaked,
        catalog_entries_left=drive.entries,
        events=len(seen),
        events_dropped=log.dropped,
        faults=tuple(finished),
        calls=tuple(calls),
        down={name: tuple(intervals) for name, intervals in down.items()},
        restart_times=restart_times,
        give_ups=tuple(
            (e.supervisor, e.at - wall_t0)
            for e in seen
            if isinstance(e, events.SupervisorGaveUp) and e.at - wall_t0 <= until_s
        ),
        supervisor_restarts=supervisor_restarts,
        catalogs_unread=drive.unread,
        hosts=plan.hosts.names if plan.hosts is not None else (),
    )


def _between_hosts(
    record: FaultRecord, plan: Plan, seen: list[events.Event], wall_t0: float
) -> FaultRecord:
    """A fault between hosts with its time to fail, time to heal and recovery."""
    if record.kind not in HOST_KINDS:
        return record
    assert plan.hosts is not None
    fault = plan.faults[record.fault]
    hit = metrics.affected_hosts(record.kind, record.target, plan.hosts.names, fault.hosts)
    providers = {m.name for m in plan.managers() if plan.host_of(m.name) in hit}
    fail_s, heal_s, recovery_s = metrics.host_fault_times(
        record, providers, fault.for_s or 0.0, seen, wall_t0
    )
    return dataclasses.replace(record, fail_s=fail_s, heal_s=heal_s, recovery_s=recovery_s)


UNHELD = "no client held it"
"""Said of a killed resource process about which no client heard: nothing to recover."""


def _unheld(record: FaultRecord, heard: list[float], window: float) -> FaultRecord:
    """Mark a `kill_resource` that no client heard about (within `window` s) as unheld."""
    if record.kind != "kill_resource" or record.injected_s is None or record.recovery_s:
        return record
    start = record.injected_s
    if any(start <= t <= start + window for t in heard):
        return record
    return dataclasses.replace(record, detail=f"{record.detail}; {UNHELD}")


def _load_error_until(
    record: FaultRecord, plan: Plan, seen: list[events.Event], wall_t0: float
) -> float | None:
    """When a `load_error` fault ended: after `for`, or at its last injected failure."""
    if record.kind != "load_error" or record.injected_s is None:
        return None
    fault = plan.faults[record.fault]
    if fault.for_s is not None:
        return record.injected_s + fault.for_s
    failures = sorted(
        e.at - wall_t0
        for e in seen
        if isinstance(e, events.LoadFailed)
        and e.registrar == record.target
        and e.error_type == "InjectedLoadError"
        and e.at - wall_t0 >= record.injected_s
    )
    return failures[fault.loads - 1] if len(failures) >= fault.loads else None
