"""Loading and dedup (DESIGN rules 1-3)."""

from __future__ import annotations

import uuid
from concurrent.futures import ThreadPoolExecutor

import pytest

import rr_actors as rr
from rr_actors.testing import catalog_snapshot

pytestmark = pytest.mark.both_apis  # the rules, against the async API too (conftest)


def test_an_equal_request_is_served_from_the_catalog_without_loading_again(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")

    first = consumer.call(provider.name, "leaf", "camera")
    second = consumer.call(provider.name, "leaf", "camera")

    assert ["camera"] == leaf.loads
    assert first.response == second.response


def test_dicts_with_the_same_items_in_another_order_are_one_resource(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")

    consumer.call(provider.name, "leaf", {"cmd": "sleep", "args": ["60"]})
    consumer.call(provider.name, "leaf", {"args": ["60"], "cmd": "sleep"})

    assert 1 == len(leaf.loads)


@pytest.mark.parametrize(
    "request_value",
    [
        [1, 2, [3, {"a": 4}]],
        {"nested": {"list": [1, 2], "set": {1, 2}}},
        {"a": {1, 2, 3}},
        [{"x": 1}, {"y": [2]}],
    ],
)
def test_unhashable_requests_are_deduplicated_by_equality(make_registrar, serve, request_value):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")
    equal_copy = eval(repr(request_value))  # noqa: S307 - a fresh, equal, unshared value

    consumer.call(provider.name, "leaf", request_value)
    consumer.call(provider.name, "leaf", equal_copy)

    assert 1 == len(leaf.loads)


def test_unequal_requests_that_share_a_hash_are_separate_resources(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")

    consumer.call(provider.name, "leaf", -1)
    consumer.call(provider.name, "leaf", -2)  # hash(-1) == hash(-2) in CPython

    assert [-1, -2] == leaf.loads


def test_different_requests_load_different_resources(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")

    a = consumer.call(provider.name, "leaf", {"id": 1})
    b = consumer.call(provider.name, "leaf", {"id": 2})

    assert [{"id": 1}, {"id": 2}] == leaf.loads
    assert {"resource": {"id": 1}} == a.response
    assert {"resource": {"id": 2}} == b.response


def test_equal_requests_on_different_servers_are_different_resources(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    one, two = serve(provider, "one"), serve(provider, "two")

    consumer.call(provider.name, "one", "x")
    consumer.call(provider.name, "two", "x")

    assert (["x"], ["x"]) == (one.loads, two.loads)


def test_every_call_gets_its_own_uuid4_query_id(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")

    ids = [consumer.call(provider.name, "leaf", "same").id for _ in range(3)]

    assert 3 == len(set(ids))
    assert all(4 == uuid.UUID(qid).version for qid in ids)


def test_the_returned_query_carries_its_metadata(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")

    query = consumer.call(provider.name, "leaf", [1, 2])

    expected = rr.Query(
        query.id, "leaf", provider.name, consumer.name, [1, 2], {"resource": [1, 2]}
    )
    assert expected == query


def test_a_duplicate_counts_as_one_more_consumer_under_its_own_id(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")

    first = consumer.call(provider.name, "leaf", "camera")
    second = consumer.call(provider.name, "leaf", "camera")

    assert {first.id, second.id} == {q.id for q in provider.server_queries("leaf")}
    (resource,) = catalog_snapshot(provider).resources
    assert {first.id: consumer.name, second.id: consumer.name} == resource.consumers


def test_the_caller_may_choose_the_query_id(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    chosen = str(uuid.uuid4())

    query = consumer.call(provider.name, "leaf", "camera", query_id=chosen)

    assert chosen == query.id
    assert [chosen] == [q.id for q in provider.server_queries("leaf")]


@pytest.mark.parametrize("durable", [False, True], ids=["in-memory", "save-on-modify"])
def test_retrying_a_call_with_the_same_query_id_neither_loads_nor_adds_a_consumer(
    make_registrar, serve, tmp_path, durable
):
    config = {"backup_path": str(tmp_path / "c.db"), "save_on_modify": True} if durable else {}
    provider, consumer = make_registrar("provider"), make_registrar("consumer", **config)
    leaf = serve(provider, "leaf")
    chosen = str(uuid.uuid4())

    first = consumer.call(provider.name, "leaf", "camera", query_id=chosen)
    retry = consumer.call(provider.name, "leaf", "camera", query_id=chosen)

    assert first == retry
    assert ["camera"] == leaf.loads
    assert [chosen] == [q.id for q in provider.server_queries("leaf")]
    assert [chosen] == [q.id for q in consumer.client_queries()]


class Camera:
    """A request of a custom class (no digest: its `==` runs off the actor thread)."""

    def __init__(self, rate):
        self.rate = rate

    def __eq__(self, other):
        return isinstance(other, Camera) and other.rate == self.rate

    def __hash__(self):
        return hash(self.rate)


@pytest.mark.parametrize(
    ("first", "second", "server"),
    [
        ("camera", "lidar", "leaf"),
        (Camera(30), Camera(60), "leaf"),
        ("camera", Camera(30), "leaf"),
        ("camera", "camera", "other"),
    ],
    ids=["plain", "custom", "plain-then-custom", "other-server"],
)
def test_a_query_id_reused_for_another_call_is_refused_naming_the_id(
    make_registrar, serve, first, second, server
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf, other = serve(provider, "leaf"), serve(provider, "other")
    chosen = str(uuid.uuid4())
    held = consumer.call(provider.name, "leaf", first, query_id=chosen)

    with pytest.raises(rr.DuplicateQueryIdError, match=chosen):
        consumer.call(provider.name, server, second, query_id=chosen, timeout=5)

    assert ([held], [held]) == (provider.server_queries("leaf"), consumer.client_queries())
    assert ([first], []) == (leaf.loads, other.loads)
    assert held == consumer.call(provider.name, "leaf", first, query_id=chosen)  # a retry


def test_concurrent_equal_requests_run_load_exactly_once(
    make_registrar, serve, gated_load, arrived
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    slow = gated_load(lambda request: {"resource": request})
    leaf = serve(provider, "leaf", slow)
    ids = [str(uuid.uuid4()) for _ in range(5)]
    with ThreadPoolExecutor(5) as pool:
        futures = [
            pool.submit(consumer.call, provider.name, "leaf", {"cam": 1}, query_id=qid)
            for qid in ids
        ]
        assert slow.started.wait(5)
        assert arrived(provider, ids)  # all five wait at the provider
        slow.gate.set()
        queries = [f.result(timeout=10) for f in futures]

    assert [{"cam": 1}] == leaf.loads
    assert ids == [q.id for q in queries]
    assert all({"resource": {"cam": 1}} == q.response for q in queries)
    assert set(ids) == {q.id for q in provider.server_queries("leaf")}


def test_concurrent_equal_requests_from_different_registrars_run_load_once(
    make_registrar, serve, gated_load, arrived
):
    provider = make_registrar("provider")
    consumers = [make_registrar(f"consumer{i}") for i in range(3)]
    slow = gated_load(lambda _request: "shared")
    leaf = serve(provider, "leaf", slow)
    ids = [str(uuid.uuid4()) for _ in consumers]
    with ThreadPoolExecutor(3) as pool:
        futures = [
            pool.submit(c.call, provider.name, "leaf", ["x"], query_id=qid)
            for c, qid in zip(consumers, ids, strict=True)
        ]
        assert slow.started.wait(5)
        assert arrived(provider, ids)
        slow.gate.set()
        responses = [f.result(timeout=10).response for f in futures]

    assert 1 == len(leaf.loads)
    assert ["shared"] * 3 == responses


def test_different_requests_to_one_server_load_concurrently(make_registrar, serve, shared):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    started = {"a": shared.event(), "b": shared.event()}

    def meet(request):
        started[request].set()
        other = "b" if request == "a" else "a"
        assert started[other].wait(5), "the other load never ran alongside this one"
        return request

    serve(provider, "leaf", meet)
    with ThreadPoolExecutor(2) as pool:
        futures = [pool.submit(consumer.call, provider.name, "leaf", r) for r in "ab"]
        assert ["a", "b"] == [f.result(timeout=10).response for f in futures]


def test_a_slow_load_on_one_server_does_not_stall_another_server(make_registrar, serve, gated_load):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    stuck = gated_load()
    serve(provider, "slow", stuck)
    serve(provider, "fast")
    with ThreadPoolExecutor(1) as pool:
        slow_call = pool.submit(consumer.call, provider.name, "slow", "s")
        assert stuck.started.wait(5)

        fast = consumer.call(provider.name, "fast", "f", timeout=5)

        assert {"resource": "f"} == fast.response
        stuck.gate.set()
        assert "s" == slow_call.result(timeout=10).response


def test_a_registrar_can_call_its_own_server(make_registrar, serve):
    provider = make_registrar("provider")
    leaf = serve(provider, "leaf")

    query = provider.call(provider.name, "leaf", "self")

    assert (provider.name, provider.name) == (query.origin_rr, query.serving_rr)
    assert ["self"] == leaf.loads
