"""DESIGN "What TeMoto's registrar got wrong, and we do not": one test per fault.

(Non-atomic backups and pid reuse belong to the persistence and supervisor tests; order
dependence is shown by every test here starting its own registrars.)
"""

from __future__ import annotations

import uuid
from concurrent.futures import ThreadPoolExecutor

import pytest

import rr_actors as rr
from rr_actors.testing import catalog_snapshot


def test_fault_status_reached_only_one_consumer(make_registrar, serve, inbox):
    provider, one, two = (make_registrar(n) for n in ("provider", "one", "two"))
    serve(provider, "leaf")
    boxes = [inbox(), inbox()]
    q1 = one.call(provider.name, "leaf", "x", on_status=boxes[0])
    q2 = two.call(provider.name, "leaf", "x", on_status=boxes[1])

    provider.send_status(q1.id, rr.Status.FATAL, "gone")

    assert [[q1.id], [q2.id]] == [[u.query_id for _, u in b.updates] for b in boxes]


def test_fault_dependencies_were_keyed_to_the_first_consumer(make_registrar, serve):
    provider, first, second = (make_registrar(n) for n in ("provider", "first", "second"))
    leaf = serve(provider, "leaf")
    serve(provider, "composite", lambda r: provider.call(provider.name, "leaf", r).response)
    q1 = first.call(provider.name, "composite", "x")
    q2 = second.call(provider.name, "composite", "x")

    first.unload(q1.id)
    released_early = list(leaf.unloads)
    second.unload(q2.id)

    assert ([], 1) == (released_early, len(leaf.unloads))


def test_fault_concurrent_identical_requests_loaded_twice(
    make_registrar, serve, gated_load, arrived
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    slow = gated_load()
    leaf = serve(provider, "leaf", slow)
    ids = [str(uuid.uuid4()) for _ in range(2)]
    with ThreadPoolExecutor(2) as pool:
        futures = [
            pool.submit(consumer.call, provider.name, "leaf", {"a": [1]}, query_id=qid)
            for qid in ids
        ]
        assert slow.started.wait(5)
        assert arrived(provider, ids)
        slow.gate.set()
        for future in futures:
            future.result(timeout=10)

    assert 1 == len(leaf.loads)


def test_fault_an_exception_from_the_load_callback_itself_leaked_sub_resources(
    make_registrar, serve
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")

    def composite(request):
        provider.call(provider.name, "leaf", request)
        raise RuntimeError("callback failed after loading a sub-resource")

    serve(provider, "composite", composite)

    with pytest.raises(rr.ResourceLoadError):
        consumer.call(provider.name, "composite", "x")

    assert 1 == len(leaf.unloads)


def test_fault_non_registrar_exceptions_escaped(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")

    def load(request):
        return {}["missing"]

    serve(provider, "leaf", load)

    with pytest.raises(rr.RrError) as info:
        consumer.call(provider.name, "leaf", "x")

    assert isinstance(info.value, rr.ResourceLoadError)
    assert not isinstance(info.value, KeyError)


def test_fault_failed_remote_calls_were_silent(make_registrar, serve):
    consumer, agent, producer = (make_registrar(n) for n in ("consumer", "agent", "producer"))
    serve(agent, "composite", lambda r: agent.call(producer.name, "missing_server", r))

    with pytest.raises(rr.ResourceLoadError) as info:
        consumer.call(agent.name, "composite", "x")

    assert "UnknownServerError" == info.value.stack[0].exc_type


def test_fault_there_was_no_cycle_detection(make_registrar, serve):
    consumer, a, b = (make_registrar(n) for n in ("consumer", "a", "b"))
    serve(a, "x", lambda r: a.call(b.name, "y", r, timeout=20))
    serve(b, "y", lambda r: b.call(a.name, "x", r, timeout=20))

    with pytest.raises(rr.DependencyCycleError):
        consumer.call(a.name, "x", "ping", timeout=20)


def test_fault_a_self_call_lost_dependency_tracking(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")
    serve(provider, "composite", lambda r: provider.call(provider.name, "leaf", r).response)
    query = consumer.call(provider.name, "composite", "x")

    (record,) = catalog_snapshot(provider).clients
    consumer.unload(query.id)

    assert record.parent is not None
    assert 1 == len(leaf.unloads)


def test_fault_consumer_records_were_never_cleared(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    consumer.call(provider.name, "leaf", "x")
    consumer.unload(consumer.call(provider.name, "leaf", "y").id)

    consumer.stop()

    assert [] == provider.server_queries("leaf")
    snapshot = catalog_snapshot(provider)
    assert ((), ()) == (snapshot.resources, snapshot.clients)
