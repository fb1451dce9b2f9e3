"""DESIGN rule 19: a provider that is gone and that no supervisor will restart is lost.

Each consumer's status callbacks get `FATAL` for the ids it held there (and up their
dependents, each callback once), and the consumer forgets those ids. A provider whose
supervisor restarts it is not lost. Real manager processes, real SIGKILLs, the AF_UNIX
carrier; the presence role decides it (`rr_actors/_registrar/presence.py`).
"""

from __future__ import annotations

import os
import signal
import sys
from collections.abc import Callable
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._registrar import Served
from rr_actors.testing import (
    RemoteRegistrar,
    SharedObjects,
    System,
    catalog_snapshot,
    crash,
)
from tests.support.names import named
from tests.support.supervising import process, sigkill
from tests.support.waiting import wait_for

pytestmark = [
    pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals"),
    pytest.mark.usefixtures("by_value"),  # (tests/conftest.py)
]

BOUND = 5.0
"""Seconds from a SIGKILL to the consumers' `FATAL` (measured: milliseconds)."""


def leaf_setup(unloads: Any = None) -> Callable[[rr.ResourceRegistrar], None]:
    def setup(registrar: rr.ResourceRegistrar) -> None:
        def unload(request: Any, _response: Any) -> None:
            if unloads is not None:
                unloads.append(request)

        registrar.register_server("leaf", load=lambda r: {"for": r}, unload=unload)

    return setup


def composite_setup(provider: str, server_heard: Any) -> Callable[[rr.ResourceRegistrar], None]:
    """A `composite` server whose load holds `provider/leaf` as a dependency (rule 5)."""

    def setup(registrar: rr.ResourceRegistrar) -> None:
        def load(request: Any) -> Any:
            return registrar.call(provider, "leaf", request, timeout=10).response

        def on_status(query: rr.Query, update: rr.StatusUpdate) -> None:
            server_heard.append((query.id, update.status))

        registrar.register_server(
            "composite", load=load, unload=lambda _r, _s: None, on_status=on_status
        )

    return setup


class Heard:
    """A status callback that records `(query id, status, source)`; `fn` to pass on."""

    def __init__(self, records: Any) -> None:
        self.records = records

    def __call__(self, query: rr.Query, update: rr.StatusUpdate) -> None:
        self.records.append((query.id, update.status, update.source))


def test_an_unsupervised_provider_killed_is_lost_its_consumers_hear_fatal_up_the_chain(
    system: System, started: list[rr.ResourceRegistrar], process_helpers: SharedObjects
) -> None:
    provider = RemoteRegistrar.start(named("provider"), system, setup=leaf_setup())
    direct_heard: list[Any] = []
    top_heard: list[Any] = []
    server_heard: list[Any] = []
    middle = rr.ResourceRegistrar.start(
        named("middle"), setup=composite_setup(provider.name, server_heard), network=system
    )
    started.append(middle)
    app = rr.ResourceRegistrar.start(named("app"))
    started.append(app)
    direct = middle.call(provider.name, "leaf", "camera", on_status=Heard(direct_heard))
    top = app.call(middle.name, "composite", "lidar", on_status=Heard(top_heard))

    assert provider.pid is not None
    os.kill(provider.pid, signal.SIGKILL)
    assert wait_for(lambda: bool(direct_heard and top_heard and server_heard), BOUND)
    provider.kill()  # (returns once its death watch went out)
    middle.client_queries()  # (a round trip: what it was told is handled)
    app.client_queries()

    source = f"{provider.name}/leaf"
    assert [(direct.id, rr.Status.FATAL, source)] == direct_heard
    assert [(top.id, rr.Status.FATAL, source)] == top_heard  # up the dependency path
    assert [(top.id, rr.Status.FATAL)] == server_heard  # the composite's on_status, once
    assert [] == [q for q in middle.client_queries() if q.serving_rr == provider.name]
    with pytest.raises(rr.UnknownQueryError):
        middle.unload(direct.id, timeout=5)
    app.unload(top.id, timeout=5)  # the dependent resource itself is still held


def test_a_consumer_in_another_process_hears_fatal_when_an_unsupervised_provider_dies(
    system: System, process_helpers: SharedObjects
) -> None:
    heard = process_helpers.list()
    provider = RemoteRegistrar.start(named("provider"), system, setup=leaf_setup())
    consumer = RemoteRegistrar.start(named("consumer"), system)
    try:
        query = consumer.call(provider.name, "leaf", "camera", on_status=Heard(heard))

        assert provider.pid is not None
        os.kill(provider.pid, signal.SIGKILL)
        assert wait_for(lambda: len(heard) > 0, BOUND)
        provider.kill()

        assert [(query.id, rr.Status.FATAL, f"{provider.name}/leaf")] == list(heard)
        assert [] == consumer.client_queries()
        with pytest.raises(rr.UnknownQueryError):
            consumer.unload(query.id, timeout=5)
    finally:
        consumer.stop()


def test_a_provider_its_supervisor_restarts_is_not_lost_its_consumers_keep_their_ids(
    supervisors: Callable[..., rr.Supervisor], tmp_path: Any
) -> None:
    name = named("provider")
    sup = supervisors([process(name, leaf_setup())], state_dir=tmp_path)
    heard: list[Any] = []
    with sup:
        app = sup.registrar(named("app"))
        first = app.call(name, "leaf", "camera", on_status=Heard(heard), timeout=10)

        sigkill(sup, name)
        sup.wait_restarted(name, timeout=15)
        again = app.call(name, "leaf", "lidar", timeout=10)  # calls succeed again
        app.unload(first.id, timeout=10)  # it kept its id (rule 15)
        app.unload(again.id, timeout=10)

        assert [] == heard
        assert [] == sup.run_in(name, lambda r: r.server_queries("leaf"))


def test_providers_of_a_supervisor_that_gave_up_are_lost(
    supervisors: Callable[..., rr.Supervisor],
) -> None:
    crashing, sibling = named("crashing"), named("sibling")
    sup = supervisors(  # no restart allowed: the first crash gives up
        [process(sibling, leaf_setup()), process(crashing, leaf_setup())], max_restarts=0
    )
    heard: list[Any] = []
    sup.start()
    app = sup.registrar(named("app"))
    at_crashing = app.call(crashing, "leaf", "camera", on_status=Heard(heard), timeout=10)
    at_sibling = app.call(sibling, "leaf", "lidar", on_status=Heard(heard), timeout=10)

    sigkill(sup, crashing)
    assert wait_for(lambda: sup.gave_up is not None and len(heard) == 2, 15)
    app.client_queries()

    assert sorted(
        [
            (at_crashing.id, rr.Status.FATAL, f"{crashing}/leaf"),
            (at_sibling.id, rr.Status.FATAL, f"{sibling}/leaf"),
        ]
    ) == sorted(heard)
    assert [] == app.client_queries()
    with pytest.raises(rr.UnknownQueryError):
        app.unload(at_crashing.id, timeout=5)


def test_a_provider_lost_twice_reports_each_callback_once_and_unloads_once(
    started: list[rr.ResourceRegistrar],
) -> None:
    unloads: list[Any] = []
    provider = rr.ResourceRegistrar.start(named("provider"), setup=leaf_setup(unloads))
    server_heard: list[Any] = []
    middle = rr.ResourceRegistrar.start(
        named("middle"), setup=composite_setup(provider.name, server_heard)
    )
    app = rr.ResourceRegistrar.start(named("app"))
    started.extend([provider, middle, app])
    direct_heard: list[Any] = []
    top_heard: list[Any] = []
    direct = middle.call(provider.name, "leaf", "camera", on_status=Heard(direct_heard))
    top = app.call(middle.name, "composite", "lidar", on_status=Heard(top_heard))

    for _ in range(2):  # as a carrier and the death watch may both say it
        Served(middle).peer_lost(provider.name)  # middle: its provider is lost
        Served(provider).peer_lost(middle.name)  # provider: its consumer is lost
    assert wait_for(lambda: bool(direct_heard and top_heard and server_heard), BOUND)
    assert wait_for(lambda: len(unloads) == 2, BOUND)
    for registrar in (middle, provider, app):
        registrar.client_queries()  # (round trips: both messages were handled)

    assert [(direct.id, rr.Status.FATAL, f"{provider.name}/leaf")] == direct_heard
    assert [(top.id, rr.Status.FATAL, f"{provider.name}/leaf")] == top_heard
    assert [(top.id, rr.Status.FATAL)] == server_heard
    assert ["camera", "lidar"] == sorted(unloads)  # each resource's unload, once
    assert [] == [r for r in catalog_snapshot(provider).resources if r.server == "leaf"]
    assert () == catalog_snapshot(middle).clients  # (its invariants hold: checked)


def test_an_unsupervised_registrar_of_this_process_that_dies_is_lost_for_other_processes(
    system: System, process_helpers: SharedObjects
) -> None:
    heard = process_helpers.list()
    provider = rr.ResourceRegistrar.start(named("provider"), setup=leaf_setup(), network=system)
    consumer = RemoteRegistrar.start(named("consumer"), system)
    try:
        query = consumer.call(provider.name, "leaf", "camera", on_status=Heard(heard))

        crash(provider)  # its actor dies; nobody restarts it
        assert wait_for(lambda: len(heard) > 0, BOUND)

        assert [(query.id, rr.Status.FATAL, f"{provider.name}/leaf")] == list(heard)
        assert [] == consumer.client_queries()
    finally:
        consumer.stop()


def test_managers_of_a_nested_supervisor_that_gave_up_and_is_restarted_are_not_lost(
    supervisors: Callable[..., rr.Supervisor], tmp_path: Any
) -> None:
    name = named("provider")
    nested = rr.SupervisorSpec(named("nested"), (process(name, leaf_setup()),), max_restarts=0)
    sup = supervisors([nested], state_dir=tmp_path)  # restarts the nested one (permanent)
    heard: list[Any] = []
    with sup:
        app = sup.registrar(named("app"))
        held = app.call(name, "leaf", "camera", on_status=Heard(heard), timeout=10)

        sigkill(sup, name)  # the nested supervisor gives up at once; its parent restarts it
        sup.wait_restarted(nested.name, timeout=15)
        sup.wait_restarted(name, timeout=15)
        app.unload(held.id, timeout=10)  # still held: not lost

        assert [] == heard


def test_managers_of_a_nested_supervisor_that_gave_up_for_good_are_lost(
    supervisors: Callable[..., rr.Supervisor],
) -> None:
    name = named("provider")
    nested = rr.SupervisorSpec(
        named("nested"), (process(name, leaf_setup()),), max_restarts=0, restart="temporary"
    )
    sup = supervisors([nested])
    heard: list[Any] = []
    with sup:
        app = sup.registrar(named("app"))
        held = app.call(name, "leaf", "camera", on_status=Heard(heard), timeout=10)

        sigkill(sup, name)  # it gives up; a temporary supervisor is not restarted
        assert wait_for(lambda: len(heard) > 0, 15)

        assert [(held.id, rr.Status.FATAL, f"{name}/leaf")] == heard
        with pytest.raises(rr.UnknownQueryError):
            app.unload(held.id, timeout=5)
