"""Restore after a real crash, and in-doubt loads (rules 15-16; `_store/restore.py`).

Crashes are real: a child process (forkserver context) runs the registrars, reports what
it did over a pipe and is SIGKILLed; the test process then starts fresh registrars on the
same backups. The child's functions are in `persisting.py` (sent by reference).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import rr_actors as rr
from rr_actors.testing import catalog_snapshot
from tests.support.durable_pair import leaf_load, noop_unload, pair_backups, start
from tests.support.persisting import (
    Recorder,
    RunAndKill,
    child_hold,
    child_released_not_unloaded,
    child_stuck_in_load,
    ordered,
)
from tests.support.waiting import wait_for


def test_a_registrar_restarted_after_a_kill_restores_every_served_query_and_client_record(
    tmp_path: Path, run_and_kill: RunAndKill, started: list[rr.ResourceRegistrar]
) -> None:
    names, paths = pair_backups(tmp_path)
    [(_, provider_view, consumer_view)] = run_and_kill(child_hold, names, tuple(map(str, paths)))

    provider = start(started, names[0], paths[0], save_on_modify=True)
    provider.register_server("leaf", load=leaf_load, unload=noop_unload)
    provider.register_server("nested", load=leaf_load, unload=noop_unload)
    consumer = start(started, names[1], paths[1], save_on_modify=True)

    assert (True, True) == (provider.restored, consumer.restored)
    assert ordered(provider_view) == ordered(catalog_snapshot(provider))
    assert ordered(consumer_view) == ordered(catalog_snapshot(consumer))


def test_setup_code_sees_the_restored_queries_before_it_registers_its_servers(
    tmp_path: Path, run_and_kill: RunAndKill, started: list[rr.ResourceRegistrar]
) -> None:
    names, paths = pair_backups(tmp_path)
    [((first, second, _), _, _)] = run_and_kill(child_hold, names, tuple(map(str, paths)))
    provider = start(started, names[0], paths[0], save_on_modify=True)
    provider.register_server("leaf", load=leaf_load, unload=noop_unload)

    held = provider.server_queries("leaf")

    assert {first, second} <= {q.id for q in held}


def test_consumer_ids_issued_before_a_kill_unload_after_the_restart(
    tmp_path: Path, run_and_kill: RunAndKill, started: list[rr.ResourceRegistrar]
) -> None:
    names, paths = pair_backups(tmp_path)
    [((first, second, _), _, _)] = run_and_kill(child_hold, names, tuple(map(str, paths)))
    provider = start(started, names[0], paths[0], save_on_modify=True)
    leaf = Recorder()
    provider.register_server("leaf", load=leaf.load, unload=leaf.unload)
    provider.register_server("nested", load=leaf.load, unload=noop_unload)
    consumer = start(started, names[1], paths[1], save_on_modify=True)

    consumer.unload(first)
    consumer.unload(second)

    assert [{"a": 1, "b": [1, 2]}] == leaf.unloads


def test_a_nested_resource_restored_after_a_kill_releases_its_dependency_when_unloaded(
    tmp_path: Path, run_and_kill: RunAndKill, started: list[rr.ResourceRegistrar]
) -> None:
    names, paths = pair_backups(tmp_path)
    [((_, _, third), _, _)] = run_and_kill(child_hold, names, tuple(map(str, paths)))
    provider = start(started, names[0], paths[0], save_on_modify=True)
    leaf, nested = Recorder(), Recorder()
    provider.register_server("leaf", load=leaf.load, unload=leaf.unload)
    provider.register_server("nested", load=nested.load, unload=nested.unload)
    consumer = start(started, names[1], paths[1], save_on_modify=True)

    consumer.unload(third)

    assert ([{"sub": "x"}], ["x"]) == (leaf.unloads, nested.unloads)


def test_an_equal_request_after_a_restart_in_another_process_reuses_the_restored_resource(
    tmp_path: Path, run_and_kill: RunAndKill, started: list[rr.ResourceRegistrar]
) -> None:
    # The child hashed its strings with another seed: only requests are stored, never hashes.
    names, paths = pair_backups(tmp_path)
    run_and_kill(child_hold, names, tuple(map(str, paths)))
    provider = start(started, names[0], paths[0], save_on_modify=True)
    leaf = Recorder()
    provider.register_server("leaf", load=leaf.load, unload=leaf.unload)
    provider.register_server("nested", load=leaf.load, unload=noop_unload)
    consumer = start(started, names[1], paths[1], save_on_modify=True)

    query = consumer.call(names[0], "leaf", {"b": [1, 2], "a": 1})

    assert ([], {"leaf": {"a": 1, "b": [1, 2]}}) == (leaf.loads, query.response)


def test_a_load_killed_inside_its_callback_is_reported_in_doubt_after_the_restart(
    tmp_path: Path, run_and_kill: RunAndKill, started: list[rr.ResourceRegistrar]
) -> None:
    names, paths = pair_backups(tmp_path)
    run_and_kill(child_stuck_in_load, names, tuple(map(str, paths)))

    provider = start(started, names[0], paths[0], save_on_modify=True)

    assert [("stuck", {"job": 7})] == [(q.server, q.request) for q in provider.in_doubt]


def test_the_dependency_of_an_in_doubt_load_is_released_after_the_restart(
    tmp_path: Path,
    run_and_kill: RunAndKill,
    started: list[rr.ResourceRegistrar],
    eventually: Callable[..., bool],
) -> None:
    names, paths = pair_backups(tmp_path)
    run_and_kill(child_stuck_in_load, names, tuple(map(str, paths)))
    provider = start(started, names[0], paths[0], save_on_modify=True)
    leaf = Recorder()

    provider.register_server("leaf", load=leaf.load, unload=leaf.unload)

    assert leaf.unloaded.wait(5)
    assert eventually(lambda: not catalog_snapshot(provider).resources)
    assert [{"dependency of": {"job": 7}}] == leaf.unloads


def test_a_registrar_without_in_doubt_loads_reports_none(
    tmp_path: Path, run_and_kill: RunAndKill, started: list[rr.ResourceRegistrar]
) -> None:
    names, paths = pair_backups(tmp_path)
    run_and_kill(child_hold, names, tuple(map(str, paths)))

    provider = start(started, names[0], paths[0], save_on_modify=True)

    assert () == provider.in_doubt


def test_a_resource_whose_last_consumer_left_before_a_kill_is_unloaded_after_the_restart(
    tmp_path: Path, run_and_kill: RunAndKill, started: list[rr.ResourceRegistrar]
) -> None:
    # Found by `rr-actors check` on the killheavy plan: the release was written, the
    # unload had not begun; the restored resource (loaded, no consumer) stayed forever,
    # holding its dependencies at other registrars.
    names, paths = pair_backups(tmp_path)
    [query_id] = run_and_kill(child_released_not_unloaded, names, tuple(map(str, paths)))
    provider = start(started, names[0], paths[0], save_on_modify=True)
    leaf = Recorder()
    provider.register_server("leaf", load=leaf.load, unload=leaf.unload)
    provider.register_server("nested", load=leaf.load, unload=noop_unload)

    assert leaf.unloaded.wait(10)
    assert [{"released": 1}] == leaf.unloads
    assert wait_for(lambda: not catalog_snapshot(provider).resources, timeout=10)
    assert query_id not in {q.id for q in provider.server_queries("leaf")}
