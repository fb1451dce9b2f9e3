"""What the observer shows, as data: catalog summaries, the dependency graph, the hub, text."""

from __future__ import annotations

import json
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._catalog import ClientRecord, Resource, ResourceState
from rr_actors.observe._hub import BATCH, Hub
from rr_actors.observe._text import render
from rr_actors.observe._view import dependency_graph, registrar_ranks, short, summarise_catalog


def resource(rid: str, server: str, request: Any, consumers: dict[str, str]) -> Resource:
    made = Resource(rid, server, request, {"r": request}, ResourceState.LOADED, consumers)
    made.request_text = short(request)  # (a registrar makes it when it stores the request)
    return made


def client(qid: str, serving: str, server: str, parent: str | None) -> ClientRecord:
    return ClientRecord(rr.Query(qid, server, serving, "x", "req", None), parent, loaded=True)


def figure_27() -> dict[str, Any]:
    """Figure 2.7's catalogs: action -> cm's filtered camera -> erm's camera and filter."""
    return {
        "erm": summarise_catalog(
            "erm",
            [
                resource("cam", "camera", 0, {"q2": "cm"}),
                resource("flt", "filter", "blur", {"q3": "cm"}),
            ],
            [],
        ),
        "cm": summarise_catalog(
            "cm",
            [resource("fc", "filtered_camera", {"d": 0}, {"q1": "action"})],
            [client("q2", "erm", "camera", "fc"), client("q3", "erm", "filter", "fc")],
        ),
        "action": summarise_catalog("action", [], [client("q1", "cm", "filtered_camera", None)]),
    }


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


# -- the hub ---------------------------------------------------------------------------------


def test_a_page_gets_each_changed_section_once_and_only_the_latest_value() -> None:
    hub = Hub()
    seen: dict[str, int] = {}
    hub.put("tree", 1)
    hub.put("tree", 2)
    hub.put("graph", "g")

    first = hub.changes(seen, 0)
    unchanged = hub.put("graph", "g")
    second = hub.changes(seen, 0)

    assert [("tree", 2), ("graph", "g")] == [(k, v) for k, _, v in first.sections]
    assert not unchanged
    assert [] == second.sections


def test_a_removed_section_reaches_a_page_that_had_it_as_none() -> None:
    hub = Hub()
    seen: dict[str, int] = {}
    hub.put("catalog/cm", {"x": 1})
    hub.changes(seen, 0)

    hub.remove("catalog/cm")

    assert [("catalog/cm", None)] == [(k, v) for k, _, v in hub.changes(seen, 0).sections]
    assert [] == hub.changes({}, 0).sections  # a new page never hears of it


def test_events_are_numbered_converted_once_and_a_page_that_fell_behind_is_told() -> None:
    converted: list[int] = []

    def convert(event: int) -> dict[str, Any]:
        converted.append(event)
        return {"value": event}

    hub = Hub(ring=10, convert=convert)
    for value in range(25):
        hub.add_event(value)

    behind = hub.changes({}, 3)
    again = hub.changes({}, 20)

    assert list(range(16, 26)) == [e["seq"] for e in behind.events]
    assert 12 == behind.missed  # 4..15 fell out of the ring
    assert list(range(15, 25)) == converted  # each once, only when asked for
    assert [21, 22, 23, 24, 25] == [e["seq"] for e in again.events]


def test_a_page_gets_at_most_a_batch_of_events_at_a_time() -> None:
    hub = Hub(ring=BATCH * 3)
    for value in range(BATCH * 2):
        hub.add_event({"value": value})

    changes = hub.changes({}, 0)

    assert (BATCH, BATCH) == (len(changes.events), changes.missed)


def _strict(data: str) -> Any:
    """`data` parsed as a browser's `JSON.parse` does: `NaN` and `Infinity` are refused."""
    return json.loads(data, parse_constant=lambda name: pytest.fail(f"{name} in {data}"))


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_an_event_with_a_number_that_is_not_finite_never_costs_the_pages_the_others(
    bad: float, caplog: pytest.LogCaptureFixture
) -> None:
    """Issue 40: one `NaN` in one host's event made every page's `JSON.parse` drop the
    whole message of events, the other hosts' included."""
    hub = Hub()
    hub.add_event({"type": "InDoubt", "at": 1.0, "text": "before", "member": "alpha"})
    hub.add_event({"type": "InDoubt", "at": 2.0, "text": "bad", "load_s": bad, "member": "evil"})
    hub.add_event({"type": "InDoubt", "at": 3.0, "text": "after", "member": "bravo"})

    messages, last = hub.messages({}, 0)

    assert 3 == last
    data = messages[-1].decode().split("data: ", 1)[1].strip()
    shown = _strict(data)["events"]
    assert ["InDoubt", "Refused", "InDoubt"] == [e["type"] for e in shown]
    assert ["alpha", "evil", "bravo"] == [e["member"] for e in shown]
    assert "not finite" in shown[1]["text"]
    assert 1 == len([r for r in caplog.records if "not finite" in r.getMessage()])


def test_listeners_hear_every_change_until_removed() -> None:
    hub = Hub()
    heard: list[int] = []
    unlisten = hub.listen(lambda: heard.append(1))

    hub.put("tree", 1)
    hub.add_event({"a": 1})
    unlisten()
    hub.put("tree", 2)

    assert 2 == len(heard)


# -- text --------------------------------------------------------------------------------------


def test_mermaid_labels_cannot_break_out_of_their_quotes() -> None:
    catalogs = {"erm": summarise_catalog("erm", [resource("r", "s", 'a"b<c>', {})], [])}

    text = render(dependency_graph(catalogs), None, "mermaid")

    assert "#quot;" in text
    assert "#lt;" in text
    assert '"b' not in text.replace('["', "").replace('"]', "")


def test_dot_labels_are_escaped() -> None:
    catalogs = {"erm": summarise_catalog("erm", [resource("r", "s", 'a"b\\c', {})], [])}

    text = render(dependency_graph(catalogs), None, "dot")

    assert 'n1 [label="\'a\\"b' in text  # the quote is escaped; the label goes on


def test_the_same_catalogs_draw_the_same_text() -> None:
    assert render(dependency_graph(figure_27()), None, "mermaid") == render(
        dependency_graph(figure_27()), None, "mermaid"
    )


def test_an_unknown_format_is_a_config_error() -> None:
    with pytest.raises(rr.ConfigError, match="svg"):
        render(dependency_graph({}), None, "svg")
