"""Tests of `rr_actors/_registrar/state.py`: what a registrar commits and publishes.

Its event stream (`TestEvents`: each kind, in order, never slowing the registrar), and a
durable registrar whose backup cannot be written (`TestFullDisk`: a real full tmpfs).
"""

from __future__ import annotations

import contextlib
import errno
import functools
import logging
import os
import signal
import sqlite3
import sys
import threading
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors import events
from rr_actors._core.replies import FutureReply
from rr_actors._registrar import actor, life, start_registrar
from rr_actors._registrar.messages import RunOnActor
from rr_actors.testing import (
    RemoteRegistrar,
    SharedObjects,
    System,
    actor_ref,
    catalog_snapshot,
    crash,
    expect_restart,
    intercept,
    run_on_actor,
)
from tests.registrar.conftest import ManagerProvider, Starter
from tests.support.gating import GatedLoad
from tests.support.heard import Heard
from tests.support.small_disk import fill, mounted
from tests.support.waiting import wait_for

# -- for TestEvents ------------------------------------------------------------------------


def _answered_then_forgotten(heard: Heard, query_id: str) -> list[str]:
    """The consumer events about `query_id`, by kind, in the order they were published."""
    consumer_kinds = (
        events.CallAnswered,
        events.CallFailed,
        events.CallWithdrawn,
        events.QueryForgotten,
    )
    with heard.lock:
        return [
            type(e).__name__
            for e in heard.events
            if isinstance(e, consumer_kinds) and e.query_id == query_id
        ]


def _slow_setup(entered: Any) -> Callable[[rr.ResourceRegistrar], None]:
    def setup(registrar: rr.ResourceRegistrar) -> None:
        def load(request: Any) -> Any:
            if request == "slow":
                entered.set()
                threading.Event().wait(60)  # until the SIGKILL
            return request

        registrar.register_server("cam", load=load, unload=lambda _q, _r: None)

    return setup


def _gated_provider(started: Any) -> tuple[rr.ResourceRegistrar, threading.Event, threading.Event]:
    """A provider whose `slow` load runs until the gate opens."""
    provider = started("erm")
    entered, gate = threading.Event(), threading.Event()

    def load(request: Any) -> Any:
        entered.set()
        gate.wait(10)
        return request

    provider.register_server("slow", load=load, unload=lambda _q, _r: None)
    return provider, entered, gate


def _on_a_thread(call: Callable[[], Any]) -> threading.Thread:
    """Run `call` on a thread of its own (it fails as its registrar crashes: expected)."""

    def run() -> None:
        with contextlib.suppress(rr.RrError):
            call()

    caller = threading.Thread(target=run)
    caller.start()
    return caller


# -- for TestFullDisk ----------------------------------------------------------------------


class Provider:
    """A durable provider on a small disk, its load and unload journal, and a consumer."""

    def __init__(self, disk: Path) -> None:
        uid = uuid.uuid4().hex[:8]
        self.path = disk / "erm.db"
        self.config = rr.RegistrarConfig(
            name=f"erm-{uid}", backup_path=self.path, save_on_modify=True
        )
        self.loads: list[Any] = []
        self.unloads: list[Any] = []
        self.unloaded = threading.Event()
        self.registrar = rr.ResourceRegistrar.start(self.config)
        self.registrar.register_server("cam", load=self.load, unload=self.unload)
        self.consumer = rr.ResourceRegistrar.start(f"app-{uid}")

    def load(self, request: Any) -> Any:
        self.loads.append(request)
        return f"cam {request}"

    def unload(self, request: Any, _response: Any) -> None:
        self.unloads.append(request)
        self.unloaded.set()

    def call(self, request: Any, **kwargs: Any) -> rr.Query:
        return self.consumer.call(self.config.name, "cam", request, timeout=5, **kwargs)

    def stop(self) -> None:
        self.consumer.stop()
        self.registrar.stop()  # (each test makes room again before it ends)


def _full(disk: Path) -> Path:
    return fill(disk)


class TestEvents:
    """A registrar's event stream: each kind of event, in order, and never slowing the registrar."""

    @pytest.fixture
    def started(self, named_registrars: Starter) -> Starter:
        return named_registrars  # (conftest's)

    def test_a_load_a_shared_load_and_the_unloads_are_published_in_order(
        self, started: Any
    ) -> None:
        provider, consumer = started("erm"), started("app")
        provider.register_server("cam", load=lambda r: f"cam {r}", unload=lambda _q, _r: None)
        heard = Heard()
        with provider.subscribe(heard) as subscription:
            first = consumer.call(provider.name, "cam", 1)
            second = consumer.call(provider.name, "cam", 1)
            consumer.unload(first.id)
            consumer.unload(second.id)
            assert subscription.wait_delivered(timeout=5)

        assert [
            "ResourceLoaded",
            "ConsumerAdded",
            "ConsumerAdded",
            "ConsumerReleased",
            "ConsumerReleased",
            "ResourceUnloaded",
        ] == heard.kinds()
        [loaded] = heard.of(events.ResourceLoaded)
        assert (provider.name, "cam", first.id) == (
            loaded.registrar,
            loaded.server,
            loaded.query_id,
        )
        assert loaded.load_s >= 0.0
        assert [first.id, second.id] == [e.query_id for e in heard.of(events.ConsumerAdded)]
        assert {consumer.name} == {e.consumer for e in heard.of(events.ConsumerAdded)}
        assert [first.id, second.id] == [e.query_id for e in heard.of(events.ConsumerReleased)]
        [unloaded] = heard.of(events.ResourceUnloaded)
        assert loaded.resource_id == unloaded.resource_id

    def test_a_failed_load_is_published_with_its_error(self, started: Any) -> None:
        provider, consumer = started("erm"), started("app")

        def load(request: Any) -> Any:
            raise ValueError(f"no device {request}")

        provider.register_server("cam", load=load, unload=lambda _q, _r: None)
        heard = Heard()
        with provider.subscribe(heard) as subscription:
            with pytest.raises(rr.ResourceLoadError):
                consumer.call(provider.name, "cam", 7)
            assert subscription.wait_delivered(timeout=5)

        [failed] = heard.of(events.LoadFailed)
        assert ("cam", "ValueError", "no device 7") == (
            failed.server,
            failed.error_type,
            failed.message,
        )
        assert [] == heard.of(events.ConsumerAdded)

    def test_a_status_is_published_where_it_is_sent_and_at_each_hop_it_reaches(
        self, started: Any
    ) -> None:
        # leaf (erm) <- composite (cm) <- app: a status about the leaf climbs two hops
        erm, cm, app = started("erm"), started("cm"), started("app")
        erm.register_server("leaf", load=lambda r: r, unload=lambda _q, _r: None)

        def composite(request: Any) -> Any:
            return cm.call(erm.name, "leaf", request).id

        cm.register_server("comp", load=composite, unload=lambda _q, _r: None)
        top = app.call(cm.name, "comp", "x")
        heard = Heard()
        subscriptions = [r.subscribe(heard) for r in (erm, cm, app)]
        leaf_id = erm.server_queries("leaf")[0].id

        erm.send_status(leaf_id, rr.Status.ERROR, "overheated")

        for subscription in subscriptions:
            assert subscription.wait_delivered(timeout=5)
            subscription.close()
        [sent] = heard.of(events.StatusSent)
        assert (erm.name, leaf_id, rr.Status.ERROR, "overheated") == (
            sent.registrar,
            sent.query_id,
            sent.status,
            sent.message,
        )
        delivered = {(e.registrar, e.query_id, e.hop) for e in heard.of(events.StatusDelivered)}
        assert {(cm.name, leaf_id, 1), (app.name, top.id, 2)} == delivered
        assert all(e.latency_s >= 0.0 for e in heard.of(events.StatusDelivered))

    def test_the_loads_a_crash_cut_short_are_published_as_in_doubt_at_restore(
        self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        config = rr.RegistrarConfig(
            name=f"erm-{uuid.uuid4().hex[:8]}", backup_path=tmp_path / "erm.db", save_on_modify=True
        )
        entered, gate = threading.Event(), threading.Event()

        def load(request: Any) -> Any:
            entered.set()
            gate.wait(10)
            return request

        provider = rr.ResourceRegistrar.start(config)
        consumer = rr.ResourceRegistrar.start(f"app-{uuid.uuid4().hex[:8]}")
        provider.register_server("slow", load=load, unload=lambda _q, _r: None)
        outcome: list[Any] = []

        def call() -> None:
            try:
                consumer.call(config.name, "slow", 1)
            except rr.RrError as exc:  # the provider dies under the call
                outcome.append(exc)

        caller = threading.Thread(target=call)
        caller.start()
        assert entered.wait(10)
        with expect_restart(config.name):
            crash(provider)
        gate.set()
        caller.join(10)
        assert [rr.RegistrarUnavailableError] == [type(e) for e in outcome]
        upstream = events.publisher()
        heard = Heard()
        subscription = upstream.subscribe(heard)
        # the restore's events are published on the actor's thread as it starts, which may
        # come after `start` returned (a `wait_delivered` at once returned before they were
        # published: CI, 2026-11-24): held here until `start` returned, every time
        started = threading.Event()
        real_publish = life.publish_restored

        def publish_late(shared: Any) -> None:
            started.wait(10)
            real_publish(shared)

        monkeypatch.setattr(life, "publish_restored", publish_late)
        restarted = start_registrar(config, upstream=upstream)
        try:
            assert restarted.in_doubt  # known at once, not yet published
            assert not heard.of(events.InDoubt)
            started.set()
            assert wait_for(lambda: heard.of(events.InDoubt), 10)
            assert subscription.wait_delivered(timeout=5)
            assert [q.id for q in restarted.in_doubt] == [
                e.query_id for e in heard.of(events.InDoubt)
            ]
            assert 1 == len(heard.of(events.InDoubt))
        finally:
            subscription.close()
            restarted.stop()
            consumer.stop()

    def test_a_blocked_subscriber_does_not_slow_calls_and_its_drops_are_counted(
        self, started: Any
    ) -> None:
        provider, consumer = started("erm"), started("app")
        provider.register_server("cam", load=lambda r: r, unload=lambda _q, _r: None)
        first = consumer.call(provider.name, "cam", 0)
        release = threading.Event()
        heard = Heard()

        def blocked(event: events.Event) -> None:
            release.wait(30)
            heard(event)

        subscription = provider.subscribe(blocked, maxsize=10)
        try:
            held = [consumer.call(provider.name, "cam", 0, timeout=5) for _ in range(100)]
            for query in held:
                consumer.unload(query.id, timeout=5)
        finally:
            release.set()
        assert subscription.wait_delivered(timeout=10)
        subscription.close()

        # 200 events (100 added, 100 released); 1 was taken by the blocked callback, 10 queued.
        # Each gap is reported where it is: one, or two when the subscriber's thread took its
        # first event only after the queue had overflowed once (a loaded machine).
        assert 200 - 11 == subscription.dropped
        gaps = heard.of(events.EventsDropped)
        assert 1 <= len(gaps) <= 2
        assert subscription.dropped == sum(gap.count for gap in gaps)
        consumer.unload(first.id)

    def test_every_event_is_also_an_info_log_line_when_info_is_on(
        self, started: Any, caplog: pytest.LogCaptureFixture
    ) -> None:
        provider, consumer = started("erm"), started("app")
        provider.register_server("cam", load=lambda r: r, unload=lambda _q, _r: None)
        with caplog.at_level(logging.INFO, logger="rr_actors.events"):
            query = consumer.call(provider.name, "cam", 1)

        records = [r for r in caplog.records if r.name == "rr_actors.events"]
        assert ["ResourceLoaded", "ConsumerAdded"] == [type(r.event).__name__ for r in records]
        assert [events.describe(r.event) for r in records] == [r.getMessage() for r in records]
        consumer.unload(query.id)

    def test_with_nobody_listening_no_event_is_built(
        self, started: Any, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        provider, consumer = started("erm"), started("app")
        provider.register_server("cam", load=lambda r: r, unload=lambda _q, _r: None)
        built: list[str] = []
        real = events.ConsumerAdded.__init__

        def counting(self: Any, *args: Any, **kwargs: Any) -> None:
            built.append("ConsumerAdded")
            real(self, *args, **kwargs)

        monkeypatch.setattr(events.ConsumerAdded, "__init__", counting)
        query = consumer.call(provider.name, "cam", 1)
        consumer.unload(query.id)

        assert [] == built

    @pytest.mark.parametrize("durable", [False, True], ids=["plain", "durable"])
    def test_a_call_answered_and_its_unload_are_published_by_the_consumer_in_order(
        self, started: Any, tmp_path: Path, durable: bool
    ) -> None:
        provider = started("erm")
        backup = {"backup_path": tmp_path / "app.db", "save_on_modify": True} if durable else {}
        consumer = started("app", **backup)
        provider.register_server("cam", load=lambda r: r, unload=lambda _q, _r: None)
        heard = Heard()
        with consumer.subscribe(heard) as subscription:
            query = consumer.call(provider.name, "cam", 1)
            again = consumer.call(provider.name, "cam", 1, query_id=query.id)  # a retry
            consumer.unload(query.id)
            assert subscription.wait_delivered(timeout=5)

        assert ["CallAnswered", "CallAnswered", "QueryForgotten"] == _answered_then_forgotten(
            heard, query.id
        )
        first, retried = heard.of(events.CallAnswered)
        assert (consumer.name, query.id, provider.name, "cam", None, False) == (
            first.registrar,
            first.query_id,
            first.serving_rr,
            first.server,
            first.parent,
            first.retry,
        )
        assert (again.id, True) == (retried.query_id, retried.retry)
        [forgotten] = heard.of(events.QueryForgotten)
        assert (provider.name, "unload") == (forgotten.serving_rr, forgotten.reason)

    def test_a_release_says_when_its_unload_left_and_when_it_last_reconciled_before(
        self, started: Any
    ) -> None:
        provider, consumer = started("erm"), started("app")
        provider.register_server("cam", load=lambda r: r, unload=lambda _q, _r: None)
        heard = Heard()
        with consumer.subscribe(heard) as subscription:
            released = consumer.call(provider.name, "cam", 1)
            consumer.unload(released.id)
            assert subscription.wait_delivered(timeout=5)

        [answered] = heard.of(events.CallAnswered)
        [forgotten] = heard.of(events.QueryForgotten)
        assert answered.hlc < forgotten.unload_sent < forgotten.hlc  # (its Unload left)
        assert 0 == forgotten.reconciled  # (it never reconciled with erm)

    def test_a_dependency_answered_names_the_resource_it_belongs_to(self, started: Any) -> None:
        erm, cm, app = started("erm"), started("cm"), started("app")
        erm.register_server("leaf", load=lambda r: r, unload=lambda _q, _r: None)
        cm.register_server(
            "comp", load=lambda r: cm.call(erm.name, "leaf", r).id, unload=lambda _q, _r: None
        )
        heard = Heard()
        with cm.subscribe(heard) as subscription:
            top = app.call(cm.name, "comp", "x")
            app.unload(top.id)
            assert subscription.wait_delivered(timeout=5)

        [loaded] = heard.of(events.ResourceLoaded)
        [dependency] = heard.of(events.CallAnswered)
        assert (cm.name, erm.name, "leaf", loaded.resource_id) == (
            dependency.registrar,
            dependency.serving_rr,
            dependency.server,
            dependency.parent,
        )
        [forgotten] = heard.of(events.QueryForgotten)  # released with its resource
        assert (dependency.query_id, "dependency") == (forgotten.query_id, forgotten.reason)

    def test_a_call_that_times_out_is_published_as_withdrawn(self, started: Any) -> None:
        provider, consumer = started("erm"), started("app")
        gate = threading.Event()
        provider.register_server(
            "slow", load=lambda r: gate.wait(10) and r, unload=lambda _q, _r: None
        )
        heard = Heard()
        with consumer.subscribe(heard) as subscription:
            with pytest.raises(rr.CallTimeoutError):
                consumer.call(provider.name, "slow", 1, timeout=0.2)
            gate.set()
            consumer.client_queries()  # (a round trip: the withdrawal was handled)
            assert subscription.wait_delivered(timeout=5)

        [withdrawn] = heard.of(events.CallWithdrawn)
        assert (consumer.name, provider.name, "slow", "timeout") == (
            withdrawn.registrar,
            withdrawn.serving_rr,
            withdrawn.server,
            withdrawn.reason,
        )
        assert [] == heard.of(events.CallAnswered) + heard.of(events.CallFailed)

    def test_a_failed_load_is_a_call_failed_that_did_not_execute_at_the_consumer(
        self,
        started: Any,
    ) -> None:
        provider, consumer = started("erm"), started("app")

        def load(request: Any) -> Any:
            raise ValueError(f"no device {request}")

        provider.register_server("cam", load=load, unload=lambda _q, _r: None)
        heard = Heard()
        with consumer.subscribe(heard) as subscription:
            with pytest.raises(rr.ResourceLoadError):
                consumer.call(provider.name, "cam", 7)
            consumer.client_queries()
            assert subscription.wait_delivered(timeout=5)

        [failed] = heard.of(events.CallFailed)
        assert ("cam", "ResourceLoadError", False) == (
            failed.server,
            failed.error_type,
            failed.may_have_executed,
        )

    def test_a_revoked_id_is_published_as_forgotten_after_its_answer(self, started: Any) -> None:
        provider, consumer = started("erm"), started("app")
        provider.register_server("cam", load=lambda r: r, unload=lambda _q, _r: None)
        heard = Heard()
        with consumer.subscribe(heard) as subscription:
            query = consumer.call(provider.name, "cam", 1)
            provider.unregister_server("cam")  # FATAL, then the id is revoked
            assert wait_for(lambda: bool(heard.of(events.QueryForgotten)), 5)
            assert subscription.wait_delivered(timeout=5)

        assert ["CallAnswered", "QueryForgotten"] == _answered_then_forgotten(heard, query.id)
        [forgotten] = heard.of(events.QueryForgotten)
        assert "revoked" == forgotten.reason
        assert [rr.Status.FATAL] == [e.status for e in heard.of(events.StatusDelivered)]

    @pytest.mark.usefixtures("by_value")  # (its provider runs in a manager process)
    def test_a_call_whose_provider_is_killed_mid_load_failed_and_may_have_executed(
        self, system: System, process_helpers: SharedObjects
    ) -> None:
        entered = process_helpers.event()
        provider = RemoteRegistrar.start(
            f"erm-{uuid.uuid4().hex[:8]}", system, setup=_slow_setup(entered)
        )
        consumer = rr.ResourceRegistrar.start(f"app-{uuid.uuid4().hex[:8]}", network=system)
        heard = Heard()
        subscription = consumer.subscribe(heard)
        outcome: list[BaseException] = []

        def call() -> None:
            try:
                consumer.call(provider.name, "cam", "slow", timeout=30)
            except rr.RrError as exc:
                outcome.append(exc)

        caller = threading.Thread(target=call)
        try:
            caller.start()
            assert entered.wait(10)
            assert provider.pid is not None
            os.kill(provider.pid, signal.SIGKILL)
            caller.join(15)
            provider.kill()
            consumer.client_queries()  # (a round trip: the failure was handled)
            assert subscription.wait_delivered(timeout=5)
        finally:
            subscription.close()
            consumer.stop()

        assert [rr.RegistrarUnavailableError] == [type(e) for e in outcome]
        [failed] = heard.of(events.CallFailed)
        assert (consumer.name, provider.name, "cam", "RegistrarUnavailableError", True) == (
            failed.registrar,
            failed.serving_rr,
            failed.server,
            failed.error_type,
            failed.may_have_executed,
        )

    @pytest.mark.usefixtures("by_value")  # (its provider runs in a manager process)
    def test_ids_held_at_a_provider_lost_for_good_are_published_as_forgotten(
        self, system: System, process_helpers: SharedObjects
    ) -> None:
        entered = process_helpers.event()
        provider = RemoteRegistrar.start(
            f"erm-{uuid.uuid4().hex[:8]}", system, setup=_slow_setup(entered)
        )
        consumer = rr.ResourceRegistrar.start(f"app-{uuid.uuid4().hex[:8]}", network=system)
        heard = Heard()
        subscription = consumer.subscribe(heard)
        try:
            query = consumer.call(provider.name, "cam", "camera", timeout=10)
            assert provider.pid is not None
            os.kill(provider.pid, signal.SIGKILL)
            assert wait_for(lambda: bool(heard.of(events.QueryForgotten)), 5)
            provider.kill()
            assert subscription.wait_delivered(timeout=5)
        finally:
            subscription.close()
            consumer.stop()

        assert ["CallAnswered", "QueryForgotten"] == _answered_then_forgotten(heard, query.id)
        [forgotten] = heard.of(events.QueryForgotten)
        assert (provider.name, "provider lost") == (forgotten.serving_rr, forgotten.reason)
        assert [(query.id, rr.Status.FATAL)] == [
            (e.query_id, e.status) for e in heard.of(events.StatusDelivered)
        ]

    def test_a_load_done_before_its_label_is_published_with_the_label(self, started: Any) -> None:
        # The label is made on a worker while the load runs; a load faster than it came
        # back first, and its ResourceLoaded said the request's text (issue 40: 1 in 30).
        provider, consumer = started("erm"), started("app")
        load_answered = threading.Event()

        def label(request: Any) -> str:
            assert load_answered.wait(10)  # held until the load's answer was handled
            return f"camera {request['n']}"

        provider.register_server(
            "cam", load=lambda r: "cam", unload=lambda _q, _r: None, label=label
        )
        heard = Heard()
        held = intercept(provider, "answer", after=lambda _answer: load_answered.set())
        with held, provider.subscribe(heard) as subscription:
            consumer.call(provider.name, "cam", {"n": 1})  # (a plain request: its text at once)
            assert subscription.wait_delivered(timeout=5)

        [loaded] = heard.of(events.ResourceLoaded)
        assert ("camera 1", ["ResourceLoaded", "ConsumerAdded"]) == (loaded.label, heard.kinds())

    @pytest.mark.parametrize("dependency", [False, True], ids=["top-level", "dependency"])
    def test_a_call_in_flight_at_a_crash_is_not_restored_and_is_released_at_its_provider(
        self, started: Any, tmp_path: Path, dependency: bool
    ) -> None:
        # A durable consumer killed while its call was in flight (its own, or a sub-call of
        # a load of its own): presumed abort, nothing of the call was written, so the
        # restart lists no record of it (CatalogRestored) and forgets none (no
        # QueryForgotten); the provider releases the id (the restart reconciles with it;
        # a thread manager's dead actor also gives back an answer that reaches it).
        provider, entered, gate = _gated_provider(started)
        config = rr.RegistrarConfig(
            name=f"app-{uuid.uuid4().hex[:8]}", backup_path=tmp_path / "app.db", save_on_modify=True
        )
        consumer = rr.ResourceRegistrar.start(config)
        if dependency:
            consumer.register_server(
                "top",
                load=lambda r: consumer.call(provider.name, "slow", r).id,
                unload=lambda _q, _r: None,
            )
            caller = _on_a_thread(lambda: consumer.call(config.name, "top", 1))
        else:
            caller = _on_a_thread(lambda: consumer.call(provider.name, "slow", 1))
        assert entered.wait(10)  # (the call's Load reached the provider: nothing written)
        with expect_restart(config.name):
            crash(consumer)
        gate.set()
        caller.join(10)
        upstream = events.publisher()
        heard = Heard()
        subscription = upstream.subscribe(heard)
        restarted = start_registrar(config, upstream=upstream)
        try:
            assert wait_for(lambda: [] == provider.server_queries("slow"), 10)
            assert wait_for(lambda: bool(heard.of(events.CatalogRestored)), 10)
            assert subscription.wait_delivered(timeout=5)
        finally:
            subscription.close()
            restarted.stop()

        [restored] = heard.of(events.CatalogRestored)
        assert ((), []) == (tuple(restored.clients), heard.of(events.QueryForgotten))

    def test_a_pending_record_of_an_older_backup_is_given_back_and_published_as_forgotten(
        self, started: Any, tmp_path: Path
    ) -> None:
        # A backup written before presumed abort may hold a call's record written as
        # pending (not loaded) before its Load left: the restart lists it
        # (CatalogRestored), gives the id back to its provider and publishes it
        # forgotten ("in doubt", issue 40), as it did.
        provider = started("erm")
        provider.register_server("cam", load=lambda r: r, unload=lambda _q, _r: None)
        config = rr.RegistrarConfig(
            name=f"app-{uuid.uuid4().hex[:8]}", backup_path=tmp_path / "app.db", save_on_modify=True
        )
        consumer = rr.ResourceRegistrar.start(config)
        held = consumer.call(provider.name, "cam", 1)
        with expect_restart(config.name):
            crash(consumer)
        with contextlib.closing(sqlite3.connect(config.backup_path)) as db, db:
            assert 1 == db.execute("UPDATE clients SET loaded = 0").rowcount  # as pending
        upstream = events.publisher()
        heard = Heard()
        subscription = upstream.subscribe(heard)
        restarted = start_registrar(config, upstream=upstream)
        try:
            assert wait_for(lambda: [] == provider.server_queries("cam"), 10)
            assert wait_for(lambda: bool(heard.of(events.QueryForgotten)), 10)
            assert subscription.wait_delivered(timeout=5)
        finally:
            subscription.close()
            restarted.stop()

        [restored] = heard.of(events.CatalogRestored)
        assert [held.id] == [qid for qid, _, _, _ in restored.clients]
        assert [(held.id, "in doubt")] == [
            (e.query_id, e.reason) for e in heard.of(events.QueryForgotten)
        ]


class TestFullDisk:
    """A durable registrar whose backup cannot be written (a real full tmpfs): callers hear at once.

    With `save_on_modify` a load or unload is durable before its caller gets the answer
    (rule 14). When the disk is full the caller fails at once with a `CatalogWriteError`
    naming the file and `ENOSPC`, nothing is left half done, new loads are refused until a
    write succeeds again, and everything already stored is still served.
    """

    @pytest.fixture
    def disk(self, tmp_path: Path) -> Iterator[Path]:
        with mounted(tmp_path / "disk", size="1m") as where:
            yield where

    @pytest.fixture
    def provider(self, disk: Path) -> Iterator[Provider]:
        made = Provider(disk)
        yield made
        (disk / "filler").unlink(missing_ok=True)  # room again: the stop writes what waits
        made.stop()

    def test_a_new_load_on_a_full_disk_fails_at_once_naming_the_file_and_enospc(
        self, provider: Provider, disk: Path
    ) -> None:
        _full(disk)

        with pytest.raises(rr.CatalogWriteError) as raised:
            provider.call("a")

        assert str(provider.path) == raised.value.path
        assert errno.ENOSPC == raised.value.errno
        assert [] == provider.loads  # nothing was loaded: it could not have been recorded
        assert () == catalog_snapshot(provider.registrar).resources
        assert [] == provider.consumer.client_queries()

    def test_a_shared_load_on_a_full_disk_is_refused_and_the_stored_one_still_served(
        self, provider: Provider, disk: Path
    ) -> None:
        held = provider.call("a")
        heard = threading.Event()
        provider.consumer.set_status_callback(held.id, lambda _q, _u: heard.set())
        _full(disk)

        with pytest.raises(rr.CatalogWriteError):
            provider.call("a")  # a second consumer cannot be recorded

        assert [held.id] == [q.id for q in provider.registrar.server_queries("cam")]
        provider.registrar.send_status(held.id, rr.Status.WARNING, "disk full", timeout=5)
        assert heard.wait(5)  # what is stored is served
        assert [held.id] == [
            q.id for q in provider.consumer.fetch_queries(provider.config.name, "cam")
        ]

    def test_an_unload_on_a_full_disk_is_refused_and_changes_nothing(
        self, provider: Provider, disk: Path
    ) -> None:
        held = provider.call("a")
        _full(disk)

        with pytest.raises(rr.CatalogWriteError):
            provider.consumer.unload(held.id)

        assert [held.id] == [q.id for q in provider.registrar.server_queries("cam")]
        assert [held.id] == [q.id for q in provider.consumer.client_queries()]
        assert [] == provider.unloads

    def test_a_last_unload_refused_on_a_full_disk_unloads_once_there_is_room_again(
        self, provider: Provider, disk: Path
    ) -> None:
        # A last release is one commit with its resource's UNLOADING mark (issue 52):
        # refused, both are undone, so the resource is loaded, held, and unloadable again.
        held = provider.call("a")
        _full(disk)
        with pytest.raises(rr.CatalogWriteError):
            provider.consumer.unload(held.id)
        (disk / "filler").unlink()

        provider.consumer.unload(held.id)

        assert provider.unloaded.wait(5)
        assert ["a"] == provider.unloads
        assert wait_for(lambda: not catalog_snapshot(provider.registrar).resources, timeout=5)

    def test_hits_and_unloads_waiting_for_one_commit_on_a_full_disk_are_all_refused_undone(
        self, provider: Provider, disk: Path
    ) -> None:
        # One turn stages the changes of the messages waiting in the mailbox (issue 52);
        # its one transaction fails: every step of it is undone and its caller fails.
        held = [provider.call("a") for _ in range(3)]
        turns: list[int] = []  # the steps each turn's commit wrote
        intercept(provider.registrar, "turn_commit", before=lambda s: turns.append(len(s)))
        gate = threading.Event()
        busy = run_on_actor(provider.registrar, lambda: gate.wait(10))  # busy meanwhile
        outcomes: list[Any] = []

        def run(op: Callable[[], Any]) -> None:
            try:
                outcomes.append(op())
            except rr.RrError as exc:
                outcomes.append(exc)

        ops = [lambda: provider.call("a"), lambda: provider.call("a")]
        ops += [functools.partial(provider.consumer.unload, q.id) for q in held[1:]]
        threads = [threading.Thread(target=run, args=(op,)) for op in ops]
        inbox = actor_ref(provider.registrar).actor_inbox
        try:
            _full(disk)
            for thread in threads:
                thread.start()
            assert wait_for(lambda: inbox.qsize() >= len(ops), 10)  # all wait in its mailbox
        finally:
            gate.set()
        busy.get(timeout=5)
        for thread in threads:
            thread.join(10)

        assert [rr.CatalogWriteError] * len(ops) == [type(o) for o in outcomes]
        assert [len(ops)] == turns  # one transaction: it failed
        ids = sorted(q.id for q in held)
        assert ids == sorted(q.id for q in provider.registrar.server_queries("cam"))
        assert ids == sorted(q.id for q in provider.consumer.client_queries())
        assert [] == provider.unloads

    def test_loads_are_served_again_once_a_write_succeeds(
        self, provider: Provider, disk: Path
    ) -> None:
        filler = _full(disk)
        with pytest.raises(rr.CatalogWriteError):
            provider.call("a")

        filler.unlink()  # room again: the next load retries the write first
        query = provider.call("a")

        assert "cam a" == query.response
        provider.registrar.stop()  # then restored from what was written
        provider.registrar = rr.ResourceRegistrar.start(
            provider.config,
            setup=lambda r: r.register_server("cam", load=provider.load, unload=provider.unload),
        )
        assert [query.id] == [q.id for q in provider.registrar.server_queries("cam")]

    def test_a_load_that_cannot_be_recorded_when_it_finishes_is_unloaded_and_fails_its_caller(
        self, provider: Provider, disk: Path
    ) -> None:
        slow = GatedLoad(threading.Event(), threading.Event(), lambda request: f"slow {request}")
        entered, gate = slow.started, slow.gate
        provider.registrar.register_server("slow", load=slow, unload=provider.unload)
        outcome: list[Any] = []

        def call() -> None:
            try:
                outcome.append(
                    provider.consumer.call(provider.config.name, "slow", "b", timeout=10)
                )
            except rr.RrError as exc:
                outcome.append(exc)

        caller = threading.Thread(target=call)
        caller.start()
        assert entered.wait(10)
        filler = _full(disk)  # the load started on record; its end cannot be written
        gate.set()
        caller.join(10)

        assert [rr.CatalogWriteError] == [type(o) for o in outcome]
        assert provider.unloaded.wait(10)  # what the load started is not left behind
        assert ["b"] == provider.unloads
        filler.unlink()
        assert [] == provider.registrar.server_queries("slow")

    def test_a_durable_consumer_on_a_full_disk_fails_its_call_and_gives_its_id_back(
        self, disk: Path, tmp_path: Path
    ) -> None:
        uid = uuid.uuid4().hex[:8]
        provider = rr.ResourceRegistrar.start(f"erm-{uid}")
        loads: list[Any] = []
        provider.register_server("cam", load=loads.append, unload=lambda _q, _r: None)
        consumer = rr.ResourceRegistrar.start(
            rr.RegistrarConfig(name=f"app-{uid}", backup_path=disk / "app.db", save_on_modify=True)
        )
        try:
            filler = _full(disk)

            with pytest.raises(rr.CatalogWriteError):
                consumer.call(provider.name, "cam", "a", timeout=5)

            # its answer could not be written: the id is given back (presumed abort: the
            # Load left, nothing was written before it)
            assert ["a"] == loads
            assert wait_for(lambda: [] == provider.server_queries("cam"), 10)
            assert [] == consumer.client_queries()
            filler.unlink()
        finally:
            consumer.stop(timeout=5)
            provider.stop()

    def test_a_stop_on_a_full_disk_stops_and_tells_its_caller_what_was_not_written(
        self,
        disk: Path,
    ) -> None:
        uid = uuid.uuid4().hex[:8]
        config = rr.RegistrarConfig(name=f"erm-{uid}", backup_path=disk / "e.db")
        provider = rr.ResourceRegistrar.start(config)  # (saves on an interval, and at stop)
        consumer = rr.ResourceRegistrar.start(f"app-{uid}")
        provider.register_server("cam", load=lambda r: r, unload=lambda _q, _r: None)
        consumer.call(config.name, "cam", "a" * 300_000)  # held, and not written yet
        filler = _full(disk)
        try:
            with pytest.raises(rr.CatalogWriteError):
                provider.stop(timeout=5)
            assert not provider.is_alive()
        finally:
            filler.unlink()
            consumer.stop()


# -- for TestTurn --------------------------------------------------------------------------


def _commits(registrar: rr.ResourceRegistrar) -> int:
    """The transactions the registrar's backup committed since it opened (on its actor)."""

    def read(actor: Any, reply: Any) -> None:
        reply.set_result(actor.shared.saver.store.commits)

    reply = FutureReply()
    actor_ref(registrar).tell(RunOnActor(read, reply))
    count: int = reply.future.get(timeout=5)
    return count


def _waiting_loads(tmp_path: Path, waiting: int) -> tuple[list[str], int, list[Any]]:
    """`waiting` dedup hits wait in a durable provider's mailbox while it is busy, then it
    handles them: their answers, its commits meanwhile, and for each turn's commit the
    steps it wrote and whether a caller had its answer by then (`turn_commit`)."""
    uid = uuid.uuid4().hex[:8]
    config = rr.RegistrarConfig(
        name=f"erm-{uid}", backup_path=tmp_path / "erm.db", save_on_modify=True
    )
    provider = rr.ResourceRegistrar.start(config)
    consumer = rr.ResourceRegistrar.start(f"app-{uid}")
    provider.register_server("cam", load=lambda r: f"cam {r}", unload=lambda _q, _r: None)
    consumer.call(provider.name, "cam", 1, timeout=5)  # loaded: every call after shares it
    answered: list[str] = []
    first = threading.Event()  # a caller has its answer
    at_commit: list[tuple[int, bool]] = []  # (steps staged, whether an answer came)

    def committing(staged: Any) -> None:  # (an answer released early wakes its caller)
        at_commit.append((len(staged), first.wait(0.5)))

    def call() -> None:
        answered.append(consumer.call(provider.name, "cam", 1, timeout=30).response)
        first.set()

    intercept(provider, "turn_commit", before=committing)
    before = _commits(provider)
    gate = threading.Event()
    busy = run_on_actor(provider, lambda: gate.wait(10))  # the provider is busy
    inbox = actor_ref(provider).actor_inbox
    callers = [threading.Thread(target=call) for _ in range(waiting)]
    try:
        for caller in callers:
            caller.start()
        assert wait_for(lambda: inbox.qsize() >= waiting, 10)  # all wait in its mailbox
        gate.set()
        busy.get(timeout=5)
        for caller in callers:
            caller.join(30)
        return answered, _commits(provider) - before, list(at_commit)  # (before the stop's)
    finally:
        gate.set()
        consumer.stop()
        provider.stop()


class TestTurn:
    """A durable registrar's turn: the changes of the messages it handled commit in one
    transaction at its end, and their answers go only after it (issue 52 parts 2, 4)."""

    def test_the_loads_waiting_in_the_mailbox_commit_once_then_each_is_answered(
        self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        monkeypatch.setattr(actor, "DRAIN_SECONDS", 60.0)  # (a loaded machine: no time bound)

        answered, commits, at_commit = _waiting_loads(tmp_path, 8)

        assert ["cam 1"] * 8 == answered
        assert 1 == commits  # one transaction for the eight
        assert [(8, False)] == at_commit  # none was answered before it

    def test_a_turn_takes_at_most_drain_messages(
        self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        monkeypatch.setattr(actor, "DRAIN_SECONDS", 60.0)
        monkeypatch.setattr(actor, "DRAIN", 3)

        answered, commits, at_commit = _waiting_loads(tmp_path, 8)

        assert ["cam 1"] * 8 == answered
        # (the first turn's first message: the one that kept the provider busy)
        assert (3, [(2, False), (3, True), (3, True)]) == (commits, at_commit)

    def test_a_registrar_that_dies_at_its_turns_commit_fails_the_staged_calls_unwritten(
        self, tmp_path: Path
    ) -> None:
        uid = uuid.uuid4().hex[:8]
        config = rr.RegistrarConfig(
            name=f"erm-{uid}", backup_path=tmp_path / "erm.db", save_on_modify=True
        )

        def setup(registrar: rr.ResourceRegistrar) -> None:
            registrar.register_server("cam", load=lambda r: f"cam {r}", unload=lambda *_: None)

        provider = rr.ResourceRegistrar.start(config, setup=setup)
        consumer = rr.ResourceRegistrar.start(f"app-{uid}")
        try:
            held = consumer.call(provider.name, "cam", 1, timeout=5)  # committed, answered

            def bug(staged: Any) -> None:
                if staged:
                    raise RuntimeError("a bug at the turn's commit")

            intercept(provider, "turn_commit", before=bug)
            with expect_restart(config.name):  # (not gone for good: its consumer keeps held)
                with pytest.raises(rr.RegistrarUnavailableError):
                    consumer.call(provider.name, "cam", 1, timeout=5)  # staged, never written
                assert provider._actor.died.wait(5)  # (its death handled: backup closed)

            again = rr.ResourceRegistrar.start(config, setup=setup)  # on its backup
            try:
                assert [held.id] == [q.id for q in again.server_queries("cam")]
            finally:
                again.stop()
        finally:
            consumer.stop()

    @pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
    @pytest.mark.usefixtures("by_value")  # (tests/conftest.py)
    def test_a_kill_at_the_turns_commit_acknowledged_nothing_staged_and_lost_nothing_acknowledged(
        self, manager_provider: Callable[..., ManagerProvider]
    ) -> None:
        # A real SIGKILL of the provider's manager process at the boundary: its turn's
        # changes are staged (a consumer id added), the transaction not begun. The call
        # whose id was staged fails; the ids acknowledged before (a miss, then a hit
        # committed at its turn's end) are in the backup the restarted provider serves.
        provider = manager_provider()
        p, sup, app = provider.name, provider.sup, provider.app
        acknowledged = [app.call(p, "leaf", "x", timeout=10).id for _ in range(2)]

        def kill_at_commit(registrar: rr.ResourceRegistrar) -> None:
            import signal  # noqa: PLC0415 - runs in the provider's first process

            from rr_actors.testing import intercept  # noqa: PLC0415

            def kill(staged: Any) -> None:
                if staged:  # (a turn with a change to write)
                    os.kill(os.getpid(), signal.SIGKILL)  # staged, not written

            intercept(registrar, "turn_commit", before=kill)

        sup.run_in(p, kill_at_commit)
        with pytest.raises(rr.RegistrarUnavailableError):
            app.call(p, "leaf", "x", timeout=10)  # a hit: staged, never acknowledged
        sup.wait_restarted(p, timeout=15)

        assert sorted(acknowledged) == sup.run_in(
            p, lambda r: sorted(q.id for q in r.server_queries("leaf"))
        )
        assert sorted(acknowledged) == sorted(q.id for q in app.client_queries())
        app.stop()

    @pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
    @pytest.mark.usefixtures("by_value")  # (tests/conftest.py)
    def test_a_hit_abandoned_in_its_own_turn_is_committed_with_its_release_or_kept(
        self,
        manager_provider: Callable[..., ManagerProvider],
        process_helpers: SharedObjects,
    ) -> None:
        # Issue 51 (the simcancel plan's real runs): a dedup hit is staged, and its
        # caller's Abandon, handled in the same turn, releases the id and commits at
        # once. The staged write must not commit the hit's ConsumerAdded with the id
        # already gone from its row and the release left to a second transaction: a real
        # SIGKILL of the provider's process right after the first commit that tells of
        # the add (its events in the backup's outbox, read after the exit). Every id whose
        # ConsumerAdded came and whose ConsumerReleased did not is held by the restart.
        provider = manager_provider()  # (no heartbeat: held)
        p, sup, app = provider.name, provider.sup, provider.app
        held = app.call(p, "leaf", "x", timeout=10).id  # loaded: the next call is a hit
        withdrawn, abandoned = process_helpers.event(), process_helpers.event()

        def arm(registrar: rr.ResourceRegistrar) -> None:
            import signal  # noqa: PLC0415 - runs in the provider's first process
            import threading  # noqa: PLC0415
            import time  # noqa: PLC0415

            from rr_actors import events  # noqa: PLC0415
            from rr_actors.testing import actor_ref, intercept, run_on_actor  # noqa: PLC0415

            inbox = actor_ref(registrar).actor_inbox

            def busy() -> None:  # until the hit's Load and its Abandon wait in the inbox
                withdrawn.wait(20)
                deadline, pause = time.monotonic() + 20, threading.Event()
                while inbox.qsize() < 2 and time.monotonic() < deadline:
                    pause.wait(0.005)

            def kill(told: Any) -> None:
                if abandoned.is_set() and any(isinstance(e, events.ConsumerAdded) for e in told):
                    os.kill(os.getpid(), signal.SIGKILL)  # committed, the next not begun

            intercept(registrar, "abandon", before=lambda _message: abandoned.set())
            intercept(registrar, "events_written", before=kill)
            run_on_actor(registrar, busy)  # (the turn that follows handles both)

        sup.run_in(p, arm)
        intercept(app, "withdraw", after=lambda _query: withdrawn.set())
        with pytest.raises(rr.CallTimeoutError):  # withdrawn: its Abandon follows its Load
            app.call(p, "leaf", "x", timeout=1.0)
        sup.wait_restarted(p, timeout=20)
        restored = set(sup.run_in(p, lambda r: [q.id for q in r.server_queries("leaf")]))
        heard = provider.events()
        app.stop()

        added = {e.query_id for e in heard.of(events.ConsumerAdded) if e.registrar == p}
        released = {e.query_id for e in heard.of(events.ConsumerReleased) if e.registrar == p}
        assert len(added) == 2  # (the first call's; the hit's, published from the outbox)
        assert held in restored
        assert added - released <= restored
