"""What the observer shows, as JSON-able data: catalogs, the dependency graph, the tree.

Pure data, no threads and no I/O: the live source, the backup source, the page and the
text renderers (`_text.py`) all read these shapes.

```
 catalog rows (Resource, ClientRecord) ──summarise_catalog──► catalog summary (per registrar)
 catalog summaries of every registrar ──dependency_graph────► {"nodes": [...], "edges": [...]}
```

A catalog summary is::

    {"registrar": "cm", "servers": ["lidar"],
     "resources": [{"id", "server", "state", "in_doubt", "request", "response",
                    "consumers": [{"query_id", "origin"}]}],
     "clients": [{"query_id", "serving_rr", "server", "request", "parent", "loaded"}],
     "in_doubt": [{"id", "request"}]}

Requests and responses are shown as bounded `repr`s (`reprlib`): a huge value costs a
bounded time to show, and the page never gets more than `REPR_WIDTH` characters of one.
"""

from __future__ import annotations

import reprlib
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from rr_actors._catalog import ClientRecord, Resource, ResourceState
from rr_actors._types import Query

__all__ = [
    "REPR_WIDTH",
    "dependency_graph",
    "registrar_ranks",
    "short",
    "summarise_catalog",
]

REPR_WIDTH = 80
"""Characters of a request's or response's `repr` the observer keeps."""

_REPR = reprlib.Repr()  # (Python 3.11 takes no keyword arguments here)
_REPR.maxlevel = 3
_REPR.maxstring = _REPR.maxother = REPR_WIDTH
_REPR.maxlong = 40
_REPR.maxdict = _REPR.maxlist = _REPR.maxtuple = _REPR.maxset = 6


def short(value: Any, width: int = REPR_WIDTH) -> str:
    """A bounded `repr` of `value` (never raises: a failing `repr` is named instead)."""
    try:
        text = _REPR.repr(value)
    except Exception as exc:  # noqa: BLE001 - any user object: show that it failed
        text = f"<repr failed: {type(exc).__name__}>"
    return text if len(text) <= width else text[: width - 3] + "..."


def _resource(resource: Resource) -> dict[str, Any]:
    state = resource.state
    return {
        "id": resource.id,
        "server": resource.server,
        "state": state.value,
        "in_doubt": state is not ResourceState.LOADED,
        "request": short(_field(resource, "request")),
        "response": short(_field(resource, "response")),
        "consumers": [{"query_id": q, "origin": o} for q, o in list(resource.consumers.items())],
    }


def _field(resource: Resource, name: str) -> Any:
    """A restored resource decodes its values on first access; that may fail."""
    try:
        return getattr(resource, name)
    except Exception as exc:  # noqa: BLE001 - a value that cannot be decoded is shown as such
        return _Unshowable(f"<cannot decode: {exc}>")


class _Unshowable:
    def __init__(self, text: str) -> None:
        self.text = text

    def __repr__(self) -> str:
        return self.text


def _client(record: ClientRecord) -> dict[str, Any]:
    query = record.query
    return {
        "query_id": query.id,
        "serving_rr": query.serving_rr,
        "server": query.server,
        "request": short(query.request),
        "parent": record.parent,
        "loaded": record.loaded,
    }


def summarise_catalog(
    registrar: str,
    resources: Iterable[Resource],
    clients: Iterable[ClientRecord],
    *,
    servers: Sequence[str] | None = None,
    in_doubt: Iterable[Query] = (),
) -> dict[str, Any]:
    """One registrar's catalog rows as the observer shows them.

    Args:
        registrar: the registrar's name.
        resources: its served resources.
        clients: its client records (the queries it holds, its own servers' included).
        servers: its registered servers (`None`: those that serve a resource).
        in_doubt: the loads a crash cut short, found when it was restored (rule 16).

    Returns:
        The catalog summary (see the module docstring).
    """
    rows = [_resource(r) for r in resources]
    known = list(servers) if servers is not None else []
    for row in rows:
        if row["server"] not in known:
            known.append(row["server"])
    return {
        "registrar": registrar,
        "servers": known,
        "resources": rows,
        "clients": [_client(c) for c in clients],
        "in_doubt": [{"id": q.id, "request": short(q.request)} for q in in_doubt],
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
            for resource in catalog["resources"]:
                node = _resource_node(name, resource["id"])
                self.nodes[node] = {
                    "id": node,
                    "kind": "resource",
                    "parent": f"reg:{name}",
                    "label": f"{resource['server']}: {resource['request']}",
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
            "label": qid[:8],
            "loaded": loaded,
            "orphan": orphan,
        }


def dependency_graph(
    catalogs: Mapping[str, dict[str, Any] | None],
    states: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """The dependency graph across registrars: who holds which resource, through which query.

    Nodes are registrars (`"reg:<name>"`, compound: their resources are inside) and
    resources (`"res:<registrar>:<id>"`, labelled `server: request`). An edge is one
    query, from the resource that holds it as a dependency (or from the registrar, for
    a top-level call) to the provider's resource that serves it: the thesis's figure
    2.7. A query whose provider's catalog is not known points to the provider registrar.

    Args:
        catalogs: registrar name -> its catalog summary (`None`: not known now).
        states: registrar name -> what to show of it (`"running"`, `"restarting"`, ...).

    Returns:
        `{"nodes": [{"id", "kind", "label", "parent", "state", ...}], "edges": [{"id",
        "source", "target", "label", "loaded", "orphan"}]}`, in a stable order. An
        orphan edge is a consumer id at a provider whose consumer's catalog is known and
        holds no such query (a consumer restarted without a backup, say).
    """
    graph = _Graph(catalogs, states or {})
    for name in catalogs:
        graph.registrar(name)
    graph.add_resources()
    graph.add_queries()
    graph.add_unexplained()
    return {
        "nodes": list(graph.nodes.values()),
        "edges": sorted(graph.edges.values(), key=lambda e: (e["source"], e["target"], e["id"])),
    }


def registrar_ranks(graph: Mapping[str, Any]) -> dict[str, int]:
    """Each registrar's row in a layered drawing: consumers above their providers.

    The rank is the longest chain of registrars that consume from it (0: nobody does).
    A cycle of registrars (a self-call, or two that serve each other) is cut, not looped.

    Args:
        graph: what `dependency_graph` returned.

    Returns:
        Registrar name -> rank.
    """
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
