"""What the observer shows, as JSON-able data: catalogs, the dependency graph, the tree.

Pure data, no threads and no I/O: the live source, the backup source, the page and the
text renderers (`_text.py`) all read these shapes.

```
 catalog rows (Resource, ClientRecord) ──summarise_catalog──► catalog summary (per registrar)
 catalog summaries of every registrar ──dependency_graph────► {"nodes": [...], "edges": [...]}
```

A catalog summary is::

    {"registrar": "cm", "servers": ["lidar"],
     "resources": [{"id", "server", "state", "in_doubt", "request", "response", "label",
                    "consumers": [{"query_id", "origin"}]}],
     "clients": [{"query_id", "serving_rr", "server", "request", "parent", "loaded"}],
     "in_doubt": [{"id", "request"}]}

Requests and responses are shown by the display texts their registrar stored
(`rr_actors._catalog.texts`): no `repr` is called and nothing is unpickled.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from rr_actors._catalog import ClientRecord, Resource, ResourceState
from rr_actors._catalog.texts import LABEL_WIDTH, NOT_SHOWN_YET, TEXT_WIDTH, display_text

__all__ = [
    "REPR_WIDTH",
    "default_labels",
    "dependency_graph",
    "registrar_ranks",
    "resource_name",
    "short",
    "shown",
    "summarise_catalog",
]

REPR_WIDTH = TEXT_WIDTH
"""Characters of a request's or response's display text the observer shows."""

short = display_text
"""A bounded `repr` (the one registrars make their display texts with)."""


def shown(text: Any, width: int = REPR_WIDTH) -> str:
    """A stored display text as the page gets it: a string (else not shown), `width` chars at
    most."""
    if text is None:
        return NOT_SHOWN_YET
    if type(text) is not str:
        return "<not shown: not a text>"
    return text if len(text) <= width else text[: width - 3] + "..."


def _resource(resource: Resource) -> dict[str, Any]:
    state = resource.state
    label = resource.label
    return {
        "id": resource.id,
        "server": resource.server,
        "state": state.value,
        "in_doubt": state is not ResourceState.LOADED,
        "request": shown(resource.request_text),
        "response": shown(resource.response_text),
        "label": None if label is None else shown(label, LABEL_WIDTH),
        "consumers": [{"query_id": q, "origin": o} for q, o in list(resource.consumers.items())],
    }


def _client(record: ClientRecord) -> dict[str, Any]:
    query = record.query
    return {
        "query_id": query.id,
        "serving_rr": query.serving_rr,
        "server": query.server,
        "request": shown(record.request_text),
        "parent": record.parent,
        "loaded": record.loaded,
    }


def summarise_catalog(
    registrar: str,
    resources: Iterable[Resource],
    clients: Iterable[ClientRecord],
    *,
    servers: Sequence[str] | None = None,
    in_doubt: Iterable[tuple[str, str | None]] = (),
) -> dict[str, Any]:
    """One registrar's catalog rows as the observer shows them.

    Args:
        registrar: the registrar's name.
        resources: its served resources.
        clients: its client records (the queries it holds, its own servers' included).
        servers: its registered servers (`None`: those that serve a resource).
        in_doubt: the loads a crash cut short, found when it was restored (rule 16): each
            resource's id and request display text.

    Returns:
        The catalog summary (see the module docstring).
    """
    rows = [_resource(r) for r in resources]
    for row, label in zip(rows, _labels(rows), strict=True):
        row["label"] = label  # (the graph's and the timeline's name for it)
    known = list(servers) if servers is not None else []
    for row in rows:
        if row["server"] not in known:
            known.append(row["server"])
    return {
        "registrar": registrar,
        "servers": known,
        "resources": rows,
        "clients": [_client(c) for c in clients],
        "in_doubt": [{"id": rid, "request": shown(text)} for rid, text in in_doubt],
    }


# -- the dependency graph (thesis figure 2.7) ---------------------------------------------


def _resource_node(registrar: str, resource_id: str) -> str:
    return f"res:{registrar}:{resource_id}"


class _Graph:
    """The nodes and edges `dependency_graph` collects, keyed by id."""

    def __init__(
        self, catalogs: Mapping[str, dict[str, Any] | None], states: Mapping[str, str]
    ) -> None:
        self.catalogs = catalogs
        self.states = states
        self.nodes: dict[str, dict[str, Any]] = {}
        self.edges: dict[str, dict[str, Any]] = {}
        self.serving: dict[str, str] = {}  # query id -> the provider's resource node

    def registrar(self, name: str) -> str:
        node = f"reg:{name}"
        if node not in self.nodes:
            known = self.catalogs.get(name) is not None
            state = self.states.get(name, "known" if known else "external")
            self.nodes[node] = {"id": node, "kind": "registrar", "label": name, "state": state}
        return node

    def known(self) -> Iterable[tuple[str, dict[str, Any]]]:
        return ((n, c) for n, c in self.catalogs.items() if c is not None)

    def add_resources(self) -> None:
        for name, catalog in self.known():
            labels = _labels(catalog["resources"])
            for resource, label in zip(catalog["resources"], labels, strict=True):
                node = _resource_node(name, resource["id"])
                self.nodes[node] = {
                    "id": node,
                    "kind": "resource",
                    "parent": f"reg:{name}",
                    "label": label,
                    "request": resource["request"],
                    "server": resource["server"],
                    "resource_id": resource["id"],
                    "registrar": name,
                    "state": resource["state"],
                    "in_doubt": resource["in_doubt"],
                    "consumers": len(resource["consumers"]),
                }
                for consumer in resource["consumers"]:
                    self.serving[consumer["query_id"]] = node

    def add_queries(self) -> None:
        """One edge per client record: from its owner resource (or registrar) to the provider's."""
        for name, catalog in self.known():
            for client in catalog["clients"]:
                qid, parent = client["query_id"], client["parent"]
                source = _resource_node(name, parent) if parent else self.registrar(name)
                if source not in self.nodes:
                    source = self.registrar(name)
                target = self.serving.get(qid) or self.registrar(client["serving_rr"])
                self.edge(qid, source, target, loaded=client["loaded"], orphan=False)

    def add_unexplained(self) -> None:
        """Consumer ids at a provider that no known client record explains."""
        for name, catalog in self.known():
            for resource in catalog["resources"]:
                for consumer in resource["consumers"]:
                    qid = consumer["query_id"]
                    if qid in self.edges:
                        continue
                    # its consumer's catalog is known and does not hold it: nobody will
                    # release it unless the consumer comes back for it (or dies for good)
                    orphan = self.catalogs.get(consumer["origin"]) is not None
                    source = self.registrar(consumer["origin"])
                    target = _resource_node(name, resource["id"])
                    self.edge(qid, source, target, loaded=True, orphan=orphan)

    def edge(self, qid: str, source: str, target: str, *, loaded: bool, orphan: bool) -> None:
        self.edges[qid] = {
            "id": f"q:{qid}",
            "source": source,
            "target": target,
            "label": "no client record" if orphan else "",  # (ids overlap: in "query_id")
            "query_id": qid,
            "loaded": loaded,
            "orphan": orphan,
        }


def _labels(resources: list[dict[str, Any]]) -> list[str]:
    """Each resource's label: its own, else its default among its server's resources."""
    by_server: dict[str, list[int]] = {}
    for index, resource in enumerate(resources):
        by_server.setdefault(resource["server"], []).append(index)
    labels = [""] * len(resources)
    for indexes in by_server.values():
        defaults = default_labels([resources[i]["request"] for i in indexes])
        for i, default in zip(indexes, defaults, strict=True):
            labels[i] = resources[i].get("label") or default
    return labels


def resource_name(
    catalog: Mapping[str, Any] | None, query_id: str, resource_id: str | None = None
) -> str | None:
    """`"<registrar>/<server> <label>"` of the resource a consumer's `query_id` holds (or
    `resource_id`, when its `ConsumerAdded` said), as the status timeline names it; `None` if
    `catalog` has neither."""
    if catalog is None:
        return None
    for resource in catalog["resources"]:
        if resource["id"] == resource_id or any(
            c["query_id"] == query_id for c in resource["consumers"]
        ):
            label = resource.get("label") or resource["request"]
            return f"{catalog['registrar']}/{resource['server']} {label}"
    return None


def default_labels(texts: Sequence[str]) -> list[str]:
    """Short labels for one server's resources, from their requests' display texts.

    For dict requests, each label is the items whose text differs between the server's
    requests (the value alone if one is left: `jackal-driver`); any other request, a server's
    only resource, or requests that differ nowhere visible keep the whole text. Computed, not
    stored: it depends on which resources the server holds now.

    Args:
        texts: the display texts of one server's requests.

    Returns:
        One label per text, at most `LABEL_WIDTH` characters each.
    """
    parsed = [_dict_items(text) for text in texts]
    if len(texts) < 2 or any(items is None for items in parsed):
        return [_fit(text) for text in texts]
    everywhere = set.intersection(*(set(items) for items in parsed if items is not None))
    labels = []
    for text, items in zip(texts, parsed, strict=True):
        rest = [item for item in items or () if item not in everywhere]
        if not rest:
            labels.append(_fit(text))
        elif len(rest) == 1:
            labels.append(_fit(_value_of(rest[0])))
        else:
            labels.append(_fit(", ".join(rest)))
    return labels


_STRING = re.compile(r"'[^'\\]*'|\"[^\"\\]*\"")


def _dict_items(text: str) -> list[str] | None:
    """The top-level `key: value` items of a dict's `repr`, or `None` if it is not one."""
    if len(text) < 2 or text[0] != "{" or text[-1] != "}" or ":" not in text:
        return None
    items: list[str] = []
    depth, start, quote = 0, 1, ""
    body = text[1:-1]
    for index, char in enumerate(body, 1):
        if quote:
            if char == quote and text[index - 1] != "\\":
                quote = ""
        elif char in "'\"":
            quote = char
        elif char in "([{":
            depth += 1
        elif char in ")]}":
            depth -= 1
        elif char == "," and depth == 0:
            items.append(text[start:index].strip())
            start = index + 1
    items.append(text[start:-1].strip())
    return items if all(":" in item for item in items) else None


def _value_of(item: str) -> str:
    """An item's value; a plain string value without its quotes."""
    value = item.split(":", 1)[1].strip() if ":" in item else item
    return value[1:-1] if _STRING.fullmatch(value) else value


def _fit(text: str) -> str:
    return text if len(text) <= LABEL_WIDTH else text[: LABEL_WIDTH - 3] + "..."


def dependency_graph(
    catalogs: Mapping[str, dict[str, Any] | None],
    states: Mapping[str, str] | None = None,
    *,
    hosts: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """The dependency graph across registrars: who holds which resource, through which query.

    Nodes are registrars (`"reg:<name>"`, compound) and resources (`"res:<registrar>:<id>"`,
    labelled by `label(request)` or `default_labels`). An edge is one query, from the
    resource holding it as a dependency (or the registrar, for a top-level call) to the
    provider's resource serving it (or the provider, if its catalog is not known): the
    thesis's figure 2.7.

    Args:
        catalogs: registrar name -> its catalog summary (`None`: not known now).
        states: registrar name -> what to show of it (`"running"`, `"restarting"`, ...).
        hosts: registrar name -> the member name of its host: each node gets its `"host"`,
            each edge `"crosses"` (its ends on known, different hosts).

    Returns:
        `{"nodes": [{"id", "kind", "label", "parent", "state", ...}], "edges": [{"id",
        "source", "target", "label", "query_id", "loaded", "orphan"}]}`, in a stable order.
        An edge's label is empty but an orphan's: a consumer id whose consumer's known
        catalog holds no such query.
    """
    graph = _Graph(catalogs, states or {})
    for name in catalogs:
        graph.registrar(name)
    graph.add_resources()
    graph.add_queries()
    graph.add_unexplained()
    if hosts is not None:
        owner = {}
        for node in graph.nodes.values():
            registrar = node["registrar"] if node["kind"] == "resource" else node["id"][4:]
            node["host"] = hosts.get(registrar)
            owner[node["id"]] = node["host"]
        for edge in graph.edges.values():
            ends = owner.get(edge["source"]), owner.get(edge["target"])
            edge["crosses"] = None not in ends and ends[0] != ends[1]
    return {
        "nodes": list(graph.nodes.values()),
        "edges": sorted(graph.edges.values(), key=lambda e: (e["source"], e["target"], e["id"])),
    }


def registrar_ranks(graph: Mapping[str, Any]) -> dict[str, int]:
    """Each registrar's row in a layered drawing: the longest chain of registrars consuming from
    it (0: nobody does); cycles are cut. `graph` is what `dependency_graph` returned."""
    owner = {n["id"]: (n.get("parent") or n["id"]) for n in graph["nodes"]}
    names = [n["id"] for n in graph["nodes"] if n["kind"] == "registrar"]
    above: dict[str, set[str]] = {name: set() for name in names}
    for edge in graph["edges"]:
        consumer, provider = owner.get(edge["source"]), owner.get(edge["target"])
        if consumer and provider and consumer != provider:
            above[provider].add(consumer)
    ranks: dict[str, int] = {}

    def rank(name: str, path: frozenset[str]) -> int:
        if name in ranks:
            return ranks[name]
        consumers = [c for c in above.get(name, ()) if c not in path]
        value = 1 + max((rank(c, path | {name}) for c in consumers), default=-1)
        ranks[name] = value
        return value

    for name in names:
        rank(name, frozenset())
    return {name.removeprefix("reg:"): value for name, value in ranks.items()}
