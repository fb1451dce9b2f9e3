"""The supervision tree and the dependency graph as text: Mermaid or Graphviz DOT.

```
 tree (LiveSource.tree, or none for backups) ─┐
 graph (dependency_graph)                     ┴─► render(graph, tree, "mermaid" | "dot") ─► str
```

Supervisors are hexagons with an arrow to each child; a registrar with resources is a
box (a Mermaid subgraph, a DOT cluster) holding them, labelled as `dependency_graph`
says; each query is a dashed arrow from its holder to the provider's resource (the
thesis's figure 2.7), with no query id (only an orphan's says "no client record"). Node
names are given in drawing order, so the same state draws the same text.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rr_actors.errors import ConfigError

__all__ = ["FORMATS", "render"]

FORMATS = ("mermaid", "dot")
"""The text formats `render` writes."""

_LABEL = 48  # characters of a resource's label kept in a drawing


def _cut(text: str, width: int = _LABEL) -> str:
    return text if len(text) <= width else text[: width - 3] + "..."


def _child_line(child: dict[str, Any]) -> str:
    parts = [child["name"]]
    if child["kind"] == "manager":
        parts.append(f"{child['isolation']} manager")
    parts.append(child["state"])
    if child.get("pid") is not None:
        parts.append(f"pid {child['pid']}")
    if child.get("restarts"):
        parts.append(f"{child['restarts']} restart" + ("s" if child["restarts"] != 1 else ""))
    return " · ".join(parts)


class _Names:
    """Short node names in drawing order, per graph id."""

    def __init__(self) -> None:
        self._names: dict[str, str] = {}
        self._counts: dict[str, int] = {}

    def __call__(self, key: str, prefix: str) -> str:
        name = self._names.get(key)
        if name is None:
            self._counts[prefix] = self._counts.get(prefix, 0) + 1
            name = self._names[key] = f"{prefix}{self._counts[prefix]}"
        return name


def _layout(
    graph: dict[str, Any], tree: dict[str, Any] | None
) -> tuple[list[tuple[str, str, str]], list[str], dict[str, list[dict[str, Any]]], dict[str, str]]:
    """Supervisor nodes and tree edges, registrar order, resources by registrar, labels."""
    supervisors: list[tuple[str, str, str]] = []  # (graph id, label, parent graph id)
    order: list[str] = []
    labels: dict[str, str] = {}

    def walk(node: dict[str, Any], parent: str) -> None:
        key = f"sup:{node['name']}"
        label = f"{node['name']}\n{node['strategy']}"
        if node.get("state") not in (None, "running"):
            label += f" · {node['state']}"
        supervisors.append((key, label, parent))
        for child in node["children"]:
            if child["kind"] == "supervisor":
                walk(child, key)
            else:
                reg = f"reg:{child['name']}"
                order.append(reg)
                labels[reg] = _child_line(child)
                supervisors.append((reg, "", key))

    if tree is not None:
        walk(tree, "")
    resources: dict[str, list[dict[str, Any]]] = {}
    for node in graph["nodes"]:
        if node["kind"] == "registrar":
            if node["id"] not in order:
                order.append(node["id"])
                labels[node["id"]] = node["label"]
        else:
            resources.setdefault(node["parent"], []).append(node)
    return supervisors, order, resources, labels


def _mermaid_text(text: str) -> str:
    escaped = text.replace("&", "#amp;").replace('"', "#quot;")
    escaped = escaped.replace("<", "#lt;").replace(">", "#gt;")
    return escaped.replace("\n", "<br/>")


def _dot_text(text: str) -> str:
    return text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


def _mermaid(graph: dict[str, Any], tree: dict[str, Any] | None) -> str:
    name = _Names()
    supervisors, order, resources, labels = _layout(graph, tree)
    lines = ["flowchart TB"]
    for key, label, _ in supervisors:
        if key.startswith("sup:"):
            lines.append(f'  {name(key, "s")}{{{{"{_mermaid_text(label)}"}}}}')
    for reg in order:
        label = _mermaid_text(labels[reg])
        held = resources.get(reg, [])
        if not held:
            lines.append(f'  {name(reg, "r")}["{label}"]')
            continue
        lines.append(f'  subgraph {name(reg, "r")}["{label}"]')
        for res in held:
            mark = " (in doubt)" if res.get("in_doubt") else ""
            text = _mermaid_text(_cut(res["label"]) + mark)
            lines.append(f'    {name(res["id"], "n")}["{text}"]')
        lines.append("  end")
    for key, _, parent in supervisors:
        if parent:
            lines.append(f"  {name(parent, 's')} --> {_tree(name, key)}")
    for edge in graph["edges"]:
        source, target = _node(name, edge["source"]), _node(name, edge["target"])
        if edge["label"]:
            lines.append(f'  {source} -. "{_mermaid_text(edge["label"])}" .-> {target}')
        else:
            lines.append(f"  {source} -.-> {target}")
    return "\n".join(lines) + "\n"


def _node(name: Callable[[str, str], str], key: str) -> str:
    """A graph node's short name: a registrar or a resource."""
    return name(key, "r" if key.startswith("reg:") else "n")


def _tree(name: Callable[[str, str], str], key: str) -> str:
    """A tree node's short name: a registrar or a supervisor."""
    return name(key, "r" if key.startswith("reg:") else "s")


def _dot_registrar(
    name: Callable[[str, str], str],
    reg: str,
    label: str,
    held: list[dict[str, Any]],
    anchors: dict[str, str],
) -> list[str]:
    """A registrar: a node, or a cluster of its resources (its first one is its anchor)."""
    reg_name = name(reg, "r")
    if not held:
        return [f'  {reg_name} [label="{_dot_text(label)}"];']
    lines = [f"  subgraph cluster_{reg_name} {{", f'    label="{_dot_text(label)}"; style=rounded;']
    for res in held:
        mark = " (in doubt)" if res.get("in_doubt") else ""
        node_name = name(res["id"], "n")
        anchors.setdefault(reg, node_name)
        style = ", style=dashed" if res.get("in_doubt") else ""
        lines.append(f'    {node_name} [label="{_dot_text(_cut(res["label"]) + mark)}"{style}];')
    lines.append("  }")
    return lines


def _dot(graph: dict[str, Any], tree: dict[str, Any] | None) -> str:
    name = _Names()
    supervisors, order, resources, labels = _layout(graph, tree)
    lines = [
        "digraph rr_actors {",
        "  rankdir=TB; compound=true;",
        '  node [shape=box, fontname="Helvetica", fontsize=10];',
        '  edge [fontname="Helvetica", fontsize=9];',
    ]
    for key, label, _ in supervisors:
        if key.startswith("sup:"):
            lines.append(f'  {name(key, "s")} [label="{_dot_text(label)}", shape=hexagon];')
    anchors: dict[str, str] = {}  # registrar drawn as a cluster -> its first resource
    for reg in order:
        lines.extend(_dot_registrar(name, reg, labels[reg], resources.get(reg, []), anchors))
    for key, _, parent in supervisors:
        if parent and key in anchors:
            cluster = f"cluster_{_tree(name, key)}"
            lines.append(f"  {name(parent, 's')} -> {anchors[key]} [lhead={cluster}];")
        elif parent:
            lines.append(f"  {name(parent, 's')} -> {_tree(name, key)};")
    for edge in graph["edges"]:
        source, target = _node(name, edge["source"]), _node(name, edge["target"])
        extra = ""
        if edge["source"] in anchors:  # from a registrar drawn as a cluster
            extra += f", ltail=cluster_{source}"
            source = anchors[edge["source"]]
        if edge["target"] in anchors:
            extra += f", lhead=cluster_{target}"
            target = anchors[edge["target"]]
        if edge["label"]:
            extra += f', label="{_dot_text(edge["label"])}"'
        lines.append(f"  {source} -> {target} [style=dashed{extra}];")
    lines.append("}")
    return "\n".join(lines) + "\n"


_RENDERERS: dict[str, Callable[[dict[str, Any], dict[str, Any] | None], str]] = {
    "mermaid": _mermaid,
    "dot": _dot,
}


def render(graph: dict[str, Any], tree: dict[str, Any] | None, fmt: str) -> str:
    """The tree (if any) and the dependency graph as Mermaid or DOT text.

    Args:
        graph: what `dependency_graph` returned.
        tree: the supervision tree as `LiveSource.tree` gives it, or `None` (backups).
        fmt: `"mermaid"` or `"dot"`.

    Returns:
        The text, ending with a newline.

    Raises:
        ConfigError: `fmt` is not one of `FORMATS`.
    """
    renderer = _RENDERERS.get(fmt)
    if renderer is None:
        raise ConfigError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    return renderer(graph, tree)
