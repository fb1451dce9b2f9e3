"""The supervision tree and the dependency graph as text (`rr_actors_lab.observe._text`): Mermaid or
Graphviz DOT, escaped, the same for the same catalogs."""

from __future__ import annotations

import pytest

import rr_actors as rr
from rr_actors_lab.observe import graph
from rr_actors_lab.observe._text import render
from rr_actors_lab.observe._view import dependency_graph, summarise_catalog
from tests.support.observed_tree import REQUEST
from tests.support.observing import figure_27, resource


def test_graph_draws_the_tree_and_figure_27_as_mermaid(tree: rr.Supervisor) -> None:
    app = tree.registrar("action")
    query = app.call("cm", "filtered_camera", REQUEST)

    text = graph(tree)

    assert text.startswith("flowchart TB\n")
    assert f'subgraph r1["erm · process manager · running · pid {tree.child("erm").pid}"]' in text
    assert "n1[\"'/dev/video0'\"]" in text  # (the server's only resource: its whole request)
    assert "s1 --> r1" in text
    assert "r3 -.-> n3" in text  # action -> cm's filtered camera (no query id drawn)
    assert 2 == text.count(" -.-> n1") + text.count(" -.-> n2")  # cm -> erm's two resources
    app.unload(query.id)


def test_graph_draws_dot_with_clusters(tree: rr.Supervisor) -> None:
    text = graph(tree, format="dot")

    assert text.startswith("digraph rr_actors {\n")
    assert "subgraph" not in text  # nothing loaded: registrars without resources are nodes
    assert 's1 [label="' in text
    assert "s1 -> r1;" in text


def test_graph_refuses_an_unknown_format(tree: rr.Supervisor) -> None:
    with pytest.raises(rr.ConfigError, match="mermaid, dot"):
        graph(tree, format="svg")


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
