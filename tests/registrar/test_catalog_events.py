"""What `CatalogRestored` and `RegistrarStopped` say of a catalog partly still in its backup.

A restore leaves most rows in the backup (issue 34): the events list them from there as
strings, in the order a full read gives, up to `LISTED_ROWS` of each kind; above that
they count them, exactly, without reading every row (and give no digest).
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

import rr_actors as rr
from rr_actors import events
from rr_actors._registrar import life, start_registrar
from rr_actors._store.files import read_backup


class Heard:
    """The catalog events a subscription delivers."""

    def __init__(self) -> None:
        self.events: list[events.CatalogRestored | events.RegistrarStopped] = []
        self.lock = threading.Lock()

    def __call__(self, event: events.Event) -> None:
        if isinstance(event, events.CatalogRestored | events.RegistrarStopped):
            with self.lock:
                self.events.append(event)


def serve(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("res", load=lambda r: {"of": r}, unload=lambda r, s: None)


@pytest.fixture
def backup(tmp_path: Path, uid: str) -> Iterator[tuple[rr.RegistrarConfig, rr.ResourceRegistrar]]:
    """A provider's backup of 4 resources and 5 consumer ids (of registrar `app`)."""
    config = rr.RegistrarConfig(name=f"cat-{uid}", backup_path=str(tmp_path / "cat.db"))
    provider = rr.ResourceRegistrar.start(config, setup=serve)
    app = rr.ResourceRegistrar.start(f"app-{uid}")
    try:
        for n in (0, 1, 2, 3, 1):
            app.call(config.name, "res", {"n": n})
        provider.stop()
        yield config, app
    finally:
        app.stop()


def restarted(
    config: rr.RegistrarConfig, heard: Heard
) -> tuple[rr.ResourceRegistrar, events.Subscription]:
    upstream = events.publisher()
    subscription = upstream.subscribe(heard)
    return start_registrar(config, setup=serve, upstream=upstream), subscription


def test_a_restored_catalog_is_listed_as_a_full_read_of_its_backup_gives_it(
    backup: tuple[rr.RegistrarConfig, rr.ResourceRegistrar],
) -> None:
    config, _ = backup
    stored = read_backup(config.backup_path or "")
    heard = Heard()
    provider, subscription = restarted(config, heard)
    try:
        assert subscription.wait_delivered(timeout=5)
    finally:
        subscription.close()
        provider.stop()

    restored = heard.events[0]
    assert isinstance(restored, events.CatalogRestored)
    assert (True, (4, 5, 0)) == (restored.complete, restored.counts)
    assert tuple((r.id, r.server, "loaded", str(r.digest), "") for r in stored.resources) == (
        restored.resources
    )
    assert (
        tuple((qid, r.id, origin) for r in stored.resources for qid, origin in r.consumers.items())
        == restored.consumers
    )


def test_above_listed_rows_the_events_count_every_row_without_listing_or_digesting_them(
    backup: tuple[rr.RegistrarConfig, rr.ResourceRegistrar], monkeypatch: pytest.MonkeyPatch
) -> None:
    config, app = backup
    monkeypatch.setattr(life, "LISTED_ROWS", 3)
    heard = Heard()
    provider, subscription = restarted(config, heard)
    try:
        held = app.call(config.name, "res", {"n": 2})  # one row read back, one id more
        app.call(config.name, "res", {"n": 9})  # a new row
        app.unload(held.id)
        provider.stop()
        assert subscription.wait_delivered(timeout=5)
    finally:
        subscription.close()

    restored, stopped = heard.events
    assert isinstance(restored, events.CatalogRestored)
    assert isinstance(stopped, events.RegistrarStopped)
    assert [(False, (4, 5, 0), (), (), ""), (False, (5, 6, 0), (), (), "")] == [
        (e.complete, e.counts, e.resources, e.consumers, e.digest) for e in (restored, stopped)
    ]
