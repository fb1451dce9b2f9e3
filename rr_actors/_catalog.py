"""The resource catalog: pure data, no threads, no I/O.

The catalog records what a registrar serves (resources, each with its consumers' query
ids) and what it holds elsewhere (client records, some of them dependencies of its own
resources). Only the registrar actor writes it, so it has no locks. Every change marks
the touched rows dirty; the persistence layer drains them as one transaction.

Dedup is by `==` on the request value, also for unhashable values: requests are bucketed
by a hash of a canonical form (mappings as item sets, sequences as tuples), and within a
bucket compared with `==`, so equal requests always meet in the same bucket.
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Iterable, Iterator, Mapping, Set
from typing import Any

from rr_actors._types import Query
from rr_actors.errors import UnknownQueryError

__all__ = ["Catalog", "Changes", "ClientRecord", "Resource", "ResourceState", "request_bucket"]

_UNHASHABLE = ("<unhashable>",)


_ATOMS = frozenset({int, float, str, bytes, bool, type(None)})


def _freeze(value: Any) -> Any:
    if type(value) in _ATOMS:
        return value
    if isinstance(value, Mapping):
        return frozenset((_freeze(k), _freeze(v)) for k, v in value.items())
    if isinstance(value, list | tuple):
        return tuple(_freeze(v) for v in value)
    if isinstance(value, Set):
        return frozenset(_freeze(v) for v in value)
    hash(value)  # raises TypeError for other unhashable values
    return value


def request_bucket(request: Any) -> Any:
    """Return a hashable key such that `a == b` implies equal keys (for the usual types).

    Values that cannot be canonicalised share one bucket and are compared by `==` alone.
    """
    try:
        return hash(_freeze(request))
    except TypeError:
        return _UNHASHABLE


def requests_equal(a: Any, b: Any) -> bool:
    """`a == b`, made total: a comparison that raises or is ambiguous means "different"."""
    try:
        return bool(a == b)
    except Exception:  # noqa: BLE001 - user __eq__ may raise anything; then they differ
        return False


class ResourceState(enum.Enum):
    """Life cycle of a served resource."""

    LOADING = "loading"
    LOADED = "loaded"
    UNLOADING = "unloading"


@dataclasses.dataclass
class Resource:
    """A resource a server of this registrar serves.

    Attributes:
        id: resource id (UUID4 string), stable for the resource's life.
        server: name of the server that loaded it.
        request: the request that describes it.
        response: what `load` returned (`None` while loading).
        state: life-cycle state.
        consumers: consumer query id -> origin registrar name, in arrival order.
    """

    id: str
    server: str
    request: Any
    response: Any = None
    state: ResourceState = ResourceState.LOADING
    consumers: dict[str, str] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass
class ClientRecord:
    """A query this registrar holds at some server (its own servers included).

    Attributes:
        query: the query, `origin_rr` being this registrar.
        parent: id of this registrar's resource that owns the query as a dependency,
            or `None` for a top-level call.
        loaded: `False` while the call is in flight.
    """

    query: Query
    parent: str | None = None
    loaded: bool = False


@dataclasses.dataclass
class Changes:
    """Rows changed since the last drain: id -> new row, or `None` when deleted."""

    resources: dict[str, Resource | None]
    clients: dict[str, ClientRecord | None]

    def __bool__(self) -> bool:
        return bool(self.resources or self.clients)


class _DirtySet(dict[str, None]):
    """An insertion-ordered set of row ids (so the store can keep the rows' order)."""

    def add(self, key: str) -> None:
        self[key] = None


class Catalog:
    """The bookkeeping of one registrar (thesis 4.3.2), without the locks."""

    def __init__(self, *, track_changes: bool = True) -> None:
        self.track_changes = track_changes
        self.resources: dict[str, Resource] = {}
        self.clients: dict[str, ClientRecord] = {}
        self._by_consumer: dict[str, str] = {}
        self._index: dict[str, dict[Any, list[str]]] = {}
        self._deps: dict[str, list[str]] = {}
        self._dirty_resources = _DirtySet()  # ordered: new rows drain in creation order
        self._dirty_clients = _DirtySet()

    # -- served resources -------------------------------------------------------------

    def find(self, server: str, request: Any) -> Resource | None:
        """Return the resource of `server` whose request `== request`, if any."""
        buckets = self._index.get(server, {})
        key = request_bucket(request)
        if key == _UNHASHABLE:  # it may equal a canonicalisable value (bytearray == bytes)
            candidates = [rid for bucket in buckets.values() for rid in bucket]
        else:
            candidates = [*buckets.get(key, ()), *buckets.get(_UNHASHABLE, ())]
        for rid in candidates:
            resource = self.resources[rid]
            if requests_equal(resource.request, request):
                return resource
        return None

    def begin_load(self, rid: str, server: str, request: Any) -> Resource:
        """Add a resource in the `LOADING` state."""
        resource = Resource(rid, server, request)
        self._insert(resource)
        return resource

    def finish_load(self, rid: str, response: Any) -> Resource:
        """Mark a loading resource `LOADED` with its response."""
        resource = self.resources[rid]
        resource.response = response
        resource.state = ResourceState.LOADED
        self._dirty_resources.add(rid)
        return resource

    def set_response(self, rid: str, response: Any) -> None:
        """Replace a resource's stored response."""
        self.resources[rid].response = response
        self._dirty_resources.add(rid)

    def begin_unload(self, rid: str) -> Resource:
        """Mark a resource `UNLOADING` (its last consumer left)."""
        resource = self.resources[rid]
        resource.state = ResourceState.UNLOADING
        self._dirty_resources.add(rid)
        return resource

    def remove_resource(self, rid: str) -> Resource:
        """Delete a resource that has no consumers any more."""
        resource = self.resources.pop(rid)
        assert not resource.consumers, "a resource with consumers cannot be removed"
        bucket = self._index[resource.server][request_bucket(resource.request)]
        bucket.remove(rid)
        if not bucket:
            del self._index[resource.server][request_bucket(resource.request)]
        self._dirty_resources.add(rid)
        return resource

    def add_consumer(self, rid: str, query_id: str, origin_rr: str) -> None:
        """Record one more consumer id of a resource."""
        if query_id in self._by_consumer:
            raise ValueError(f"query id {query_id} is already a consumer")
        self.resources[rid].consumers[query_id] = origin_rr
        self._by_consumer[query_id] = rid
        self._dirty_resources.add(rid)

    def release(self, query_id: str) -> Resource:
        """Remove one consumer id and return its resource.

        Raises:
            UnknownQueryError: the id is not a consumer of any resource here.
        """
        resource = self.resource_of(query_id)
        del resource.consumers[query_id]
        del self._by_consumer[query_id]
        self._dirty_resources.add(resource.id)
        return resource

    def resource_of(self, query_id: str) -> Resource:
        """Return the resource a consumer id belongs to.

        Raises:
            UnknownQueryError: the id is not a consumer of any resource here.
        """
        rid = self._by_consumer.get(query_id)
        if rid is None:
            raise UnknownQueryError(f"unknown or released query id {query_id!r}")
        return self.resources[rid]

    def has_consumer(self, query_id: str) -> bool:
        """Whether `query_id` is a consumer id of one of the resources served here."""
        return query_id in self._by_consumer

    def queries(self, resource: Resource, serving_rr: str) -> Iterator[Query]:
        """Yield one `Query` per consumer id of `resource`."""
        for qid, origin in resource.consumers.items():
            yield Query(
                qid, resource.server, serving_rr, origin, resource.request, resource.response
            )

    def server_queries(self, server: str, serving_rr: str) -> list[Query]:
        """Every consumer query of every loaded resource of `server`."""
        return [
            query
            for bucket in self._index.get(server, {}).values()
            for rid in bucket
            for query in self.queries(self.resources[rid], serving_rr)
        ]

    def resources_of(self, server: str) -> list[Resource]:
        """Every resource of `server`, oldest first."""
        return [r for r in self.resources.values() if r.server == server]

    # -- client records ---------------------------------------------------------------

    def add_client(self, record: ClientRecord) -> None:
        """Record an outbound query (in flight until `client_loaded`)."""
        qid = record.query.id
        if qid in self.clients:
            raise ValueError(f"query id {qid} is already a client record")
        self.clients[qid] = record
        if record.parent is not None:
            self._deps.setdefault(record.parent, []).append(qid)
        self._dirty_clients.add(qid)

    def client_loaded(self, query_id: str, response: Any) -> ClientRecord | None:
        """Mark an outbound query answered; `None` if the record is gone."""
        record = self.clients.get(query_id)
        if record is None:
            return None
        record.query = record.query.with_response(response)
        record.loaded = True
        self._dirty_clients.add(query_id)
        return record

    def remove_client(self, query_id: str) -> ClientRecord:
        """Delete an outbound query record.

        Raises:
            UnknownQueryError: no such record.
        """
        record = self.clients.pop(query_id, None)
        if record is None:
            raise UnknownQueryError(f"unknown or released query id {query_id!r}")
        if record.parent is not None:
            deps = self._deps[record.parent]
            deps.remove(query_id)
            if not deps:
                del self._deps[record.parent]
        self._dirty_clients.add(query_id)
        return record

    def dependencies(self, rid: str) -> list[ClientRecord]:
        """The client records owned by resource `rid`, oldest first."""
        return [self.clients[qid] for qid in self._deps.get(rid, ())]

    # -- persistence ------------------------------------------------------------------

    def drain_changes(self) -> Changes:
        """Return and forget the rows changed since the last drain.

        Without `track_changes` (a catalog nobody persists) this is always empty.
        """
        if not self.track_changes:
            self._dirty_resources.clear()
            self._dirty_clients.clear()
            return Changes({}, {})
        changes = Changes(
            {rid: self.resources.get(rid) for rid in self._dirty_resources},
            {qid: self.clients.get(qid) for qid in self._dirty_clients},
        )
        self._dirty_resources.clear()
        self._dirty_clients.clear()
        return changes

    @classmethod
    def restore(cls, resources: Iterable[Resource], clients: Iterable[ClientRecord]) -> Catalog:
        """Build a catalog from stored rows (nothing is marked dirty)."""
        catalog = cls(track_changes=True)
        for resource in resources:
            catalog._insert(resource)
            for qid in resource.consumers:
                catalog._by_consumer[qid] = resource.id
        for record in clients:
            catalog.add_client(record)
        catalog.drain_changes()
        return catalog

    def check_invariants(self) -> None:
        """Raise `AssertionError` if the indexes disagree with the rows (for tests)."""
        by_consumer = {q: r.id for r in self.resources.values() for q in r.consumers}
        assert by_consumer == self._by_consumer, "consumer index out of sync"
        for resource in self.resources.values():
            if resource.state is ResourceState.LOADED:
                equal = [
                    r
                    for r in self.resources_of(resource.server)
                    if r.id != resource.id and requests_equal(r.request, resource.request)
                ]
                assert not equal, f"resource {resource.id} is loaded twice"
        deps: dict[str, list[str]] = {}
        for qid, record in self.clients.items():
            if record.parent is not None:
                assert record.parent in self.resources, f"dependency {qid} has no owner"
                deps.setdefault(record.parent, []).append(qid)
        assert deps == self._deps, "dependency index out of sync"

    def _insert(self, resource: Resource) -> None:
        self.resources[resource.id] = resource
        key = request_bucket(resource.request)
        self._index.setdefault(resource.server, {}).setdefault(key, []).append(resource.id)
        self._dirty_resources.add(resource.id)
