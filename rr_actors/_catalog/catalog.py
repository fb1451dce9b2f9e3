"""The resource catalog: data and its indexes, no threads; stored rows read when needed.

The catalog records what a registrar serves (resources, each with its consumers' query
ids) and what it holds elsewhere (client records, some of them dependencies of its own
resources). Only the registrar actor writes it, so it has no locks. `Catalog` is the one
name the registrar and the store use; it wires its roles, each in its own module and
owning its own state, and sequences the steps that concern more than one:

```
 Catalog     wires the roles (bottom first); runs the steps     (the roles only)
     │       that span them: a consumer added is its row's
     │       (Served) and its index's (ConsumerIds)
 backlog     rows still in the backup, read in when a lookup    the backup's reader
     │       needs them: ConsumerIds.take, Served.take          (`UnreadRows`), or None
 invariants  every index against the rows (for tests)           (none)
     │
 served      the resources in memory: their life's steps,       resources by id
     │       matching, listings
 consumers   query id -> resource id                            that index
 clients     the client records, each resource's dependencies   records, dependencies
     │
 index       request digest (or in-process key) -> ids          buckets per server
 changes     the rows changed since the last drain              changed row ids
     │
 records, digest, texts: the rows (`Resource`, `ClientRecord`, `Changes`), request
                         digests, display texts

 a change ──► ChangeLog ──► Catalog.drain_changes ──► the store (_store/saver.py) writes
              the rows as they are then, one transaction
```
Each role changes another's state only by calling it, and calls only the roles below it
(a layers contract in pyproject.toml checks it). Requests are matched by `==` through
digests (`rr_actors._catalog.digest`).

A resource its provider reported `FATAL` is marked `failed` (`mark_failed`) and is never
matched again (rule 1; why: `served`).

It opens no file itself, but it is not free of I/O: a restored catalog asks the
`UnreadRows` it was given (the store's reader of the backup) for the resources a lookup
needs and has not read yet (`backlog.Backlog`), and a restored resource decodes its
request and response from their stored bytes on first use (`records.Resource`).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import Any

from rr_actors._catalog import invariants
from rr_actors._catalog.backlog import Backlog
from rr_actors._catalog.changes import ChangeLog
from rr_actors._catalog.clients import ClientRecords
from rr_actors._catalog.consumers import ConsumerIds
from rr_actors._catalog.digest import (
    identity_equality,
    request_digest,
    requests_equal,
    runtime_key,
)
from rr_actors._catalog.records import Changes, ClientRecord, Resource, UnreadRows
from rr_actors._catalog.served import Served
from rr_actors._types import Query
from rr_actors.errors import UnknownQueryError

__all__ = ["Catalog"]


_UNKNOWN: Any = object()
"""A `digest` argument not given (`None` means "the request has none")."""


class Catalog:
    """The bookkeeping of one registrar (thesis 4.3.2), without the locks.

    A restored catalog may hold only part of its resources in memory (`resources`); the
    others are read from the backup (`UnreadRows`) when a lookup first needs them, so a
    restore does not cost a read of every row. Methods that look resources up (`find`,
    `resource_of`, `has_consumer`, `resources_of`, ...) see both.

    Attributes:
        track_changes: whether changed rows are kept for the store (`drain_changes`).
    """

    def __init__(self, *, track_changes: bool = True) -> None:
        self.track_changes = track_changes
        self._changes = ChangeLog(track_changes=track_changes)
        self._served = Served(self._changes)
        self._consumers = ConsumerIds()
        self._clients = ClientRecords(self._changes)
        self._backlog = Backlog(self._served, self._consumers)

    @property
    def resources(self) -> dict[str, Resource]:
        """The resources in memory, by id (a restored catalog's others are in the backup)."""
        return self._served.resources

    @property
    def clients(self) -> dict[str, ClientRecord]:
        """The client records, by query id, oldest first."""
        return self._clients.records

    # The ids of the rows changed since the last drain (a test checks none are kept).
    @property
    def _dirty_resources(self) -> dict[str, None]:
        return self._changes.resources

    @property
    def _dirty_clients(self) -> dict[str, None]:
        return self._changes.clients

    # -- served resources -------------------------------------------------------------

    def find(self, server: str, request: Any) -> Resource | None:
        """Return the resource of `server` whose request `== request`, if any.

        Runs `==` (and the request's `hash()`) itself, user code included: the registrar
        uses `lookup` instead, and runs what user code remains off its actor thread.
        """
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
        """Look `request` up among the resources of `server` as far as plain values go.

        Runs no code of the request's classes, nor of the stored requests' classes:
        plain values (those with a digest, `request_digest`) are compared here; the
        resources only a `==` that runs such code can judge are returned, for the
        caller to compare (the registrar does it off its actor thread, with a bound).
        Restored requests it needs are read from the backup first. A resource marked
        `failed` is never returned.

        Args:
            server: the server's name.
            request: the request to find.
            key: for a request without a digest, its `runtime_key` (the caller computes
                it: it runs the request's `__hash__`); ignored for a plain request.
            digest: `request_digest(request)`, if the caller has it already.

        Returns:
            `(found, undecided)`: the resource whose plain request `== request`, or
            `None`; and when none was found, the resources whose requests may still
            `== request` (in the order `find` compares them), else `[]`.
        """
        if digest is _UNKNOWN:
            digest = request_digest(request)
        found, undecided = self._served.match(server, request, digest, key)
        if found is None and self._backlog.remaining():
            if digest is not None:
                self._backlog.read_request(server, digest)
            elif not identity_equality(request):  # may equal any value: read them all
                self._backlog.read_server(server)
            else:
                return None, undecided  # equal only to itself: never to a value read back
            found, undecided = self._served.match(server, request, digest, key)
        return found, undecided

    def begin_load(self, rid: str, server: str, request: Any, *, key: Any = None) -> Resource:
        """Add a resource in the `LOADING` state (`Served.begin_load`)."""
        return self._served.begin_load(rid, server, request, key)

    def finish_load(self, rid: str, response: Any) -> Resource:
        """Mark a loading resource `LOADED` with its response."""
        return self._served.finish_load(rid, response)

    def set_response(self, rid: str, response: Any) -> None:
        """Replace a resource's stored response."""
        self._served.set_response(rid, response)

    def set_texts(
        self,
        rid: str,
        *,
        request_text: str | None = None,
        response_text: str | None = None,
        label: str | None = None,
    ) -> None:
        """Set a resource's display texts or label (those given; `None`: keep it)."""
        self._served.set_texts(rid, request_text, response_text, label)

    def mark_failed(self, rid: str) -> Resource:
        """Mark a resource dead: its provider reported it `FATAL` (`Served.mark_failed`)."""
        return self._served.mark_failed(rid)

    def begin_unload(self, rid: str) -> Resource:
        """Mark a resource `UNLOADING` (its last consumer left)."""
        return self._served.begin_unload(rid)

    def remove_resource(self, rid: str) -> Resource:
        """Delete a resource that has no consumers any more."""
        return self._served.remove(rid)

    def add_consumer(self, rid: str, query_id: str, origin_rr: str) -> None:
        """Record one more consumer id of a resource, held by registrar `origin_rr`."""
        if self.has_consumer(query_id):
            raise ValueError(f"query id {query_id} is already a consumer")
        self._served.add_consumer(rid, query_id, origin_rr)
        self._consumers.add(query_id, rid)

    def release(self, query_id: str) -> Resource:
        """Remove one consumer id and return its resource.

        Raises:
            UnknownQueryError: the id is not a consumer of any resource here.
        """
        resource = self.resource_of(query_id)
        self._served.drop_consumer(resource, query_id)
        self._consumers.remove(query_id)
        return resource

    def resource_of(self, query_id: str) -> Resource:
        """Return the resource a consumer id belongs to.

        Raises:
            UnknownQueryError: the id is not a consumer of any resource here.
        """
        rid = self._consumers.rid_of(query_id)
        if rid is None:
            rid = self._backlog.read_consumer(query_id)
        if rid is None:
            raise UnknownQueryError(f"unknown or released query id {query_id!r}")
        return self._served.resources[rid]

    def has_consumer(self, query_id: str) -> bool:
        """Whether `query_id` is a consumer id of one of the resources served here."""
        return query_id in self._consumers or self._backlog.read_consumer(query_id) is not None

    def queries(self, resource: Resource, serving_rr: str) -> Iterator[Query]:
        """Yield one `Query` per consumer id of `resource`."""
        for qid, origin in resource.consumers.items():
            yield Query(
                qid, resource.server, serving_rr, origin, resource.request, resource.response
            )

    def server_queries(self, server: str, serving_rr: str) -> list[Query]:
        """Every consumer query of every loaded resource of `server`."""
        self._backlog.read_server(server)
        return [
            query
            for resource in self._served.indexed(server)
            for query in self.queries(resource, serving_rr)
        ]

    def resources_of(self, server: str) -> list[Resource]:
        """Every resource of `server`, oldest first."""
        self._backlog.read_server(server)
        return self._served.of_server(server)

    def consumers_from(self, origin_rr: str) -> list[str]:
        """The consumer ids, of any resource here, that registrar `origin_rr` holds."""
        self._backlog.read_origin(origin_rr)
        return self._served.consumers_from(origin_rr)

    def consumer_origins(self) -> set[str]:
        """The registrars that hold consumer ids of the resources in memory (`sweep`
        gives those of the resources still in the backup)."""
        return self._served.consumer_origins()

    def consumer_ids_from(self, origin_rr: str) -> set[str]:
        """The consumer ids here that `origin_rr` holds (reading no resource from the backup)."""
        ids = set(self._served.consumers_from(origin_rr))
        ids.update(self._backlog.consumer_ids_from(origin_rr))
        return ids

    def unheld(self) -> list[Resource]:
        """Resources in memory loaded that no consumer holds, oldest first (`Served.unheld`;
        `sweep` finds those still in the backup)."""
        return self._served.unheld()

    def sweep(self, after: int) -> tuple[list[Resource], set[str], int | None]:
        """Look at the next slice of the resources still in the backup (`Backlog.sweep`)."""
        return self._backlog.sweep(after)

    def read_all(self) -> dict[str, Resource]:
        """Every resource (reading those still in the backup), by id, oldest first."""
        self._backlog.read_all()
        return self._served.in_order()

    def rows(self, limit: int) -> tuple[list[tuple[str, ...]], list[tuple[str, ...]]] | None:
        """Every resource and consumer id as a row of strings, reading none from the backup.

        Args:
            limit: the most rows of either kind to return.

        Returns:
            `(resources, consumers)`, oldest first (the rows: `Served.listing`); `None`
            if either kind has more than `limit` rows.
        """
        memory = self._served.listing(limit)
        listing = None if memory is None else self._backlog.merged(memory, limit)
        if listing is None:
            return None
        return [row for _, row in listing[0]], [row for _, row in listing[1]]

    def counts(self) -> tuple[int, int]:
        """How many resources there are, and how many consumer ids (reading no row)."""
        memory, unread = self._served.counts(), self._backlog.counts()
        return memory[0] + unread[0], memory[1] + unread[1]

    # -- client records ---------------------------------------------------------------

    def add_client(self, record: ClientRecord) -> None:
        """Record an outbound query (in flight until `client_loaded`)."""
        self._clients.add(record)

    def client_loaded(self, query_id: str, response: Any) -> ClientRecord | None:
        """Mark an outbound query answered; `None` if the record is gone."""
        return self._clients.loaded(query_id, response)

    def set_client_text(self, query_id: str, request_text: str) -> None:
        """Set a client record's request display text."""
        self._clients.set_text(query_id, request_text)

    def remove_client(self, query_id: str) -> ClientRecord:
        """Delete an outbound query record.

        Raises:
            UnknownQueryError: no such record.
        """
        return self._clients.remove(query_id)

    def dependencies(self, rid: str) -> list[ClientRecord]:
        """The client records owned by resource `rid`, oldest first."""
        return self._clients.dependencies(rid)

    # -- persistence ------------------------------------------------------------------

    def mark_changed(self, rid: str) -> None:
        """Have the next drain report resource `rid` as it is now (its row, or its removal).

        For a change whose write was held back (an in-doubt resource settled while its
        manager's `setup` runs): the write of what it is by then is owed.
        """
        self._changes.resource_changed(rid)

    def drain_changes(self) -> Changes:
        """Return and forget the rows changed since the last drain.

        Without `track_changes` (a catalog nobody persists) this is always empty, and
        nothing is kept meanwhile (a registrar without a backup never drains).
        """
        return self._changes.drain(self._served.resources, self._clients.records)

    @classmethod
    def restore(
        cls,
        resources: Iterable[Resource],
        clients: Iterable[ClientRecord],
        unread: UnreadRows | None = None,
    ) -> Catalog:
        """Build a catalog from stored rows (nothing is marked changed).

        Resources whose `digest` is known are indexed without looking at their request
        (a restored request stays encoded until first used). `unread` holds the stored
        resources not given in `resources`: lookups read them when they need them.
        """
        catalog = cls(track_changes=True)
        if unread is not None and unread.remaining:
            catalog._backlog.rows = unread
        served = catalog._served
        served.restore(resources)
        catalog._consumers.restore(served.resources.values())
        catalog._clients.restore(clients)
        return catalog

    def check_invariants(self) -> None:
        """Raise `AssertionError` if the indexes disagree with the rows (for tests)."""
        self.read_all()
        invariants.check(self._served, self._consumers, self._clients)
