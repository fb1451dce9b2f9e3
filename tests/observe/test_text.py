"""The supervision tree and the dependency graph as text (`rr_actors.observe._text`): Mermaid or
Graphviz DOT, escaped, the same for the same catalogs."""

from __future__ import annotations

from typing import Any

import pytest

import rr_actors as rr
from rr_actors._catalog import ClientRecord, Resource, ResourceState
from rr_actors.observe._text import render
from rr_actors.observe._view import dependency_graph, short, summarise_catalog
from tests.support.observed_tree import REQUEST


def test_graph_draws_the_tree_and_figure_27_as_mermaid(tree: rr.Supervisor) -> None:
    app = tree.registrar("action")
    query = app.call("cm", "filtered_camera", REQUEST)

    text = tree.graph()

    assert text.startswith("flowchart TB\n")
    assert f'subgraph r1["erm · process manager · running · pid {tree.child("erm").pid}"]' in text
    assert "n1[\"'/dev/video0'\"]" in text  # (the server's only resource: its whole request)
    assert "s1 --> r1" in text
    assert "r3 -.-> n3" in text  # action -> cm's filtered camera (no query id drawn)
    assert 2 == text.count(" -.-> n1") + text.count(" -.-> n2")  # cm -> erm's two resources
    app.unload(query.id)


def test_graph_draws_dot_with_clusters(tree: rr.Supervisor) -> None:
    text = tree.graph(format="dot")

    assert text.startswith("digraph rr_actors {\n")
    assert "subgraph" not in text  # nothing loaded: registrars without resources are nodes
    assert 's1 [label="' in text
    assert "s1 -> r1;" in text


def test_graph_refuses_an_unknown_format(tree: rr.Supervisor) -> None:
    with pytest.raises(rr.ConfigError, match="mermaid, dot"):
        tree.graph(format="svg")


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
