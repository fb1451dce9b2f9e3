"""TeMoto's seven core registrar tests (thesis table 4.3), re-expressed for rr_actors.

Each test starts its own registrars, so they run in any order (the originals depended
on their order).
"""

from __future__ import annotations

import pytest

import rr_actors as rr
from rr_actors.testing import catalog_snapshot


@pytest.fixture
def chain(make_registrar, serve):
    """TeMoto's topology: consumer -> agent -> producer (the agent's load calls the producer)."""
    consumer, agent, producer = (make_registrar(n) for n in ("consumer", "agent", "producer"))
    leaf = serve(producer, "producer_server")
    middle = serve(
        agent,
        "agent_server",
        lambda r: {"via": agent.call(producer.name, "producer_server", r).response},
    )
    return consumer, agent, producer, middle, leaf


def test_resource_registrar_test_chain_loads_and_unloads_with_exact_counts(chain):
    consumer, agent, _, middle, leaf = chain

    first = consumer.call(agent.name, "agent_server", "lidar")
    second = consumer.call(agent.name, "agent_server", "lidar")
    assert (1, 1) == (len(middle.loads), len(leaf.loads))
    assert {"via": {"resource": "lidar"}} == first.response == second.response

    consumer.unload(first.id)
    assert (0, 0) == (len(middle.unloads), len(leaf.unloads))
    consumer.unload(second.id)
    assert (1, 1) == (len(middle.unloads), len(leaf.unloads))

    for registrar in chain[:3]:
        snapshot = catalog_snapshot(registrar)
        assert ((), ()) == (snapshot.resources, snapshot.clients)


def test_registrar_configuration_test_properties_reach_the_registrar(
    make_registrar, serve, tmp_path
):
    path = tmp_path / "configured.db"
    registrar = make_registrar(
        "configured", backup_path=str(path), save_on_modify=True, call_timeout=7.5
    )
    serve(registrar, "leaf")

    query = registrar.call(registrar.name, "leaf", "x")

    assert registrar.name == registrar.config.name
    assert (registrar.name, registrar.name) == (query.origin_rr, query.serving_rr)
    assert (str(path), True, 7.5) == (
        registrar.config.backup_path,
        registrar.config.save_on_modify,
        registrar.config.call_timeout,
    )
    assert path.exists(), "save_on_modify wrote no backup"


def test_registrar_configuration_test_a_name_alone_gives_the_defaults(make_registrar):
    registrar = make_registrar("defaults")

    assert rr.RegistrarConfig(name=registrar.name) == registrar.config


def test_catalog_response_update_test_consumers_see_the_updated_response(chain):
    consumer, agent, producer, _, _ = chain
    query = consumer.call(agent.name, "agent_server", "lidar")
    (leaf_query,) = producer.server_queries("producer_server")

    producer.update_response(leaf_query.id, "calibrated")
    agent.update_response(query.id, "agent ready")

    assert ["calibrated"] == [
        q.response for q in agent.fetch_queries(producer.name, "producer_server")
    ]
    assert ["agent ready"] == [q.response for q in consumer.client_queries()]


def test_client_unload_test_stopping_a_client_frees_its_resources(chain):
    consumer, _, producer, middle, leaf = chain
    consumer.call(chain[1].name, "agent_server", "lidar")

    consumer.stop()

    assert (1, 1) == (len(middle.unloads), len(leaf.unloads))
    assert [] == producer.server_queries("producer_server")


def test_callback_error_test_error_stack_propagates_and_dependencies_unload(make_registrar, serve):
    consumer, agent, producer = (make_registrar(n) for n in ("consumer", "agent", "producer"))
    good = serve(producer, "good")

    def failing(request):
        raise RuntimeError("producer broke")

    serve(producer, "bad", failing)

    def agent_load(request):
        agent.call(producer.name, "good", request)
        return agent.call(producer.name, "bad", request).response

    serve(agent, "agent_server", agent_load)

    with pytest.raises(rr.ResourceLoadError) as info:
        consumer.call(agent.name, "agent_server", "x")

    assert [(producer.name, "bad"), (agent.name, "agent_server")] == [
        (f.registrar, f.server) for f in info.value.stack
    ]
    assert "producer broke" == info.value.stack[0].message
    assert [("x", {"resource": "x"})] == good.unloads


def test_data_fetch_test_a_client_fetches_its_queries_from_another_registrar(chain):
    consumer, agent, _, _, _ = chain
    queries = [consumer.call(agent.name, "agent_server", r) for r in ("a", "a", "b")]

    fetched = consumer.fetch_queries(agent.name, "agent_server")

    assert sorted(queries, key=lambda q: q.id) == sorted(fetched, key=lambda q: q.id)


def test_rr_server_status_callback_test_every_server_and_client_in_the_chain_runs(chain, inbox):
    consumer, agent, producer, middle, leaf = chain
    box = inbox()
    query = consumer.call(agent.name, "agent_server", "lidar", on_status=box)
    (leaf_query,) = producer.server_queries("producer_server")

    producer.send_status(leaf_query.id, rr.Status.ERROR, "lidar lost")

    assert (1, 1) == (len(leaf.statuses), len(middle.statuses))
    assert [(query.id, rr.Status.ERROR)] == [(u.query_id, u.status) for _, u in box.updates]
