"""Reconciliation's edges (issue 21): real manager processes, real SIGKILLs, real backups.

- A consumer stopped for good while its provider was down holds nothing (rule 12): the
  restarted provider releases its ids, and each `unload` runs once.
- A provider's restart makes every registrar that holds ids there reconcile, not only
  those its backup names: ids lost with a whole save interval are reported `FATAL`.
- An `unload` that ran and was answered does not run again after a restart that lost
  the save interval it happened in.
"""

from __future__ import annotations

import os
import signal
import sys
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.testing import RemoteRegistrar, SharedObjects, expect_restart, intercept
from tests.support.supervising import ManualTimer, crash

pytestmark = [
    pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals"),
    pytest.mark.usefixtures("by_value"),  # (tests/conftest.py)
]


def provider_setup(unloads: Any, reconciled: Any = None) -> Callable[[rr.ResourceRegistrar], None]:
    """A provider with a server "leaf" whose unloads are recorded in `unloads`.

    `reconciled` (a shared event) is set after a `Reconcile` was handled.
    """

    def setup(registrar: rr.ResourceRegistrar) -> None:
        registrar.register_server(
            "leaf", load=lambda r: {"for": r}, unload=lambda r, _s: unloads.append(r)
        )
        if reconciled is not None:
            intercept(registrar, "reconcile", after=lambda _message: reconciled.set())

    return setup


def named(prefix: str, tmp_path: Path, **options: Any) -> rr.RegistrarConfig:
    name = f"{prefix}-{uuid.uuid4().hex[:8]}"
    return rr.RegistrarConfig(name, backup_path=tmp_path / f"{name}.db", **options)


def test_a_consumer_stopped_while_its_provider_was_down_has_its_ids_released_at_the_restart(
    managers: Callable[..., RemoteRegistrar],
    tmp_path: Path,
    process_helpers: SharedObjects,
    eventually: Callable[..., bool],
) -> None:
    unloads = process_helpers.list()
    config = named("provider", tmp_path, save_on_modify=True)
    provider = managers(config, provider_setup(unloads))
    consumer = managers(named("consumer", tmp_path, save_on_modify=True), None)
    for n in range(10):
        consumer.call(config.name, "leaf", f"device-{n}", timeout=10)
    with expect_restart(config.name):  # as its supervisor would: no death watch
        provider.kill()
    consumer.stop()  # for good: its releases cannot reach the provider

    restarted = managers(config, provider_setup(unloads))
    assert eventually(lambda: len(unloads) == 10, timeout=10)
    assert [] == restarted.server_queries("leaf")
    with expect_restart(config.name):  # as its supervisor would: no death watch
        restarted.kill()
    again = managers(config, provider_setup(unloads))

    assert [] == again.server_queries("leaf")
    assert sorted(f"device-{n}" for n in range(10)) == sorted(unloads)  # each once


def test_ids_a_provider_lost_with_its_save_interval_are_reported_fatal_to_their_consumer(
    managers: Callable[..., RemoteRegistrar],
    tmp_path: Path,
    process_helpers: SharedObjects,
    eventually: Callable[..., bool],
) -> None:
    unloads, heard = process_helpers.list(), process_helpers.list()
    config = named("provider", tmp_path, save_on_modify=False, save_interval=3600.0)
    provider = managers(config, provider_setup(unloads))
    consumer = managers(named("consumer", tmp_path, save_on_modify=True), None)

    def note(query: rr.Query, update: rr.StatusUpdate) -> None:
        heard.append((query.id, update.status))

    held = [
        consumer.call(config.name, "leaf", f"device-{n}", on_status=note, timeout=10).id
        for n in range(10)
    ]
    with expect_restart(config.name):  # as its supervisor would: no death watch
        provider.kill()  # before its first flush: the backup names no consumer
    managers(config, provider_setup(unloads))

    assert eventually(lambda: len(heard) == 10, timeout=10)
    assert sorted((q, rr.Status.FATAL) for q in held) == sorted(heard)
    assert [] == consumer.client_queries()


def test_an_answered_unload_does_not_run_again_after_a_restart_lost_the_save_interval(
    managers: Callable[..., RemoteRegistrar],
    tmp_path: Path,
    process_helpers: SharedObjects,
) -> None:
    unloads, reconciled = process_helpers.list(), process_helpers.event()
    config = named("provider", tmp_path, save_on_modify=False, save_interval=3600.0)
    provider = managers(config, provider_setup(unloads))
    consumer = managers(named("consumer", tmp_path, save_on_modify=True), None)
    kept = consumer.call(config.name, "leaf", "kept", timeout=10)
    gone = [consumer.call(config.name, "leaf", f"device-{n}", timeout=10) for n in range(5)]
    provider.save_catalog()  # the loads are on disk
    for query in gone:
        consumer.unload(query.id, timeout=10)  # answered: their unload ran
    with expect_restart(config.name):  # as its supervisor would: no death watch
        provider.kill()  # before the next flush

    restarted = managers(config, provider_setup(unloads, reconciled))
    assert reconciled.wait(10)  # the consumer told it what it holds (`kept`)
    consumer.unload(kept.id, timeout=10)

    assert sorted([f"device-{n}" for n in range(5)] + ["kept"]) == sorted(unloads)
    assert [] == restarted.server_queries("leaf")


def serve_leaf(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("leaf", load=lambda r: {"for": r}, unload=lambda _r, _s: None)


def test_a_supervised_provider_killed_before_its_first_flush_reports_every_id_fatal(
    tmp_path: Path, eventually: Callable[..., bool]
) -> None:
    # The consumer is the application's registrar in the supervisor's process.
    name = f"provider-{uuid.uuid4().hex[:8]}"
    config = rr.RegistrarConfig(
        name, backup_path=tmp_path / f"{name}.db", save_on_modify=False, save_interval=3600.0
    )
    spec = rr.ManagerSpec(name, serve_leaf, isolation="process", config=config)
    heard: list[tuple[str, rr.Status]] = []

    def note(query: rr.Query, update: rr.StatusUpdate) -> None:
        heard.append((query.id, update.status))

    with rr.Supervisor([spec], max_restarts=5, period=10.0) as sup:
        app = sup.registrar(f"app-{uuid.uuid4().hex[:8]}")
        held = [app.call(name, "leaf", n, on_status=note, timeout=10).id for n in range(10)]
        (info,) = sup.which_children()
        assert info.pid is not None
        os.kill(info.pid, signal.SIGKILL)
        sup.wait_restarted(name, timeout=10)

        assert eventually(lambda: len(heard) == 10, timeout=10)
        assert sorted((q, rr.Status.FATAL) for q in held) == sorted(heard)
        assert [] == app.client_queries()


@pytest.mark.parametrize("isolation", ["process", "thread"])
def test_a_supervised_provider_without_a_backup_restarted_reports_every_id_fatal(
    isolation: str, eventually: Callable[..., bool]
) -> None:
    # No backup: the restarted provider serves an empty catalog, so every id held there
    # was lost; its supervisor has every registrar of the tree reconcile with it.
    name = f"provider-{uuid.uuid4().hex[:8]}"
    spec = rr.ManagerSpec(name, serve_leaf, isolation=isolation)
    heard: list[tuple[str, rr.Status]] = []

    def note(query: rr.Query, update: rr.StatusUpdate) -> None:
        heard.append((query.id, update.status))

    with rr.Supervisor([spec], max_restarts=5, period=10.0) as sup:
        app = sup.registrar(f"app-{uuid.uuid4().hex[:8]}")
        held = [app.call(name, "leaf", n, on_status=note, timeout=10).id for n in range(5)]
        if isolation == "process":
            (info,) = sup.which_children()
            assert info.pid is not None
            os.kill(info.pid, signal.SIGKILL)
        else:
            crash(sup, name)  # the registrar actor dies, as a thread manager's SIGKILL
        sup.wait_restarted(name, timeout=10)

        assert eventually(lambda: len(heard) == 5, timeout=10)
        assert sorted((q, rr.Status.FATAL) for q in held) == sorted(heard)
        assert [] == app.client_queries()


def consumer_of(provider: str) -> Callable[[rr.ResourceRegistrar], None]:
    """A manager whose setup holds ten ids at `provider`."""

    def setup(registrar: rr.ResourceRegistrar) -> None:
        for n in range(10):
            registrar.call(provider, "leaf", f"device-{n}", timeout=10)

    return setup


def test_a_consumer_that_died_for_good_while_its_provider_was_down_has_its_ids_released(
    tmp_path: Path, process_helpers: SharedObjects, eventually: Callable[..., bool]
) -> None:
    unloads = process_helpers.list()
    uid = uuid.uuid4().hex[:8]
    provider, consumer = f"provider-{uid}", f"consumer-{uid}"
    timer = ManualTimer()  # the provider's restart waits for the test
    specs = [
        rr.ManagerSpec(provider, provider_setup(unloads), isolation="process"),
        rr.ManagerSpec(consumer, consumer_of(provider), isolation="process", restart="temporary"),
    ]
    sup = rr.Supervisor(
        specs, state_dir=tmp_path, backoff=rr.Backoff(initial=1.0, jitter=0.0), timer=timer
    )
    with sup:
        pids = {info.name: info.pid for info in sup.which_children()}
        os.kill(pids[provider], signal.SIGKILL)
        assert timer.wait_scheduled(1, timeout=10)  # its restart is due, not done
        os.kill(pids[consumer], signal.SIGKILL)  # for good: its death watch misses the provider
        assert eventually(
            lambda: [i.state for i in sup.which_children()] == ["restarting", "exited"],
            timeout=10,
        )
        timer.fire()
        sup.wait_restarted(provider, timeout=10)

        assert eventually(lambda: len(unloads) == 10, timeout=10)
        assert sorted(f"device-{n}" for n in range(10)) == sorted(unloads)
