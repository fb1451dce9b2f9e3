"""Load errors: `ResourceLoadError` stacks and rollback of sub-resources (DESIGN rule 4)."""

from __future__ import annotations

import contextvars
import pickle
import threading
import uuid
from concurrent.futures import Future, ThreadPoolExecutor

import pytest

import rr_actors as rr
from rr_actors.testing import catalog_snapshot
from tests.support.gating import GatedLoad

pytestmark = pytest.mark.both_apis  # the rules, against the async API too (conftest)


class SensorError(Exception):
    """An application exception that knows nothing of rr_actors."""


def raise_(exc: BaseException):
    def load(request):
        raise exc

    return load


@pytest.mark.parametrize(
    "exc", [ValueError("bad value"), KeyError("k"), SensorError("lidar offline"), SystemExit(3)]
)
def test_any_exception_from_load_fails_the_call_with_resource_load_error(
    make_registrar, serve, exc
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf", raise_(exc))

    with pytest.raises(rr.ResourceLoadError) as info:
        consumer.call(provider.name, "leaf", "x")

    assert isinstance(info.value, rr.RrError)
    assert type(exc).__qualname__ == info.value.stack[0].exc_type


def test_the_origin_frame_names_registrar_server_exception_message_and_traceback(
    make_registrar, serve
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")

    def broken(request):
        raise SensorError("lidar offline")

    serve(provider, "leaf", broken)

    with pytest.raises(rr.ResourceLoadError) as info:
        consumer.call(provider.name, "leaf", "x")

    (frame,) = info.value.stack
    assert (provider.name, "leaf", "SensorError", "lidar offline") == (
        frame.registrar,
        frame.server,
        frame.exc_type,
        frame.message,
    )
    assert "in broken" in frame.traceback
    assert "SensorError: lidar offline" in frame.traceback


def test_the_stack_has_one_frame_per_failing_hop_origin_first(make_registrar, serve):
    consumer, agent, producer = (make_registrar(n) for n in ("consumer", "agent", "producer"))
    serve(producer, "leaf", raise_(SensorError("no signal")))
    serve(agent, "composite", lambda request: agent.call(producer.name, "leaf", request))

    with pytest.raises(rr.ResourceLoadError) as info:
        consumer.call(agent.name, "composite", "x")

    expected = [
        (producer.name, "leaf", "SensorError"),
        (agent.name, "composite", "ResourceLoadError"),
    ]
    assert expected == [(f.registrar, f.server, f.exc_type) for f in info.value.stack]
    assert "no signal" in str(info.value)


def test_servers_of_one_registrar_each_add_a_frame(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf", raise_(ValueError("deep")))
    serve(provider, "middle", lambda r: provider.call(provider.name, "leaf", r))
    serve(provider, "top", lambda r: provider.call(provider.name, "middle", r))

    with pytest.raises(rr.ResourceLoadError) as info:
        consumer.call(provider.name, "top", 1)

    assert ["leaf", "middle", "top"] == [f.server for f in info.value.stack]


def test_a_load_error_pickles_with_its_stack(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf", raise_(ValueError("boom")))

    with pytest.raises(rr.ResourceLoadError) as info:
        consumer.call(provider.name, "leaf", "x")

    copy = pickle.loads(pickle.dumps(info.value))
    assert (info.value.stack, str(info.value)) == (copy.stack, str(copy))


def test_sub_resources_are_unloaded_when_the_load_callback_itself_raises(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")

    def composite(request):
        provider.call(provider.name, "leaf", "part-1")
        provider.call(provider.name, "leaf", "part-2")
        raise SensorError("assembly failed")

    serve(provider, "composite", composite)

    with pytest.raises(rr.ResourceLoadError):
        consumer.call(provider.name, "composite", "x")

    # Unloaded before the error was returned: no waiting needed.
    assert {"part-1", "part-2"} == {request for request, _ in leaf.unloads}
    snapshot = catalog_snapshot(provider)
    assert ((), ()) == (snapshot.resources, snapshot.clients)


def _agent(tmp_path, save_on_modify):
    return rr.ResourceRegistrar.start(
        rr.RegistrarConfig(
            name=f"A-{uuid.uuid4().hex[:8]}",
            backup_path=tmp_path / "a.db" if save_on_modify else None,
            save_on_modify=save_on_modify,
        )
    )


DURABILITY = pytest.mark.parametrize(
    "save_on_modify", [False, True], ids=["in-memory", "save-on-modify"]
)


@DURABILITY
def test_a_sub_call_made_after_its_load_failed_is_released_not_leaked(tmp_path, save_on_modify):
    # The load hands a sub-call to a thread of its own (in its context: a dependency) and
    # raises; the sub-call goes out only after the load failed and its rollback is done.
    # Nothing would ever release that late dependency: it is given back at once.
    provider = rr.ResourceRegistrar.start(f"P-{uuid.uuid4().hex[:8]}")
    agent = _agent(tmp_path, save_on_modify)
    consumer = rr.ResourceRegistrar.start(f"C-{uuid.uuid4().hex[:8]}")
    failed, unloaded = threading.Event(), threading.Event()
    late: list[Future[rr.Query]] = []
    pool = ThreadPoolExecutor(1)
    try:
        provider.register_server("leaf", load=lambda r: r, unload=lambda r, s: unloaded.set())

        def sub_call(request):
            assert failed.wait(10)
            return agent.call(provider.name, "leaf", request)

        def composite(request):
            late.append(pool.submit(contextvars.copy_context().run, sub_call, request))
            raise SensorError("failed before its sub-call went out")

        agent.register_server("composite", load=composite, unload=lambda r, s: None)
        with pytest.raises(rr.ResourceLoadError):
            consumer.call(agent.name, "composite", "x")
        failed.set()

        assert late[0].result(10).response == "x"  # the sub-call itself succeeded
        assert unloaded.wait(10), "the late dependency leaked at its provider"
        assert [] == provider.server_queries("leaf")
        assert ((), ()) == (catalog_snapshot(agent).resources, catalog_snapshot(agent).clients)
    finally:
        failed.set()
        pool.shutdown()
        for registrar in (consumer, agent, provider):
            registrar.stop()


@DURABILITY
def test_a_sub_call_in_flight_when_its_load_fails_is_released_not_leaked(tmp_path, save_on_modify):
    # The sub-call reached its provider before the load raised, and returns after the
    # rollback. A durable agent wrote it down before sending it, so the rollback gives
    # it up at the provider (its caller hears so); an in-memory one learns of it only
    # from the answer, and gives it back then. Either way nothing is left anywhere.
    provider = rr.ResourceRegistrar.start(f"P-{uuid.uuid4().hex[:8]}")
    agent = _agent(tmp_path, save_on_modify)
    consumer = rr.ResourceRegistrar.start(f"C-{uuid.uuid4().hex[:8]}")
    leaf = GatedLoad(threading.Event(), threading.Event())
    started, gate, unloaded = leaf.started, leaf.gate, threading.Event()
    late: list[Future[rr.Query]] = []
    pool = ThreadPoolExecutor(1)
    try:
        provider.register_server("leaf", load=leaf, unload=lambda r, s: unloaded.set())

        def composite(request):
            context = contextvars.copy_context()
            late.append(pool.submit(context.run, agent.call, provider.name, "leaf", request))
            assert started.wait(10)  # the sub-call is at its provider, loading
            raise SensorError("failed while its sub-call runs")

        agent.register_server("composite", load=composite, unload=lambda r, s: None)
        with pytest.raises(rr.ResourceLoadError):
            consumer.call(agent.name, "composite", "x")
        gate.set()

        outcome = late[0].exception(10)
        assert outcome is None or isinstance(outcome, rr.CallTimeoutError)  # given up
        assert unloaded.wait(10), "the dependency leaked at its provider"
        assert [] == provider.server_queries("leaf")
        assert ((), ()) == (catalog_snapshot(agent).resources, catalog_snapshot(agent).clients)
    finally:
        gate.set()
        pool.shutdown()
        for registrar in (consumer, agent, provider):
            registrar.stop()


def test_sub_resources_are_unloaded_when_a_later_sub_call_fails(make_registrar, serve):
    consumer, agent, producer = (make_registrar(n) for n in ("consumer", "agent", "producer"))
    good = serve(producer, "good")
    serve(producer, "bad", raise_(SensorError("no signal")))

    def composite(request):
        agent.call(producer.name, "good", "a")
        agent.call(producer.name, "bad", "b")
        return "never"

    serve(agent, "composite", composite)

    with pytest.raises(rr.ResourceLoadError):
        consumer.call(agent.name, "composite", "x")

    assert [("a", {"resource": "a"})] == good.unloads
    assert () == catalog_snapshot(producer).resources
    assert () == catalog_snapshot(agent).clients


def test_a_sub_resource_shared_with_another_consumer_survives_the_rollback(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")
    kept = consumer.call(provider.name, "leaf", "shared")

    def composite(request):
        provider.call(provider.name, "leaf", "shared")
        raise SensorError("assembly failed")

    serve(provider, "composite", composite)

    with pytest.raises(rr.ResourceLoadError):
        consumer.call(provider.name, "composite", "x")

    assert [] == leaf.unloads
    assert [kept.id] == [q.id for q in provider.server_queries("leaf")]


def test_a_failed_load_leaves_nothing_so_an_equal_request_loads_afresh(
    make_registrar, serve, shared
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    attempts = shared.list()

    def flaky(request):
        attempts.append(request)
        if len(attempts) == 1:
            raise SensorError("first try fails")
        return "ok"

    serve(provider, "leaf", flaky)

    with pytest.raises(rr.ResourceLoadError):
        consumer.call(provider.name, "leaf", "x")
    query = consumer.call(provider.name, "leaf", "x")

    assert ("ok", ["x", "x"]) == (query.response, attempts)
    assert [query.id] == [q.id for q in provider.server_queries("leaf")]
    assert [query.id] == [q.id for q in consumer.client_queries()]


def test_every_waiter_of_a_failing_load_gets_the_error(make_registrar, serve, gated_load, arrived):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")

    def fail(request):
        raise SensorError("late failure")

    fails_later = gated_load(fail)
    serve(provider, "leaf", fails_later)
    ids = [str(uuid.uuid4()) for _ in range(3)]
    with ThreadPoolExecutor(3) as pool:
        futures = [
            pool.submit(consumer.call, provider.name, "leaf", "x", query_id=qid) for qid in ids
        ]
        assert fails_later.started.wait(5)
        assert arrived(provider, ids)
        fails_later.gate.set()
        errors = [f.exception(timeout=10) for f in futures]

    assert all(isinstance(e, rr.ResourceLoadError) for e in errors)
    assert () == catalog_snapshot(consumer).clients


def test_a_failing_load_does_not_disturb_other_resources_of_the_server(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")

    def picky(request):
        if request == "bad":
            raise SensorError("bad request")
        return request

    serve(provider, "leaf", picky)
    good = consumer.call(provider.name, "leaf", "good")

    with pytest.raises(rr.ResourceLoadError):
        consumer.call(provider.name, "leaf", "bad")

    assert [good] == consumer.client_queries()
    assert "again" == consumer.call(provider.name, "leaf", "again").response
