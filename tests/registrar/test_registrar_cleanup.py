"""Cleanup: stop(), unregister_server(), dead consumers, erase_on_destruct (rules 12-13)."""

from __future__ import annotations

import contextlib
import threading
import uuid

import pytest

import rr_actors as rr
from rr_actors._registrar import Served
from rr_actors.testing import catalog_snapshot, crash, intercept
from tests.support.waiting import wait_for

pytestmark = pytest.mark.both_apis  # the rules, against the async API too (conftest)


def test_stop_unloads_everything_the_registrar_holds_as_a_consumer(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")
    consumer.call(provider.name, "leaf", "a")
    consumer.call(provider.name, "leaf", "a")
    consumer.call(provider.name, "leaf", "b")

    consumer.stop()

    assert {"a", "b"} == {request for request, _ in leaf.unloads}
    assert [] == provider.server_queries("leaf")


def test_stop_unloads_newest_first(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")
    for request in ("first", "second", "third"):
        consumer.call(provider.name, "leaf", request)

    consumer.stop()

    assert ["third", "second", "first"] == [request for request, _ in leaf.unloads]


def test_stop_releases_a_consumer_s_own_composites_with_their_dependencies(
    make_registrar, serve, journal
):
    owner = make_registrar("owner")
    serve(owner, "leaf")
    serve(owner, "composite", lambda r: owner.call(owner.name, "leaf", r).response)
    owner.call(owner.name, "composite", "x")

    owner.stop()

    assert [
        (f"{owner.name}/leaf", "unload", "x"),
        (f"{owner.name}/composite", "unload", "x"),
    ] == [entry for entry in journal if entry[1] == "unload"]


def test_stop_keeps_what_the_registrar_s_own_servers_serve_to_others(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")
    consumer.call(provider.name, "leaf", "x")

    provider.stop()

    assert [] == leaf.unloads


def test_a_stopped_registrar_refuses_work_with_registrar_stopped_error(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    provider.stop()

    with pytest.raises(rr.RegistrarStoppedError):
        consumer.call(provider.name, "leaf", "x")
    with pytest.raises(rr.RegistrarStoppedError):
        provider.call(consumer.name, "leaf", "x")


def test_stopping_twice_is_harmless(make_registrar):
    registrar = make_registrar("once")

    registrar.stop()
    registrar.stop()

    assert not registrar.is_alive()


def test_unregister_server_sends_fatal_to_every_consumer_with_its_own_id(
    make_registrar, serve, inbox
):
    provider, one, two = (make_registrar(n) for n in ("provider", "one", "two"))
    leaf = serve(provider, "leaf")
    boxes = [inbox(), inbox()]
    q1 = one.call(provider.name, "leaf", "x", on_status=boxes[0])
    q2 = two.call(provider.name, "leaf", "x", on_status=boxes[1])

    provider.unregister_server("leaf")

    got = [[(u.query_id, u.status) for _, u in box.updates] for box in boxes]
    assert [[(q1.id, rr.Status.FATAL)], [(q2.id, rr.Status.FATAL)]] == got
    assert 1 == len(leaf.statuses)


def test_unregister_server_unloads_everything_it_serves_once(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")
    consumer.call(provider.name, "leaf", "a")
    consumer.call(provider.name, "leaf", "a")
    consumer.call(provider.name, "leaf", "b")

    provider.unregister_server("leaf")

    assert ["a", "b"] == sorted(request for request, _ in leaf.unloads)
    # The consumer forgets its ids when the provider's `Revoke` reaches it: told, not
    # asked, so in another process it may come after unregister_server returned.
    assert wait_for(lambda: [] == consumer.client_queries(), 10.0), consumer.client_queries()
    with pytest.raises(rr.UnknownServerError):
        provider.server_queries("leaf")


def test_unregister_server_unloads_in_the_providers_actor_thread_whoever_acknowledges() -> None:
    # The FATAL's acknowledgement arrives on the consumer's side (here its actor thread);
    # the revoke and the unload that follow touch the provider's catalog, so they must
    # run back in the provider's own actor thread.
    threads: dict[str, list[str]] = {"close": [], "unload": []}
    provider = rr.ResourceRegistrar.start(f"P-{uuid.uuid4().hex[:8]}")
    consumer = rr.ResourceRegistrar.start(f"C-{uuid.uuid4().hex[:8]}")
    try:
        intercept(
            provider,
            "close_resource",
            before=lambda _: threads["close"].append(threading.current_thread().name),
        )
        intercept(
            provider,
            "unload_resource",
            before=lambda _: threads["unload"].append(threading.current_thread().name),
        )
        provider.register_server("leaf", load=lambda r: r, unload=lambda r, s: None)
        consumer.call(provider.name, "leaf", "x")

        provider.unregister_server("leaf")

        assert len(threads["close"]) == 1
        assert threads["close"] == threads["unload"]
    finally:
        consumer.stop()
        provider.stop()


def test_after_unregister_server_calls_and_unloads_there_fail_clearly(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    query = consumer.call(provider.name, "leaf", "x")
    provider.unregister_server("leaf")

    with pytest.raises(rr.UnknownServerError):
        consumer.call(provider.name, "leaf", "x")
    with pytest.raises(rr.UnknownQueryError):
        consumer.unload(query.id)


def test_unregister_server_releases_the_dependencies_of_its_resources(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")
    serve(provider, "composite", lambda r: provider.call(provider.name, "leaf", r).response)
    consumer.call(provider.name, "composite", "x")

    provider.unregister_server("composite")

    assert [("x", {"resource": "x"})] == leaf.unloads
    assert ((), ()) == (catalog_snapshot(provider).resources, catalog_snapshot(provider).clients)


def test_a_server_name_can_be_registered_again_after_unregister(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    provider.unregister_server("leaf")
    again = serve(provider, "leaf")

    consumer.call(provider.name, "leaf", "x")

    assert ["x"] == again.loads


def test_unregister_server_of_an_unknown_server_raises(make_registrar):
    provider = make_registrar("provider")

    with pytest.raises(rr.UnknownServerError):
        provider.unregister_server("nope")


def test_a_crashed_consumer_s_ids_are_released_at_the_provider(make_registrar, serve):
    provider, consumer, other = (make_registrar(n) for n in ("provider", "consumer", "other"))
    leaf = serve(provider, "leaf")
    consumer.call(provider.name, "leaf", "dies-with-consumer")
    kept = other.call(provider.name, "leaf", "kept")
    consumer.call(provider.name, "leaf", "kept")

    crash(consumer)

    assert leaf.unloaded.wait(5)
    assert [("dies-with-consumer", {"resource": "dies-with-consumer"})] == leaf.unloads
    assert [kept.id] == [q.id for q in provider.server_queries("leaf")]


def test_a_crashed_registrar_fails_its_callers_with_registrar_unavailable(make_registrar):
    registrar = make_registrar("doomed")
    crash(registrar)

    with pytest.raises(rr.RegistrarUnavailableError):
        registrar.client_queries()


def test_erase_on_destruct_removes_the_backup_after_a_clean_stop(make_registrar, serve, tmp_path):
    path = tmp_path / "erase.db"
    registrar = make_registrar(
        "erase", backup_path=str(path), erase_on_destruct=True, save_on_modify=True
    )
    serve(registrar, "leaf")
    registrar.call(registrar.name, "leaf", "x")
    assert path.exists()

    registrar.stop()

    assert not path.exists()


def test_a_crash_keeps_the_backup_even_with_erase_on_destruct(make_registrar, serve, tmp_path):
    path = tmp_path / "kept.db"
    registrar = make_registrar(
        "kept", backup_path=str(path), erase_on_destruct=True, save_on_modify=True
    )
    serve(registrar, "leaf")
    registrar.call(registrar.name, "leaf", "x")

    crash(registrar)

    assert path.exists()


def test_without_erase_on_destruct_a_clean_stop_keeps_the_backup(make_registrar, tmp_path):
    path = tmp_path / "keep.db"
    registrar = make_registrar("keep", backup_path=str(path))

    registrar.stop()

    assert path.exists()


def test_consumer_records_are_cleared_when_a_consumer_stops_while_a_load_runs(
    make_registrar, serve, gated_load
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    slow = gated_load()
    leaf = serve(provider, "slow", slow)
    caller = threading.Thread(target=_call_ignoring_errors, args=(consumer, provider.name))
    caller.start()
    assert slow.started.wait(5)

    consumer.stop()
    slow.gate.set()
    caller.join(10)

    assert leaf.unloaded.wait(5)
    assert [] == provider.server_queries("slow")


def _call_ignoring_errors(consumer, provider_name):
    with contextlib.suppress(rr.RrError):  # stopped, or stopped while waiting
        consumer.call(provider_name, "slow", "x", timeout=10)


def test_a_consumer_that_crashes_while_its_call_loads_is_released_when_the_load_ends(
    make_registrar, serve, gated_load
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    slow = gated_load()
    leaf = serve(provider, "slow", slow)
    caller = threading.Thread(target=_call_ignoring_errors, args=(consumer, provider.name))
    caller.start()
    assert slow.started.wait(5)

    crash(consumer)
    slow.gate.set()
    caller.join(10)

    assert leaf.unloaded.wait(5)
    assert [] == provider.server_queries("slow")


# -- yielding its name (rule 22: another registrar of its name is kept) -------------------------
#
# The carrier calls `Endpoint.yield_name` in the registrar's own process once it stopped
# serving it (`tests/multihost/test_registrars_on_two_hosts.py` has the whole cut and heal).


def _started(prefix: str) -> rr.ResourceRegistrar:
    return rr.ResourceRegistrar.start(f"{prefix}-{uuid.uuid4().hex[:8]}")


def test_a_registrar_that_yields_its_name_unloads_what_it_serves_tells_no_consumer_and_stops():
    provider, consumer, below = _started("P"), _started("C"), _started("D")
    unloads: list[str] = []
    below_unloads: list[str] = []
    heard: list[rr.StatusUpdate] = []
    released: list[str] = []
    try:
        below.register_server(
            "leaf", load=lambda r: r, unload=lambda r, _s: below_unloads.append(r)
        )
        provider.register_server(
            "camera",
            load=lambda r: provider.call(below.name, "leaf", r).response,
            unload=lambda r, _s: unloads.append(r),
        )
        ids = [
            consumer.call(provider.name, "camera", r, on_status=lambda _q, u: heard.append(u)).id
            for r in ("a", "a", "b")
        ]
        provider.subscribe(
            lambda e: (
                released.append(e.reason) if isinstance(e, rr.events.ConsumerReleased) else None
            )
        )

        Served(provider).yield_name("another registrar of its name is kept")

        assert wait_for(lambda: not provider.is_alive(), 10.0)
        assert ["a", "b"] == sorted(unloads)  # each resource's unload once
        assert ["a", "b"] == sorted(below_unloads)  # and what it held for them, released
        assert ["name yielded"] * 3 == released
        assert [] == heard  # no FATAL from it: its consumers reconcile with the one kept
        assert sorted(ids) == sorted(q.id for q in consumer.client_queries())
    finally:
        for registrar in (consumer, provider, below):
            registrar.stop()


def test_a_load_under_way_when_a_registrar_yields_its_name_fails_its_caller_and_is_unloaded():
    provider, consumer = _started("P"), _started("C")
    gate, started, unloaded = threading.Event(), threading.Event(), threading.Event()
    outcome: list[BaseException] = []

    def load(request: str) -> str:
        started.set()
        gate.wait(10)
        return request

    def call() -> None:
        try:
            consumer.call(provider.name, "slow", "x", timeout=10)
        except rr.RrError as exc:
            outcome.append(exc)

    try:
        provider.register_server("slow", load=load, unload=lambda _r, _s: unloaded.set())
        caller = threading.Thread(target=call)
        caller.start()
        assert started.wait(5)

        Served(provider).yield_name("another registrar of its name is kept")
        gate.set()
        caller.join(10)

        assert unloaded.wait(5)  # before it stopped, not left in doubt
        assert wait_for(lambda: not provider.is_alive(), 10.0)
        assert [rr.UnknownServerError] == [type(exc) for exc in outcome]
        assert [] == consumer.client_queries()
    finally:
        gate.set()
        consumer.stop()
        provider.stop()
