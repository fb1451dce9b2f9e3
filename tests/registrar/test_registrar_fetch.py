"""Data fetch, response updates and re-attached status callbacks (DESIGN rules 10-11)."""

from __future__ import annotations

import uuid

import pytest

import rr_actors as rr

pytestmark = pytest.mark.both_apis  # the rules, against the async API too (conftest)


def test_server_queries_lists_each_consumer_id_once_with_request_and_response(
    make_registrar, serve
):
    provider, one, two = (make_registrar(n) for n in ("provider", "one", "two"))
    serve(provider, "leaf")
    made = [
        one.call(provider.name, "leaf", {"cam": 1}),
        one.call(provider.name, "leaf", {"cam": 1}),
        two.call(provider.name, "leaf", {"cam": 2}),
    ]

    listed = provider.server_queries("leaf")

    assert sorted(made, key=lambda q: q.id) == sorted(listed, key=lambda q: q.id)


def test_server_queries_does_not_list_other_servers_or_released_ids(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    serve(provider, "other")
    kept = consumer.call(provider.name, "leaf", "x")
    consumer.unload(consumer.call(provider.name, "leaf", "x").id)
    consumer.call(provider.name, "other", "x")

    assert [kept] == provider.server_queries("leaf")


def test_server_queries_of_an_unknown_server_raises(make_registrar):
    provider = make_registrar("provider")

    with pytest.raises(rr.UnknownServerError):
        provider.server_queries("nope")


def test_fetch_queries_lists_exactly_what_this_registrar_holds_there(make_registrar, serve):
    provider, mine, theirs = (make_registrar(n) for n in ("provider", "mine", "theirs"))
    serve(provider, "leaf")
    held = [mine.call(provider.name, "leaf", r) for r in ("a", "a", "b")]
    theirs.call(provider.name, "leaf", "a")

    fetched = mine.fetch_queries(provider.name, "leaf")

    assert sorted(held, key=lambda q: q.id) == sorted(fetched, key=lambda q: q.id)


def test_fetch_queries_includes_dependencies_held_by_this_registrar(make_registrar, serve):
    consumer, agent, producer = (make_registrar(n) for n in ("consumer", "agent", "producer"))
    serve(producer, "leaf")
    serve(agent, "composite", lambda r: agent.call(producer.name, "leaf", r).id)
    query = consumer.call(agent.name, "composite", "x")

    (fetched,) = agent.fetch_queries(producer.name, "leaf")

    assert (query.response, "x", agent.name) == (fetched.id, fetched.request, fetched.origin_rr)


def test_fetch_queries_is_empty_after_everything_was_unloaded(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    consumer.unload(consumer.call(provider.name, "leaf", "x").id)

    assert [] == consumer.fetch_queries(provider.name, "leaf")


def test_fetch_queries_from_an_unknown_registrar_or_server_raises(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")

    with pytest.raises(rr.UnknownServerError):
        consumer.fetch_queries(f"nobody-{uuid.uuid4().hex[:8]}", "leaf")
    with pytest.raises(rr.UnknownServerError):
        consumer.fetch_queries(provider.name, "nope")


def test_client_queries_lists_the_loaded_queries_a_registrar_holds(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    first = consumer.call(provider.name, "leaf", "a")
    second = consumer.call(provider.name, "leaf", "b")

    assert [first, second] == consumer.client_queries()


def test_update_response_reaches_the_provider_catalog_and_every_consumer(make_registrar, serve):
    provider, one, two = (make_registrar(n) for n in ("provider", "one", "two"))
    serve(provider, "leaf")
    q1 = one.call(provider.name, "leaf", "x")
    q2 = two.call(provider.name, "leaf", "x")

    provider.update_response(q1.id, {"port": 4242})

    assert [{"port": 4242}] * 2 == [q.response for q in provider.server_queries("leaf")]
    assert [{"port": 4242}] == [q.response for q in two.fetch_queries(provider.name, "leaf")]
    assert [q1.id] == [q.id for q in one.client_queries() if q.response == {"port": 4242}]
    assert [q2.id] == [q.id for q in two.client_queries() if q.response == {"port": 4242}]


def test_a_duplicate_after_update_response_gets_the_new_response(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")
    query = consumer.call(provider.name, "leaf", "x")
    provider.update_response(query.id, "ready")

    duplicate = consumer.call(provider.name, "leaf", "x")

    assert ("ready", 1) == (duplicate.response, len(leaf.loads))


def test_the_unload_callback_gets_the_updated_response(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")
    query = consumer.call(provider.name, "leaf", "x")
    provider.update_response(query.id, "ready")

    consumer.unload(query.id)

    assert [("x", "ready")] == leaf.unloads


def test_update_response_for_an_unknown_id_raises(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    query = consumer.call(provider.name, "leaf", "x")

    with pytest.raises(rr.UnknownQueryError):
        provider.update_response(str(uuid.uuid4()), "nope")
    with pytest.raises(rr.UnknownQueryError):
        consumer.update_response(query.id, "not the provider")

    assert [{"resource": "x"}] == [q.response for q in provider.server_queries("leaf")]


def test_set_status_callback_attaches_a_callback_to_a_query_made_without_one(
    make_registrar, serve, inbox
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    query = consumer.call(provider.name, "leaf", "x")
    box = inbox()

    consumer.set_status_callback(query.id, box)
    provider.send_status(query.id, rr.Status.ERROR, "lost")

    assert [query.id] == [update.query_id for _, update in box.updates]


def test_set_status_callback_replaces_the_previous_callback(make_registrar, serve, inbox):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    old, new = inbox(), inbox()
    query = consumer.call(provider.name, "leaf", "x", on_status=old)

    consumer.set_status_callback(query.id, new)
    provider.send_status(query.id, rr.Status.OK, "")

    assert ([], 1) == (old.updates, len(new.updates))


def test_set_status_callback_for_an_unknown_id_raises(make_registrar):
    consumer = make_registrar("consumer")

    with pytest.raises(rr.UnknownQueryError):
        consumer.set_status_callback(str(uuid.uuid4()), lambda q, u: None)


def test_set_status_callback_rejects_a_non_callable(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    query = consumer.call(provider.name, "leaf", "x")

    with pytest.raises(rr.ConfigError):
        consumer.set_status_callback(query.id, "not callable")  # type: ignore[arg-type]
