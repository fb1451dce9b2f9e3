"""A supervised tree of manager processes on the simulation, under kills, over many seeds.

Three managers in simulated processes (`rr_actors.simulation`: each its own pid, its own
per-process state, its backup a real SQLite file) under the real supervisor, on the
in-memory network; clients of a registrar in the supervisor's process call them while a
fault thread SIGKILLs managers (a kill runs no `finally` block and keeps what committed).
Every effect of a `load`/`unload` callback and every answer a client got goes to one
journal, in the order they happened; the rules are checked on it:

- nothing acknowledged is lost: a query a client got is served after the restores, or
  its consumer was told (a status);
- nothing is loaded twice: no `load` of a request while a client holds an answer for it;
- nothing is left: once every client released what it held, nothing is served.
"""

from __future__ import annotations

import random
import shutil
import signal
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors import simulation
from rr_actors._core import runtime

pytest.importorskip("greenlet")  # (the simulation extra)

ROOT = Path(__file__).resolve().parent.parent.parent

SEEDS = range(60)
"""The seeds each scenario runs with."""

SWEEP = pytest.mark.timeout(600)
"""A sweep of `SEEDS` takes 5-10 s of CPU; under load (the suite beside other work on two
cores) its wall time is several times that, past the suite's 60 s default."""

PREEMPT = 0.05

JOURNAL: list[tuple[Any, ...]] = []
"""What happened, in order: `("load" | "unload", registrar, request, pid)`, `("ack",
request, query id)`, `("release", request, query id)`, `("status", query id, status)`,
`("kill", name, pid)`. One list for every simulated process (one OS process)."""


def _note(*entry: Any) -> None:
    JOURNAL.append(entry)
    simulation.note(repr(entry))  # (the run's hash covers the history)


def camera_setup(registrar: rr.ResourceRegistrar) -> None:
    """A leaf: its loads take virtual time."""

    def load(request: Any) -> Any:
        _note("load", "camera", request, simulation.pid())
        simulation.sleep(0.2)
        return f"frames of {request}"

    def unload(request: Any, response: Any) -> None:
        _note("unload", "camera", request, simulation.pid())

    registrar.register_server("frames", load=load, unload=unload)


def filter_setup(registrar: rr.ResourceRegistrar) -> None:
    """A composite: its load calls the camera (a dependency)."""

    def load(request: Any) -> Any:
        _note("load", "filter", request, simulation.pid())
        frames = registrar.call("camera", "frames", request, timeout=5.0)
        return f"filtered {frames.response}"

    def unload(request: Any, response: Any) -> None:
        _note("unload", "filter", request, simulation.pid())

    registrar.register_server("filtered", load=load, unload=unload)


def logger_setup(registrar: rr.ResourceRegistrar) -> None:
    """A leaf of its own."""

    def load(request: Any) -> Any:
        _note("load", "logger", request, simulation.pid())
        return f"log {request}"

    def unload(request: Any, response: Any) -> None:
        _note("unload", "logger", request, simulation.pid())

    registrar.register_server("log", load=load, unload=unload)


MANAGERS = {
    "camera": ("frames", camera_setup),
    "filter": ("filtered", filter_setup),
    "logger": ("log", logger_setup),
}


def tree(
    kills: int,
    *,
    cuts: int = 0,
    hangs: int = 0,
    backups: bool = True,
    clients: int = 3,
    rounds: int = 4,
) -> Callable[[], dict[str, Any]]:
    """The scenario: the tree (its catalogs backed up, or in memory only) on a simulated
    network, `clients` clients of `rounds` calls each, `kills` kills, `cuts` cuts of a
    manager's process off the others (each healed after a while) and `hangs` SIGSTOPs
    of one (each continued after a while, unless its heartbeat killed it first), in a
    seeded order."""

    def scenario() -> dict[str, Any]:
        JOURNAL.clear()
        folder = tempfile.mkdtemp(prefix="rr-sim-tree-")
        network = simulation.SimulatedNetwork()
        try:
            faults = ["kill"] * kills + ["cut"] * cuts + ["hang"] * hangs
            return _run_tree(network, folder if backups else None, faults, clients, rounds)
        finally:
            network.close()
            shutil.rmtree(folder, ignore_errors=True)

    return scenario


def _run_tree(
    network: simulation.SimulatedNetwork,
    folder: str | None,
    faults: list[str],
    clients: int,
    rounds: int,
) -> dict[str, Any]:
    specs = [
        rr.ManagerSpec(name, setup=setup, isolation="process")
        for name, (_, setup) in MANAGERS.items()
    ]
    supervisor = rr.Supervisor(
        specs, state_dir=folder, network=network, name="root", max_restarts=1000, period=1.0
    )
    supervisor.start()
    app = supervisor.registrar("app")
    choose = random.Random(runtime.random())  # noqa: S311 - (the seed's)

    def hear(query: rr.Query, update: rr.StatusUpdate) -> None:
        _note("status", query.id, update.status.name)

    def client(number: int) -> Callable[[], None]:
        def body() -> None:
            for _ in range(rounds):
                name = choose.choice(sorted(MANAGERS))
                request = f"r{choose.randrange(2)}"
                try:
                    query = app.call(name, MANAGERS[name][0], request, timeout=10.0, on_status=hear)
                except (
                    rr.RegistrarUnavailableError,
                    rr.CallTimeoutError,
                    rr.ResourceLoadError,
                ) as exc:
                    _note("failed", (name, request), type(exc).__name__)
                    simulation.sleep(choose.uniform(0.1, 1.0))
                    continue
                _note("ack", (name, request), query.id)
                simulation.sleep(choose.uniform(0.1, 2.0))
                if not serves(name, query.id):
                    _note("lost", (name, request), query.id)
                _note("release", (name, request), query.id)
                try:
                    app.unload(query.id)
                except rr.RrError as exc:
                    _note("unload failed", query.id, type(exc).__name__)

        return body

    def serves(name: str, query_id: str) -> bool:
        """Whether manager `name` serves `query_id` (asked until it is back)."""
        server = MANAGERS[name][0]
        while True:
            try:
                return bool(
                    supervisor.run_in(
                        name,
                        lambda r: query_id in {q.id for q in r.server_queries(server)},
                        timeout=5.0,
                    )
                )
            except (rr.RegistrarUnavailableError, rr.CallTimeoutError):
                simulation.sleep(0.5)

    def inject() -> None:
        choose.shuffle(faults)
        for fault in faults:
            simulation.sleep(choose.uniform(0.2, 2.0))
            name = choose.choice(sorted(MANAGERS))
            pid = supervisor.child(name).pid
            if pid is None:
                continue
            _note(fault, name, pid)
            if fault == "kill":
                simulation.kill(pid)
            elif fault == "hang":
                simulation.kill(pid, signal.SIGSTOP)
                simulation.sleep(choose.uniform(0.1, 2.0))
                _note("continue")
                simulation.kill(pid, signal.SIGCONT)  # (nothing if it was killed as hung)
            else:
                network.partition([pid])
                simulation.sleep(choose.uniform(0.1, 3.0))
                _note("heal")
                network.heal()

    threads = [runtime.Thread(target=client(n), name=f"client-{n}") for n in range(clients)]
    threads.append(runtime.Thread(target=inject, name="faults"))
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for name in MANAGERS:  # every manager back
        while supervisor.child(name).state != "running":
            simulation.sleep(0.1)
    left = app.client_queries()
    # app stops first: a call of its that failed as its provider died or was cut off may
    # have run there, and is kept for a retry with its id while app lives (rule 17 case
    # 3); its stop gives such ids back (rule 12). What is still served then is a leak.
    app.stop()
    simulation.sleep(2.0)  # (what the last releases started settles)
    held = {
        name: sorted(
            (q.request, q.origin_rr)
            for q in supervisor.run_in(name, lambda r, s=server: r.server_queries(s), timeout=10.0)
        )
        for name, (server, _) in MANAGERS.items()
    }
    restarts = {info.name: info.restarts for info in supervisor.which_children()}
    supervisor.stop()
    return {"journal": list(JOURNAL), "held": held, "left": left, "restarts": restarts}


def broken_rules(seen: dict[str, Any], *, leaks: bool = True) -> list[str]:
    """What the run broke, in words (nothing: `[]`); `leaks`: also what was served after
    every release."""
    broken = []
    holding: dict[Any, set[str]] = {}  # (manager, request) -> query ids acknowledged, held
    told = {entry[:2] for entry in seen["journal"] if entry[0] == "status"}
    for entry in seen["journal"]:
        kind = entry[0]
        if kind == "ack":
            holding.setdefault(entry[1], set()).add(entry[2])
        elif kind == "release":
            holding[entry[1]].discard(entry[2])
        elif kind == "status" and entry[2] == "FATAL":  # (told: it is gone)
            for held in holding.values():
                held.discard(entry[1])
        elif kind == "lost" and ("status", entry[2]) not in told:
            broken.append(f"{entry[1]} lost {entry[2]} and did not say so")
        elif kind == "load" and holding.get((entry[1], entry[2])):
            broken.append(f"{entry[1]} loaded {entry[2]!r} again while it was held: {entry}")
    if leaks and any(seen["held"].values()):
        broken.append(f"served after every release: {seen['held']}")
    if seen["left"]:
        broken.append(f"the app still holds {seen['left']}")
    return broken


def seeds_where_broken(
    scenario: Callable[[], dict[str, Any]], *, leaks: bool = True
) -> dict[int, list[str]]:
    """The seeds of `SEEDS` whose run broke a rule, with what it broke (each replays:
    `simulation.run(scenario, seed=S, preempt=PREEMPT)`)."""
    failed = {}
    for seed in SEEDS:
        run = simulation.run(scenario, seed=seed, preempt=PREEMPT)
        broken = broken_rules(run.value, leaks=leaks) + list(run.errors)
        if broken:
            failed[seed] = broken
    return failed


@SWEEP
def test_a_tree_without_faults_serves_every_call_and_leaves_nothing() -> None:
    assert {} == seeds_where_broken(tree(kills=0))


@SWEEP
def test_a_tree_under_kills_loses_nothing_acknowledged_and_loads_nothing_twice() -> None:
    assert {} == seeds_where_broken(tree(kills=3))


@SWEEP
def test_a_tree_without_backups_tells_its_consumers_what_a_kill_lost_and_leaves_nothing() -> None:
    """Each acknowledged query a kill lost was told `FATAL` to its consumer; a load again
    is then no second load of something held; nothing is left served.

    A composite without a backup, killed and restarted, used to leave the ids it held at
    its providers held there for ever (its new incarnation reconciled only with the
    providers its empty catalog knows, and `lost_everything` told only the registrars
    holding ids *at* it): about a third of these seeds ended with the filter's ids still
    served at the camera. Found by this simulation; now its supervisor tells it it
    restarted with an empty catalog, and it reconciles with every registrar of the system
    (`tests/registrar/test_life.py`, `TestRestartedWithoutBackup`, the same with real
    processes)."""
    assert {} == seeds_where_broken(tree(kills=3, backups=False))


@SWEEP
def test_a_tree_under_kills_cuts_and_hangs_loses_nothing_acknowledged_and_leaves_nothing() -> None:
    """A manager's process cut off the others for a while (its callers see it
    unavailable; what was on the wire across is lost), then healed (rule 20: its
    consumers reconcile); one stopped for a while (its heartbeat kills it past 0.75 s),
    among kills."""
    assert {} == seeds_where_broken(tree(kills=2, cuts=2, hangs=2))
