"""rr_actors_lab.experiments.services: the generic manager's statuses on a schedule."""

from __future__ import annotations

import queue
import uuid

import pytest

import rr_actors as rr
from rr_actors_lab.experiments.services import service


def test_a_service_with_status_every_sends_a_warning_to_its_consumer_until_it_stops() -> None:
    name = f"svc-{uuid.uuid4().hex[:8]}"
    provider = rr.ResourceRegistrar.start(name)
    consumer = rr.ResourceRegistrar.start(f"app-{uuid.uuid4().hex[:8]}")
    heard: queue.Queue[rr.StatusUpdate] = queue.Queue()
    try:
        service(provider, status_every=0.05)
        query = consumer.call(name, "resource", "cam", on_status=lambda _q, u: heard.put(u))

        update = heard.get(timeout=5.0)

        expected = (query.id, rr.Status.WARNING, "scheduled", f"{name}/resource")
        assert expected == (update.query_id, update.status, update.message, update.source)
        consumer.unload(query.id)
    finally:
        consumer.stop()
        provider.stop()


def test_a_service_with_uses_request_makes_its_resources_share_one_dependency() -> None:
    db_name, api_name = f"db-{uuid.uuid4().hex[:8]}", f"api-{uuid.uuid4().hex[:8]}"
    db = rr.ResourceRegistrar.start(db_name)
    api = rr.ResourceRegistrar.start(api_name)
    app = rr.ResourceRegistrar.start(f"app-{uuid.uuid4().hex[:8]}")
    try:
        service(db)
        service(api, uses=[db_name], uses_request="shared")
        first = app.call(api_name, "resource", "a")
        second = app.call(api_name, "resource", "b")

        held = db.server_queries("resource")

        assert [("shared", api_name)] * 2 == [(q.request, q.origin_rr) for q in held]
        assert 1 == len({q.response["request"] for q in held})
        app.unload(first.id)
        app.unload(second.id)
        assert [] == db.server_queries("resource")
    finally:
        app.stop()
        api.stop()
        db.stop()


def test_a_service_with_list_every_lists_its_server_and_its_registrar_publishes_it() -> None:
    name = f"svc-{uuid.uuid4().hex[:8]}"
    provider = rr.ResourceRegistrar.start(name)
    consumer = rr.ResourceRegistrar.start(f"app-{uuid.uuid4().hex[:8]}")
    heard: queue.Queue[rr.events.ServerQueriesListed] = queue.Queue()
    subscription = provider.subscribe(
        lambda e: heard.put(e) if isinstance(e, rr.events.ServerQueriesListed) else None
    )
    try:
        service(provider, list_every=0.05)
        query = consumer.call(name, "resource", "cam")

        listing = heard.get(timeout=5.0)
        while query.id not in listing.query_ids:
            listing = heard.get(timeout=5.0)

        assert (name, "resource", (query.id,)) == (
            listing.registrar,
            listing.server,
            listing.query_ids,
        )
        consumer.unload(query.id)
    finally:
        subscription.close()
        consumer.stop()
        provider.stop()


def test_a_service_refuses_a_negative_list_every() -> None:
    with rr.ResourceRegistrar.start(f"svc-{uuid.uuid4().hex[:8]}") as provider:
        with pytest.raises(rr.ConfigError, match="list_every"):
            service(provider, list_every=-1.0)
        with pytest.raises(rr.ConfigError, match="status_every"):
            service(provider, status_every="0.2")  # type: ignore[arg-type]
