"""A registrar that starts after a death watch went out still hears it (rule 19).

The death watch used to be a broadcast at one instant: a registrar that was down then
(restarting, restoring its catalog) never heard it, restored the ids of the lost
registrar, and held them for good (issue 32: the kill-heavy plan's `end` findings). Now
every process keeps a membership (`rr_actors._core.membership`): a mark is recorded before
it is sent, and a registrar that starts hears every name gone for good then, as if it
had heard the mark (Erlang: monitoring a process that is already dead gives 'DOWN' at
once). Registrars of this process, real crashes (`testing.crash`), the restarts done by
the test in its own order.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path

import rr_actors as rr
from rr_actors.testing import crash, expect_restart


def _backed(name: str, tmp_path: Path) -> rr.RegistrarConfig:
    return rr.RegistrarConfig(
        name=name, backup_path=str(tmp_path / f"{name}.db"), save_on_modify=True
    )


def test_a_provider_restored_after_its_consumer_died_for_good_releases_its_ids(
    tmp_path: Path, uid: str
) -> None:
    config = _backed(f"prov-{uid}", tmp_path)
    unloaded = threading.Event()

    def setup(registrar: rr.ResourceRegistrar) -> None:
        registrar.register_server("leaf", load=lambda r: r, unload=lambda _r, _s: unloaded.set())

    provider = rr.ResourceRegistrar.start(config, setup=setup)
    consumer = rr.ResourceRegistrar.start(f"cons-{uid}")
    consumer.call(provider.name, "leaf", "x", timeout=10)
    with expect_restart(provider.name):  # down for a restart: no death watch
        crash(provider)
    crash(consumer)  # gone for good while the provider is down: its death watch goes out now

    back = rr.ResourceRegistrar.start(config, setup=setup)  # restores the consumer's id
    try:
        assert unloaded.wait(10)  # released (its unload ran): it heard the mark at its start
        assert [] == back.server_queries("leaf")
    finally:
        back.stop()


def test_a_consumer_restored_after_its_provider_died_for_good_is_told_fatal(
    tmp_path: Path, uid: str, eventually: Callable[..., bool]
) -> None:
    config = _backed(f"cons-{uid}", tmp_path)
    provider = rr.ResourceRegistrar.start(f"prov-{uid}")
    provider.register_server("leaf", load=lambda r: r, unload=lambda _r, _s: None)
    consumer = rr.ResourceRegistrar.start(config)
    query = consumer.call(provider.name, "leaf", "x", timeout=10)
    with expect_restart(consumer.name):  # down for a restart: no death watch
        crash(consumer)
    crash(provider)  # gone for good while the consumer is down

    back = rr.ResourceRegistrar.start(config)  # restores the id held at the provider
    try:
        assert eventually(lambda: [] == back.client_queries(), timeout=10)  # FATAL, forgotten
        try:
            back.unload(query.id, timeout=10)
        except rr.UnknownQueryError:
            pass  # forgotten: it is not held any more
        else:
            raise AssertionError("a query held at a lost provider was still held")
    finally:
        back.stop()
