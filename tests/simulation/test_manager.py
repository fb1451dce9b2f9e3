"""Manager processes in a simulation: the real supervisor starts, restarts and stops them
as simulated processes (`runtime.manager_process`), their catalogs restored from real
SQLite backups."""

from __future__ import annotations

import shutil
import signal
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cloudpickle
import pytest

import rr_actors as rr
from rr_actors import simulation
from rr_actors._core import runtime
from rr_actors._process.manager import ManagerProcess
from rr_actors._store.restore import read_backup
from rr_actors.config import RegistrarConfig
from rr_actors.testing import MemoryNetwork
from tests.support.durable_pair import new_store

pytest.importorskip("greenlet")  # (the simulation extra)


def leaf_setup(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("leaf", load=lambda r: f"leaf {r}", unload=lambda *_: None)


def failing_setup(registrar: rr.ResourceRegistrar) -> None:
    raise ValueError("no camera")


def served(supervisor: rr.Supervisor) -> list[Any]:
    return sorted(
        supervisor.run_in(
            "provider", lambda r: [q.request for q in r.server_queries("leaf")], timeout=5.0
        )
    )


def with_tree(
    body: Callable[[rr.Supervisor, rr.ResourceRegistrar], Any], **spec: Any
) -> Callable[[], Any]:
    """A scenario: one process manager `provider` (a backup in a temporary folder) under
    a supervisor on an in-memory network, a consumer `app` in the supervisor's process."""

    def scenario() -> Any:
        folder = tempfile.mkdtemp(prefix="rr-sim-manager-")
        network = MemoryNetwork("simulated")
        try:
            manager = rr.ManagerSpec(
                "provider", setup=spec.pop("setup", leaf_setup), isolation="process", **spec
            )
            supervisor = rr.Supervisor(manager, state_dir=folder, network=network, name="root")
            supervisor.start()
            app = supervisor.registrar("app")
            try:
                return body(supervisor, app)
            finally:
                supervisor.stop()
                app.stop()
        finally:
            network.close()
            shutil.rmtree(folder, ignore_errors=True)

    return scenario


TICKS: list[float] = []
"""When `ticking_setup`'s thread ticked (virtual seconds): while its manager process lives."""


def ticking_setup(registrar: rr.ResourceRegistrar) -> None:
    """A leaf whose process ticks every 0.1 s on a thread of its own."""

    def tick() -> None:
        while True:
            simulation.sleep(0.1)
            TICKS.append(simulation.now())

    leaf_setup(registrar)
    runtime.Thread(target=tick, name="tick", daemon=True).start()


def test_a_manager_process_dies_with_the_process_that_started_it() -> None:
    # (as PR_SET_PDEATHSIG makes a real one: a program killed takes its managers along)
    TICKS.clear()

    def program(folder: str, network: MemoryNetwork, started: Any) -> None:
        manager = rr.ManagerSpec("provider", setup=ticking_setup, isolation="process")
        supervisor = rr.Supervisor(manager, state_dir=folder, network=network, name="root")
        supervisor.start()
        started.put(supervisor.child("provider").pid)

    def scenario() -> Any:
        folder = tempfile.mkdtemp(prefix="rr-sim-manager-")
        network = MemoryNetwork("simulated")
        try:
            started: Any = runtime.SimpleQueue()
            pid = simulation.start_process(
                lambda: program(folder, network, started), name="program"
            )
            manager = started.get()
            simulation.sleep(0.55)
            simulation.kill(pid)
            killed_at, ticked = simulation.now(), len(TICKS)
            simulation.sleep(1.0)
            return manager, pid, ticked, [t for t in TICKS if t > killed_at]
        finally:
            network.close()
            shutil.rmtree(folder, ignore_errors=True)

    manager, program_pid, ticked, after = simulation.run(scenario, seed=1).value

    assert manager != program_pid
    assert ticked >= 4  # (it ticked while its program lived)
    assert [] == after  # (and not once after its program was killed)


def test_a_manager_runs_in_a_simulated_process_of_its_own() -> None:
    def body(supervisor: rr.Supervisor, app: rr.ResourceRegistrar) -> Any:
        query = app.call("provider", "leaf", "x")
        pid = supervisor.child("provider").pid
        inside = supervisor.run_in("provider", lambda r: simulation.pid(), timeout=5.0)
        return query.response, pid, inside, simulation.pid()

    assert ("leaf x", 2, 2, 1) == simulation.run(with_tree(body), seed=1).value


def test_a_killed_manager_is_restarted_by_the_supervisor_with_its_catalog_restored() -> None:
    def body(supervisor: rr.Supervisor, app: rr.ResourceRegistrar) -> Any:
        app.call("provider", "leaf", "x")
        simulation.kill(supervisor.child("provider").pid)
        info = supervisor.wait_restarted("provider", timeout=10.0)
        return info.pid, info.last_exit, served(supervisor)

    for seed in range(20):
        run = simulation.run(with_tree(body), seed=seed, preempt=0.1)
        assert (3, "killed by SIGKILL", ["x"]) == run.value, f"seed {seed}"


def test_a_killed_manager_s_parent_hears_of_its_end_once_what_it_served_is_gone() -> None:
    # (as a kernel closes a SIGKILLed process's descriptors, its name lock among them,
    # before its parent's sentinel says it ended: the restart finds the name free; before,
    # the end was told first and a restart that ran before the rest failed with
    # DuplicateNameError: `rr-actors experiment simslow --simulate --seeds 203`)
    def scenario() -> list[str]:
        network = simulation.SimulatedNetwork()
        try:
            heard: Any = runtime.SimpleQueue()
            handle = ManagerProcess.start(
                "provider",
                cloudpickle.dumps(leaf_setup),
                RegistrarConfig(name="provider"),
                network.address,
                start_timeout=10.0,
                heartbeat=None,
                heartbeat_timeout=None,
                on_exit=lambda _: heard.put(network.link().names()),
            )
            handle.kill()
            served: list[str] = heard.get(timeout=10.0)
            return served
        finally:
            network.close()

    for seed in range(10):  # (before: still served at seeds 2, 3, 5, 7 and 8)
        assert [] == simulation.run(scenario, seed=seed, preempt=1.0).value, f"seed {seed}"


def test_a_hung_manager_is_killed_by_its_heartbeat_and_restarted() -> None:
    def body(supervisor: rr.Supervisor, app: rr.ResourceRegistrar) -> Any:
        app.call("provider", "leaf", "x")
        simulation.kill(supervisor.child("provider").pid, signal.SIGSTOP)
        began = simulation.now()
        info = supervisor.wait_restarted("provider", timeout=10.0)
        return info.last_exit.split(":")[0], simulation.now() - began, served(supervisor)

    hung, took, held = simulation.run(with_tree(body, heartbeat=0.5), seed=4).value

    assert "hung" == hung
    assert 1.0 < took < 5.0  # (its bound: three periods of silence)
    assert ["x"] == held


def test_a_manager_stopped_and_continued_answers_what_was_asked_meanwhile() -> None:
    def body(supervisor: rr.Supervisor, app: rr.ResourceRegistrar) -> Any:
        pid = supervisor.child("provider").pid
        simulation.kill(pid, signal.SIGSTOP)
        outcome: list[Any] = []

        def ask() -> None:
            outcome.append(app.call("provider", "leaf", "x", timeout=30.0).response)
            outcome.append(simulation.now())

        asking = simulation_thread(ask)
        simulation.sleep(5.0)
        simulation.kill(pid, signal.SIGCONT)
        asking.join()
        return outcome[0], outcome[1] >= 5.0, supervisor.child("provider").restarts

    assert ("leaf x", True, 0) == simulation.run(with_tree(body, heartbeat=None), seed=2).value


def simulation_thread(target: Callable[[], None]) -> Any:
    from rr_actors._core import runtime  # noqa: PLC0415

    thread = runtime.Thread(target=target, name="asker")
    thread.start()
    return thread


def test_a_setup_that_raises_fails_the_start_with_its_traceback() -> None:
    def scenario() -> str:
        network = MemoryNetwork("simulated")
        try:
            manager = rr.ManagerSpec("provider", setup=failing_setup, isolation="process")
            try:
                rr.Supervisor(manager, network=network, name="root").start()
            except rr.SupervisorGaveUpError as exc:
                return str(exc.__cause__)
            return "started"
        finally:
            network.close()

    reason = simulation.run(scenario, seed=1).value

    assert "failed to start" in reason
    assert "ValueError: no camera" in reason


def test_a_stopped_manager_exits_cleanly() -> None:
    def body(supervisor: rr.Supervisor, app: rr.ResourceRegistrar) -> Any:
        query = app.call("provider", "leaf", "x")
        app.unload(query.id)
        supervisor.stop()
        return supervisor.child("provider").last_exit

    assert "shutdown" == simulation.run(with_tree(body), seed=1).value


def test_a_manager_s_events_reach_the_supervisor_s_subscribers_while_they_listen() -> None:
    def body(supervisor: rr.Supervisor, app: rr.ResourceRegistrar) -> Any:
        heard: list[Any] = []
        with supervisor.subscribe(heard.append) as subscription:
            query = app.call("provider", "leaf", "x")
            app.unload(query.id)
            assert supervisor.flush_events(timeout=5.0)
            subscription.wait_delivered(timeout=5.0)
        return sorted(
            {type(e).__name__ for e in heard if getattr(e, "registrar", None) == "provider"}
        )

    kinds = simulation.run(with_tree(body), seed=1).value

    assert ["ConsumerAdded", "ConsumerReleased", "ResourceLoaded", "ResourceUnloaded"] == kinds


def commit_one(path: Path) -> list[str]:
    """Commit a resource with a consumer to a new backup at `path`; the files beside it
    just after the commit (the store is closed then)."""
    store, catalog = new_store(path)
    catalog.begin_load("r1", "leaf", {"rid": "r1"})
    catalog.finish_load("r1", {"pid": 1})
    catalog.add_consumer("r1", "q1", "C")
    store.write(catalog.drain_changes())
    files = sorted(p.name for p in path.parent.iterdir())
    store.close(erase=False)
    return files


def test_a_simulated_backup_keeps_no_commit_count_beside_its_log_and_its_commits_all_the_same(
    tmp_path: Path,
) -> None:
    """`runtime.guards_files`: nothing but the simulation touches its backups, so their
    logs are never cut short and no count is kept to tell (a real store keeps one)."""
    (tmp_path / "real").mkdir()
    (tmp_path / "sim").mkdir()

    real = commit_one(tmp_path / "real" / "b.db")
    simulated = simulation.run(lambda: commit_one(tmp_path / "sim" / "b.db"), seed=1).value

    assert "b.db-commits" in real
    assert ["b.db", "b.db-shm", "b.db-wal"] == simulated
    restored = read_backup(tmp_path / "sim" / "b.db").resources
    assert [("r1", ["q1"])] == [(r.id, list(r.consumers)) for r in restored]
