"""What the observer shows, as data (`rr_actors_lab.observe._view`): catalog summaries, the
dependency graph, and a resource read by what tells it apart (issue 24, item 2)."""

from __future__ import annotations

from typing import Any

import rr_actors_lab.observe as _lab_observe
from rr_actors._catalog import Resource, ResourceState
from rr_actors_lab.observe._text import render
from rr_actors_lab.observe._view import (
    default_labels,
    dependency_graph,
    registrar_ranks,
    resource_name,
    short,
    summarise_catalog,
)
from tests.support.observed_tree import figure_27 as figure_27_tree
from tests.support.observing import client, figure_27, resource


def edges(graph: dict[str, Any]) -> set[tuple[str, str, str, bool]]:
    return {(e["source"], e["target"], e["query_id"], e["orphan"]) for e in graph["edges"]}


def test_the_graph_has_one_edge_per_query_from_its_owner_to_the_providers_resource() -> None:
    graph = dependency_graph(figure_27())

    assert {
        ("reg:action", "res:cm:fc", "q1", False),
        ("res:cm:fc", "res:erm:cam", "q2", False),
        ("res:cm:fc", "res:erm:flt", "q3", False),
    } == edges(graph)
    assert {"res:erm:cam", "res:erm:flt"} == {
        n["id"] for n in graph["nodes"] if n.get("parent") == "reg:erm"
    }


def test_a_query_whose_provider_is_unknown_points_to_the_provider_registrar() -> None:
    catalogs: dict[str, Any] = {**figure_27(), "erm": None}

    graph = dependency_graph(catalogs, {"erm": "restarting"})

    assert {("res:cm:fc", "reg:erm", "q2", False), ("res:cm:fc", "reg:erm", "q3", False)} <= edges(
        graph
    )
    assert "restarting" == next(n for n in graph["nodes"] if n["id"] == "reg:erm")["state"]


def test_a_consumer_id_no_known_client_record_explains_is_an_orphan() -> None:
    catalogs = figure_27()
    catalogs["cm"] = summarise_catalog("cm", [], [])  # cm restarted without a backup

    graph = dependency_graph(catalogs)

    assert {("reg:cm", "res:erm:cam", "q2", True), ("reg:cm", "res:erm:flt", "q3", True)} <= edges(
        graph
    )


def test_a_consumer_without_a_known_catalog_is_an_external_registrar_not_an_orphan() -> None:
    catalogs = figure_27()
    del catalogs["action"]

    graph = dependency_graph(catalogs)

    assert ("reg:action", "res:cm:fc", "q1", False) in edges(graph)
    assert "external" == next(n for n in graph["nodes"] if n["id"] == "reg:action")["state"]


def test_consumers_rank_above_their_providers_and_a_cycle_is_cut() -> None:
    assert {"action": 0, "cm": 1, "erm": 2} == registrar_ranks(dependency_graph(figure_27()))
    catalogs = {
        "a": summarise_catalog(
            "a", [resource("ra", "s", 0, {"qb": "b"})], [client("qa", "b", "s", None)]
        ),
        "b": summarise_catalog(
            "b", [resource("rb", "s", 0, {"qa": "a"})], [client("qb", "a", "s", None)]
        ),
    }
    assert {"a", "b"} == set(registrar_ranks(dependency_graph(catalogs)))


def test_a_huge_or_failing_repr_is_bounded() -> None:
    class Broken:
        def __repr__(self) -> str:
            raise ValueError("no")

    assert 80 >= len(short("x" * 10_000))
    assert 80 >= len(short(list(range(10_000))))
    assert short(Broken()).startswith("<Broken instance at")  # (reprlib's own fallback)


def test_an_in_doubt_resource_is_marked() -> None:
    loading = Resource("r", "s", 0, None, ResourceState.LOADING, {})

    summary = summarise_catalog("erm", [loading], [])

    assert (True, "loading") == (
        summary["resources"][0]["in_doubt"],
        summary["resources"][0]["state"],
    )


# -- issue 24, item 2: labels ------------------------------------------------------------------


def test_a_servers_requests_are_labelled_by_what_tells_them_apart() -> None:
    bus = "'bus': 'rr-actors-demo/bus'"

    labels = default_labels(
        [
            f"{{{bus}, 'name': 'jackal-driver', 'rate': 50}}",
            f"{{{bus}, 'name': 'jackal-navigation', 'rate': 20}}",
            f"{{{bus}, 'name': 'lidar2', 'rate': 10}}",
        ]
    )

    assert [
        "'name': 'jackal-driver', 'rate': 50",
        "'name': 'jackal-navigation', 'rate': 20",
        "'name': 'lidar2', 'rate': 10",
    ] == labels
    assert ["jackal-driver", "lidar2"] == default_labels(
        [f"{{{bus}, 'name': 'jackal-driver'}}", f"{{{bus}, 'name': 'lidar2'}}"]
    )
    assert ["'/dev/video0'"] == default_labels(["'/dev/video0'"])  # alone: the whole text
    assert ["1", "<not shown yet>"] == default_labels(["1", "<not shown yet>"])


def test_graph_text_reads_each_resource_by_its_label_and_draws_no_query_ids(
    supervisors: Any,
) -> None:
    sup = figure_27_tree(supervisors, isolation="thread").start()
    app = sup.registrar("action")
    held = [
        app.call("erm", "camera", {"bus": "b", "name": name}, timeout=5)
        for name in ("jackal-driver", "jackal-navigation")
    ]

    text = _lab_observe.graph(sup)
    dot = _lab_observe.graph(sup, format="dot")

    assert '["jackal-driver"]' in text
    assert '["jackal-navigation"]' in text
    assert 'label="jackal-driver"' in dot
    for q in held:
        assert q.id[:8] not in text
        assert q.id[:8] not in dot
        app.unload(q.id)


def test_a_label_given_by_the_server_wins_over_the_default() -> None:
    from rr_actors._catalog import Resource, ResourceState  # noqa: PLC0415

    named = Resource("r1", "program", {"name": "a"}, "ok", ResourceState.LOADED, {})
    named.request_text, named.label = "{'name': 'a'}", "the driver"
    other = Resource("r2", "program", {"name": "b"}, "ok", ResourceState.LOADED, {})
    other.request_text = "{'name': 'b'}"
    graph = dependency_graph({"erm": summarise_catalog("erm", [named, other], [])})

    assert ["the driver", "b"] == [n["label"] for n in graph["nodes"] if n["kind"] == "resource"]
    assert '["the driver"]' in render(graph, None, "mermaid")


def test_a_catalogs_resources_carry_the_short_label_the_graph_draws() -> None:
    from rr_actors._catalog import Resource, ResourceState  # noqa: PLC0415

    bus = "/home/class/rr-actors-demo/bus"  # (every request starts with it, as in the demo)
    resources = []
    for name in ("jackal-driver", "jackal-navigation"):
        request = {"bus": bus, "name": name}
        r = Resource(name, "program", request, "ok", ResourceState.LOADED, {f"{name}-q": "cm"})
        r.request_text = repr(request)
        resources.append(r)
    catalog = summarise_catalog("erm", resources, [])
    graph = dependency_graph({"erm": catalog})

    drawn = [n["label"] for n in graph["nodes"] if n["kind"] == "resource"]
    assert ["jackal-driver", "jackal-navigation"] == drawn
    assert drawn == [r["label"] for r in catalog["resources"]]
    # A status row of the timeline names the resource as the graph draws it.
    assert "erm/program jackal-navigation" == resource_name(catalog, "jackal-navigation-q")
    assert resource_name(catalog, "unknown") is None


def test_a_consumer_a_catalog_does_not_list_yet_is_named_by_the_resource_it_holds() -> None:
    # A catalog read during the load lists the resource, not yet its first consumer; the
    # observer knows which one it holds from its provider's ConsumerAdded (LiveSource._name).
    loading = Resource("cam", "camera", "/dev/video0", None, ResourceState.LOADING, {})
    loading.request_text = short("/dev/video0")
    catalog = summarise_catalog("erm", [loading], [])

    assert resource_name(catalog, "q-cm") is None
    assert "erm/camera '/dev/video0'" == resource_name(catalog, "q-cm", "cam")
    assert resource_name(catalog, "q-cm", "another") is None
