"""The resource catalog: what a registrar serves and holds, as data; no threads, no locks.

What a registrar serves (resources, with their consumers' query ids) and holds elsewhere
(client records, some of them dependencies of its own resources); only the registrar
actor writes it:

```
 the registrar actor
   │ load: has_consumer ─► lookup ─► begin_load ─► finish_load     rows: resources,
   │ hit:  has_consumer ─► lookup ─► add_consumer                  clients (records.py)
   │ release ─► begin_unload ─► remove_resource; client records    indexes: query id ->
   ▼                                                               resource, resource ->
 Catalog ──► RequestIndex (below): which resources of a            its dependencies
   │         server may serve a request, by digest
   ├──► UnreadRows: a restored catalog's backlog, the rows still in the backup
   │    (the store's reader, _store/restore.py), read in when a lookup needs them
   │    (by digest, consumer id, server, origin) or by the registrar's sweep
   └──► each change marks its row ──► drain_changes ──► the store (_store/saver.py)
        writes the rows as they are then, one transaction
```

Requests are matched by `==` through digests (`digest.py`): the index gives the
candidates, the catalog compares the plain ones itself. A resource reported `FATAL` is
never matched again (rule 1, docs/explanation/semantics.md). It opens no file, but a
restored catalog reads rows through its `UnreadRows` and decodes values on first use.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator, Sequence, ValuesView
from typing import Any

from rr_actors._catalog.digest import (
    NO_DIGEST,
    UNHASHABLE,
    candidates_without_digest,
    identity_equality,
    request_digest,
    requests_equal,
    runtime_key,
)
from rr_actors._catalog.records import (
    Changes,
    ClientRecord,
    Listing,
    Resource,
    ResourceState,
    UnreadRows,
)
from rr_actors._types import Query
from rr_actors.errors import UnknownQueryError

_UNKNOWN: Any = object()  # a `digest` argument not given (`None`: the request has none)


class _DirtySet(dict[str, None]):
    """An insertion-ordered set of row ids (so the store can keep the rows' order)."""

    add: Any = dict.setdefault  # (in C: on every change's path)


class _NoDirt(_DirtySet):
    """The changed rows of a catalog nobody persists: none are kept."""

    add: Any = dict.get


class Catalog:
    """The bookkeeping of one registrar (thesis 4.3.2), without the locks; lookups see the
    resources still in the backup too (they read them in). `resources`: those in memory
    (read-back ones in stored order only once an ordered listing asks)."""

    shares: Callable[[Any, Any, bool, bool], bool] | None = None
    """A copy of the dedup step of plain requests, or `None` for this module's own
    (`RegistrarConfig.steps.shares`, set by the registrar that opens the catalog)."""

    def __init__(self, *, track_changes: bool = True) -> None:
        self.track_changes = track_changes
        self.resources: dict[str, Resource] = {}
        self._clients: dict[str, ClientRecord] = {}  # query id -> its record, oldest first
        self._index = RequestIndex()
        self._by_consumer: dict[str, str] = {}  # query id -> its resource's id (in memory)
        self._deps: dict[str, list[str]] = {}  # resource id -> the query ids it owns
        self._unread: UnreadRows | None = None  # the backlog; None once it is all read in
        self._unsorted = False  # resources read back since `resources` was last ordered
        # the ids of the rows changed since the last drain, in the order they first changed
        self._dirty_resources = _DirtySet() if track_changes else _NoDirt()
        self._dirty_clients = _DirtySet() if track_changes else _NoDirt()
        # `Changes.consumers`; the resources whose every consumer is compared (`mark_changed`)
        self._touched: dict[str, dict[str, None]] = {}
        self._whole: set[str] = set()

    # -- matching ---------------------------------------------------------------------

    def find(self, server: str, request: Any) -> Resource | None:
        """The resource of `server` whose request `== request`, if any (runs user code: the
        registrar uses `lookup`)."""
        key = None if request_digest(request) is not None else runtime_key(request)
        found, undecided = self.lookup(server, request, key)
        if found is not None:
            return found
        for resource in undecided:
            if requests_equal(resource.request, request):
                return resource
        return None

    def lookup(
        self, server: str, request: Any, key: Any = None, *, digest: Any = _UNKNOWN
    ) -> tuple[Resource | None, list[Resource]]:
        """Look `request` up among the resources of `server`, running no user code.

        Plain values are compared here; `key`: a request's `runtime_key` when it has no
        digest (the caller computes it). A `failed` resource is never returned.

        Returns:
            `(found, undecided)`: the resource whose plain request `== request`, or
            `None`; then the resources only a user `==` can judge (for the caller).
        """
        if digest is _UNKNOWN:
            digest = request_digest(request)
        found, undecided = self._match(server, request, digest, key)
        if found is None and self._unread is not None:
            if digest is not None:
                self._read_in(self._unread.by_request(server, digest))
            elif not identity_equality(request):  # may equal any value: read them all
                self._read_in(self._unread.of_server(server))
            else:
                return None, undecided  # equal only to itself: never to a value read back
            found, undecided = self._match(server, request, digest, key)
        return found, undecided

    def _match(
        self, server: str, request: Any, digest: int | None, key: Any
    ) -> tuple[Resource | None, list[Resource]]:
        resources = self.resources
        index = self._index
        if digest is not None:
            shares = self.shares  # (a copy passed in: `RegistrarConfig.steps`)
            for rid in index.with_digest(server, digest):
                resource = resources[rid]
                if shares is not None:
                    loading = resource.state is ResourceState.LOADING
                    if shares(resource.request, request, loading, resource.failed):
                        return resource, []
                    continue
                if resource.failed:  # reported FATAL: never matched again
                    continue
                if requests_equal(resource.request, request):  # both plain: no user code
                    return resource, []
        undecided = index.undecided(server, request, digest, key)
        return None, [resources[rid] for rid in undecided if not resources[rid].failed]

    # -- a resource's life ------------------------------------------------------------

    def begin_load(self, rid: str, server: str, request: Any, *, key: Any = None) -> Resource:
        """Add a resource in the `LOADING` state (`key`: as for `lookup`)."""
        resource = Resource(rid, server, request)
        self.resources[rid] = resource
        self._index.add(resource, key)
        self._dirty_resources.add(rid)
        return resource

    def finish_load(self, rid: str, response: Any) -> Resource:
        """Mark a loading resource `LOADED` with its response."""
        resource = self.resources[rid]
        resource.response = response
        resource.response_version += 1
        resource.state = ResourceState.LOADED
        self._dirty_resources.add(rid)
        return resource

    def set_response(self, rid: str, response: Any) -> None:
        """Replace a resource's stored response."""
        resource = self.resources[rid]
        resource.response = response
        resource.response_version += 1
        self._dirty_resources.add(rid)

    def set_texts(
        self,
        rid: str,
        *,
        request_text: str | None = None,
        response_text: str | None = None,
        label: str | None = None,
    ) -> None:
        """Set a resource's display texts or label (those given; `None`: keep it)."""
        resource = self.resources[rid]
        if request_text is not None:
            resource.request_text = request_text
        if response_text is not None:
            resource.response_text = response_text
        if label is not None:
            resource.label = label
        self._dirty_resources.add(rid)

    def mark_failed(self, rid: str) -> Resource:
        """Mark a resource dead (reported `FATAL`): never matched again; it keeps its
        consumers until each releases it."""
        resource = self.resources[rid]
        if not resource.failed:
            resource.failed = True
            self._dirty_resources.add(rid)
        return resource

    def begin_unload(self, rid: str) -> Resource:
        """Mark a resource `UNLOADING` (its last consumer left)."""
        resource = self.resources[rid]
        resource.state = ResourceState.UNLOADING
        self._dirty_resources.add(rid)
        return resource

    def cancel_unload(self, rid: str) -> None:
        """Mark an `UNLOADING` resource `LOADED` again (its unload was never written)."""
        self.resources[rid].state = ResourceState.LOADED
        self._dirty_resources.add(rid)

    def remove_resource(self, rid: str) -> Resource:
        """Delete a resource that has no consumers any more."""
        resource = self.resources.pop(rid)
        assert not resource.consumers, "a resource with consumers cannot be removed"
        self._index.remove(resource)
        self._dirty_resources.add(rid)
        return resource

    # -- consumers --------------------------------------------------------------------

    def add_consumer(self, rid: str, query_id: str, origin_rr: str) -> None:
        """Record one more consumer id of a resource, held by registrar `origin_rr`."""
        if self.has_consumer(query_id):
            raise ValueError(f"query id {query_id} is already a consumer")
        self.resources[rid].consumers[query_id] = origin_rr
        self._by_consumer[query_id] = rid
        self._dirty_resources.add(rid)
        if self.track_changes:
            self._touch(rid, query_id)

    def release(self, query_id: str) -> Resource:
        """Remove one consumer id and return its resource.

        Raises:
            UnknownQueryError: the id is not a consumer of any resource here.
        """
        resource = self.resource_of(query_id)
        del resource.consumers[query_id]
        del self._by_consumer[query_id]
        self._dirty_resources.add(resource.id)
        if self.track_changes:
            self._touch(resource.id, query_id)
        return resource

    def _touch(self, rid: str, query_id: str) -> None:
        ids = self._touched.get(rid)
        if ids is None:
            self._touched[rid] = {query_id: None}
        else:
            ids.pop(query_id, None)  # (to the end: the order they last changed)
            ids[query_id] = None

    def resource_of(self, query_id: str) -> Resource:
        """The resource a consumer id belongs to (`UnknownQueryError`)."""
        rid = self._by_consumer.get(query_id)
        if rid is None:
            rid = self._read_consumer(query_id)
            if rid is None:
                raise UnknownQueryError(f"unknown or released query id {query_id!r}")
        return self.resources[rid]

    def has_consumer(self, query_id: str) -> bool:
        """Whether `query_id` is a consumer id of one of the resources served here."""
        if query_id in self._by_consumer:
            return True
        return self._unread is not None and self._read_consumer(query_id) is not None

    def queries(self, resource: Resource, serving_rr: str) -> Iterator[Query]:
        """Yield one `Query` per consumer id of `resource`."""
        for qid, origin in resource.consumers.items():
            yield Query(
                qid, resource.server, serving_rr, origin, resource.request, resource.response
            )

    def server_queries(self, server: str, serving_rr: str) -> list[Query]:
        """Every consumer query of every loaded resource of `server`."""
        if self._unread is not None:
            self._read_in(self._unread.of_server(server))
        resources = self.resources
        return [
            query
            for rid in self._index.ids_of(server)  # (those with a digest first)
            for query in self.queries(resources[rid], serving_rr)
        ]

    def consumers_from(self, origin_rr: str) -> list[str]:
        """The consumer ids, of any resource here, that registrar `origin_rr` holds."""
        if self._unread is not None:
            self._read_in(self._unread.with_origin(origin_rr))
        return self._consumers_in_memory(origin_rr)

    def consumer_ids_from(self, origin_rr: str) -> set[str]:
        """The consumer ids here that `origin_rr` holds (reading no resource from the backup)."""
        ids = set(self._consumers_in_memory(origin_rr))
        if self._unread is not None:
            ids.update(self._unread.consumer_ids_from(origin_rr))
        return ids

    def _consumers_in_memory(self, origin_rr: str) -> list[str]:
        return [
            query_id
            for resource in self.resources.values()
            for query_id, origin in resource.consumers.items()
            if origin == origin_rr
        ]

    def consumer_origins(self) -> set[str]:
        """The registrars that hold consumer ids of the resources in memory (`sweep`
        gives those of the resources still in the backup)."""
        return {o for resource in self.resources.values() for o in resource.consumers.values()}

    # -- listings ---------------------------------------------------------------------

    def resources_of(self, server: str) -> list[Resource]:
        """Every resource of `server`, oldest first."""
        if self._unread is not None:
            self._read_in(self._unread.of_server(server))
        return [r for r in self._in_order().values() if r.server == server]

    def unheld(self) -> list[Resource]:
        """Resources in memory loaded that no consumer holds, oldest first (a crash before
        their unload began; `sweep` finds those still in the backup)."""
        return [
            resource
            for resource in self._in_order().values()
            if resource.state is ResourceState.LOADED and not resource.consumers
        ]

    def sweep(self, after: int) -> tuple[list[Resource], set[str], int | None]:
        """Look at the next slice of the resources still in the backup (row keys above
        `after`): those loaded and unheld (read in now), the registrars holding consumer
        ids in it, and the row key to sweep on from (`None`: nothing is left)."""
        if self._unread is None:
            return [], set(), None
        unheld, origins, last = self._unread.sweep(after)
        self._read_in(unheld)
        return unheld, origins, last

    def read_all(self) -> dict[str, Resource]:
        """Every resource (reading those still in the backup), by id, oldest first."""
        if self._unread is not None:
            self._read_in(self._unread.every())
        return self._in_order()

    def rows(self, limit: int) -> tuple[list[tuple[str, ...]], list[tuple[str, ...]]] | None:
        """Every resource and consumer id as a row of strings, reading none from the backup:
        `(id, server, state, digest or "", "failed" or "")` per resource, oldest first, and
        `(query id, resource id, consumer registrar)` per consumer id, by resource, in
        arrival order; `None` if either kind has more than `limit` rows."""
        resources: list[tuple[Any, ...]] = []  # (each row after its row key: `Listing`)
        consumers: list[tuple[Any, ...]] = []
        for resource in self._in_order().values():
            order = _stored_order(resource)
            digest = resource.digest
            plain = digest is not None and digest != NO_DIGEST
            rid = resource.id
            failed = "failed" * resource.failed
            resources.append(
                (order, rid, resource.server, resource.state.value, str(digest) * plain, failed)
            )
            consumers.extend((order, qid, rid, o) for qid, o in resource.consumers.items())
            if len(resources) > limit or len(consumers) > limit:
                return None
        if self._unread is not None:  # merged by row key, arrival order kept (stable)
            unread: Listing | None = self._unread.listing(limit)
            if unread is None:
                return None
            if resources:  # (none in memory, a restore's usual: the backup's order as is)
                resources = sorted([*resources, *unread[0]], key=_first)
                consumers = sorted([*consumers, *unread[1]], key=_first)
            else:
                resources, consumers = unread
            if len(resources) > limit or len(consumers) > limit:
                return None
        return [row[1:] for row in resources], [row[1:] for row in consumers]

    def counts(self) -> tuple[int, int]:
        """How many resources there are, and how many consumer ids (reading no row)."""
        resources = self.resources.values()
        held = sum(len(resource.consumers) for resource in resources)
        if self._unread is None:
            return len(resources), held
        unread = self._unread.counts()
        return len(resources) + unread[0], held + unread[1]

    def _in_order(self) -> dict[str, Resource]:
        """`resources`, oldest first (sorted in place only when asked)."""
        resources = self.resources
        if self._unsorted:
            ordered = sorted(resources.values(), key=_stored_order)
            resources.clear()
            resources.update((resource.id, resource) for resource in ordered)
            self._unsorted = False
        return resources

    # -- the backlog: a restored catalog's rows still in the backup -------------------

    def _read_consumer(self, query_id: str) -> str | None:
        """Read in the resource `query_id` is a consumer of; its id, or `None`."""
        unread = self._unread
        if unread is None:
            return None
        resource = unread.by_consumer(query_id)
        if resource is None:
            return None
        self._read_in([resource])
        return resource.id

    def _read_in(self, resources: list[Resource]) -> None:
        by_consumer = self._by_consumer
        for resource in resources:
            rid = resource.id
            for query_id in resource.consumers:
                by_consumer[query_id] = rid
            self.resources[rid] = resource
            self._index.add(resource)
            self._unsorted = True
        if self._unread is not None and not self._unread.remaining:
            self._unread = None  # everything is in memory: stop asking

    # -- client records ---------------------------------------------------------------

    def client(self, query_id: str) -> ClientRecord | None:
        """The client record of `query_id` (an outbound query), `None` if there is none."""
        return self._clients.get(query_id)

    def client_records(self) -> ValuesView[ClientRecord]:
        """Every client record, oldest first (a live view: copy it to change the catalog)."""
        return self._clients.values()

    def providers(self) -> set[str]:
        """The registrars that serve a client record of this catalog."""
        return {record.query.serving_rr for record in self._clients.values()}

    def add_client(self, record: ClientRecord) -> None:
        """Record an outbound query (in flight until `client_loaded`)."""
        qid = record.query.id
        if qid in self._clients:
            raise ValueError(f"query id {qid} is already a client record")
        self._clients[qid] = record
        if record.parent is not None:
            self._deps.setdefault(record.parent, []).append(qid)
        self._dirty_clients.add(qid)

    def client_loaded(self, query_id: str, response: Any) -> ClientRecord | None:
        """Mark an outbound query answered; `None` if the record is gone."""
        record = self._clients.get(query_id)
        if record is None:
            return None
        record.query = record.query.with_response(response)
        record.loaded = True
        record.response_version += 1
        self._dirty_clients.add(query_id)
        return record

    def set_client_text(self, query_id: str, request_text: str) -> None:
        """Set a client record's request display text."""
        self._clients[query_id].request_text = request_text
        self._dirty_clients.add(query_id)

    def remove_client(self, query_id: str) -> ClientRecord:
        """Delete an outbound query record (`UnknownQueryError`)."""
        record = self._clients.pop(query_id, None)
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
        """The client records owned by resource `rid`, oldest first (rule 5: when it is
        unloaded, they are released)."""
        return [self._clients[qid] for qid in self._deps.get(rid, ())]

    # -- persistence ------------------------------------------------------------------

    def mark_changed(self, rid: str) -> None:
        """Have the next drain report resource `rid` as it is now, every consumer compared
        (a change whose write was held back)."""
        self._dirty_resources.add(rid)
        if self.track_changes:
            self._whole.add(rid)

    def changed(self) -> bool:
        """Whether a row changed since the last drain (never without `track_changes`)."""
        return bool(self._dirty_resources or self._dirty_clients)

    def drain_changes(self) -> Changes:
        """Return and forget the rows changed since the last drain, in the order they first
        changed (always empty without `track_changes`)."""
        resources, clients, dirty = self.resources, self._clients, self._dirty_resources
        touched, whole = self._touched, self._whole
        changes = Changes(  # (no comprehension run for nothing: most turns change one kind)
            {rid: resources.get(rid) for rid in dirty} if dirty else {},
            {qid: clients.get(qid) for qid in self._dirty_clients} if self._dirty_clients else {},
            {rid: touched.get(rid) or {} for rid in dirty if rid not in whole} if dirty else {},
        )
        dirty.clear()
        self._dirty_clients.clear()
        self._touched = {}
        if whole:
            whole.clear()
        return changes

    @classmethod
    def restore(
        cls,
        resources: Iterable[Resource],
        clients: Iterable[ClientRecord],
        unread: UnreadRows | None = None,
    ) -> Catalog:
        """Build a catalog from stored rows, in their stored order (nothing is marked
        changed); `unread`: the stored resources not given, read when needed."""
        catalog = cls(track_changes=True)
        if unread is not None and unread.remaining:
            catalog._unread = unread
        catalog.resources = {resource.id: resource for resource in resources}
        catalog._index.restore(catalog.resources.values())
        catalog._by_consumer = {
            query_id: resource.id
            for resource in catalog.resources.values()
            for query_id in resource.consumers
        }
        catalog._clients = {record.query.id: record for record in clients}
        deps = catalog._deps
        for qid, record in catalog._clients.items():
            if record.parent is not None:
                deps.setdefault(record.parent, []).append(qid)
        return catalog

    def check_invariants(self) -> None:
        """Raise `AssertionError` if the indexes disagree with the rows (for tests)."""
        resources = self.read_all()
        by_consumer = {q: r.id for r in resources.values() for q in r.consumers}
        assert by_consumer == self._by_consumer, "consumer index out of sync"
        for resource in resources.values():
            if resource.state is ResourceState.LOADED and not resource.failed:
                equal = [
                    r
                    for r in resources.values()
                    if r.server == resource.server
                    and r.id != resource.id
                    and not r.failed
                    and requests_equal(r.request, resource.request)
                ]
                assert not equal, f"resource {resource.id} is loaded twice"
        deps: dict[str, list[str]] = {}
        for qid, record in self._clients.items():
            if record.parent is not None:
                assert record.parent in resources, f"dependency {qid} has no owner"
                deps.setdefault(record.parent, []).append(qid)
        assert deps == self._deps, "dependency index out of sync"


class RequestIndex:
    """The resource ids of each server, by request digest or by in-process key (it writes
    one field of a resource: its `digest`, once)."""

    def __init__(self) -> None:
        self._digested: dict[str, dict[int, list[str]]] = {}
        self._others: dict[str, dict[Any, list[str]]] = {}
        self._other_keys: dict[str, Any] = {}  # resource id -> its key in `_others`

    def add(self, resource: Resource, key: Any = None) -> None:
        """Index a resource new here (`key`: see `Catalog.begin_load`) or read back (no key:
        without a digest it goes with the unhashable ones, running no code of its class)."""
        digest = resource.digest
        if digest is None:
            digest = request_digest(resource.request)
            resource.digest = NO_DIGEST if digest is None else digest
            if key is None and digest is None:
                key = runtime_key(resource.request)
        if digest is not None and digest != NO_DIGEST:
            index = self._digested.setdefault(resource.server, {})
            index.setdefault(digest, []).append(resource.id)
        else:
            key = self._other_keys[resource.id] = UNHASHABLE if key is None else key
            self._others.setdefault(resource.server, {}).setdefault(key, []).append(resource.id)

    def restore(self, resources: Iterable[Resource]) -> None:
        """Index stored resources (by a known digest without decoding their request)."""
        index = self._digested
        for resource in resources:
            digest = resource.digest
            if digest is not None and digest != NO_DIGEST:
                server = index.get(resource.server)
                if server is None:
                    server = index[resource.server] = {}
                bucket = server.get(digest)
                if bucket is None:
                    server[digest] = [resource.id]
                else:
                    bucket.append(resource.id)
            else:
                self.add(resource)

    def remove(self, resource: Resource) -> None:
        key = self._other_keys.pop(resource.id, None)
        buckets: dict[Any, list[str]]
        if key is None:
            key, buckets = resource.digest, self._digested[resource.server]
        else:
            buckets = self._others[resource.server]
        bucket = buckets[key]
        bucket.remove(resource.id)
        if not bucket:
            del buckets[key]

    def with_digest(self, server: str, digest: int) -> Sequence[str]:
        digested = self._digested.get(server)
        return digested.get(digest, ()) if digested else ()

    def undecided(self, server: str, request: Any, digest: int | None, key: Any) -> list[str]:
        """The ids of `server`'s resources only a user `==` can compare with `request`."""
        others = self._others.get(server)
        if digest is not None:
            # (a plain request's `runtime_key` is a built-in `hash()`: no user code)
            return candidates_without_digest(others, runtime_key(request)) if others else []
        undecided = candidates_without_digest(others, key) if others else []
        digested = self._digested.get(server)
        if digested and not identity_equality(request):
            # A custom `__eq__` may equal a plain value: compare with every one.
            undecided += [rid for bucket in digested.values() for rid in bucket]
        return undecided

    def ids_of(self, server: str) -> Iterator[str]:
        for index in (self._digested, self._others):
            for bucket in index.get(server, {}).values():
                yield from bucket


def _stored_order(resource: Resource) -> float:
    order: float = resource.__dict__.get("_order", math.inf)
    return order


def _first(item: tuple[Any, ...]) -> Any:
    return item[0]
