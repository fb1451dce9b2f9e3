"""The served resources in memory: their rows, their life's steps, matching, listings.

```
 Catalog ──► begin_load ─► finish_load ─► (set_response, set_texts, mark_failed)
               ─► begin_unload ─► remove          each step: ChangeLog.resource_changed
         ──► add_consumer / drop_consumer          the row's consumers (ConsumerIds
                                                   keeps the index from query ids)
         ──► match(server, request, digest, key) ─► RequestIndex ─► (found, undecided)
         ──► of_server, unheld, listing, counts, consumers_from, ...  (rows in memory)
 Backlog ──► take(resource): a row read back from the backup (no change to store)
```

A resource its provider reported `FATAL` is marked `failed` (`mark_failed`) and is never
matched again: an equal request loads a new resource, while the dead one stays, held by
its consumers under their ids, until each released it (docs/explanation/semantics.md,
rule 1). FATAL means dead: sharing a dead resource would let one holder that never
releases it keep every later consumer from a working one.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

from rr_actors._catalog.changes import ChangeLog
from rr_actors._catalog.digest import NO_DIGEST, requests_equal
from rr_actors._catalog.index import RequestIndex
from rr_actors._catalog.records import Listing, Resource, ResourceState

__all__ = ["Served"]


class Served:
    """The resources in memory, by id, with their request index.

    Attributes:
        resources: id -> resource; in creation order but for those read back from the
            backup, which `in_order` puts back in their stored order when asked.
    """

    def __init__(self, changes: ChangeLog) -> None:
        self._changes = changes
        self._index = RequestIndex()
        self.resources: dict[str, Resource] = {}
        self._unsorted = False  # resources read back since `resources` was last ordered

    # -- matching -------------------------------------------------------------------

    def match(
        self, server: str, request: Any, digest: int | None, key: Any
    ) -> tuple[Resource | None, list[Resource]]:
        """`Catalog.lookup` among the resources in memory (none is read from the backup)."""
        resources = self.resources
        if digest is not None:
            for rid in self._index.with_digest(server, digest):
                resource = resources[rid]
                if resource.failed:  # reported FATAL: never matched again
                    continue
                if requests_equal(resource.request, request):  # both plain: no user code
                    return resource, []
        undecided = self._index.undecided(server, request, digest, key)
        return None, [resources[rid] for rid in undecided if not resources[rid].failed]

    # -- a resource's life ----------------------------------------------------------

    def begin_load(self, rid: str, server: str, request: Any, key: Any) -> Resource:
        """Add a resource in the `LOADING` state.

        Args:
            rid: its id.
            server: its server's name.
            request: its request.
            key: for a request without a digest, its `runtime_key` if the caller computed
                it already (off the actor thread: it runs the request's `__hash__`).
        """
        resource = Resource(rid, server, request)
        self.resources[rid] = resource
        self._index.add(resource, key)
        self._changes.resource_changed(rid)
        return resource

    def finish_load(self, rid: str, response: Any) -> Resource:
        """Mark a loading resource `LOADED` with its response."""
        resource = self.resources[rid]
        resource.response = response
        resource.response_version += 1
        resource.state = ResourceState.LOADED
        self._changes.resource_changed(rid)
        return resource

    def set_response(self, rid: str, response: Any) -> None:
        """Replace a resource's stored response."""
        resource = self.resources[rid]
        resource.response = response
        resource.response_version += 1
        self._changes.resource_changed(rid)

    def set_texts(
        self, rid: str, request_text: str | None, response_text: str | None, label: str | None
    ) -> None:
        """Set a resource's display texts or label (those given; `None`: keep it)."""
        resource = self.resources[rid]
        if request_text is not None:
            resource.request_text = request_text
        if response_text is not None:
            resource.response_text = response_text
        if label is not None:
            resource.label = label
        self._changes.resource_changed(rid)

    def mark_failed(self, rid: str) -> Resource:
        """Mark a resource dead: its provider reported it `FATAL`.

        From now on no request matches it (`Catalog.find`, `Catalog.lookup`): an equal
        request loads a new resource. It keeps its consumers until each releases it, and
        it is unloaded as any other when the last one does.
        """
        resource = self.resources[rid]
        if not resource.failed:
            resource.failed = True
            self._changes.resource_changed(rid)
        return resource

    def begin_unload(self, rid: str) -> Resource:
        """Mark a resource `UNLOADING` (its last consumer left)."""
        resource = self.resources[rid]
        resource.state = ResourceState.UNLOADING
        self._changes.resource_changed(rid)
        return resource

    def remove(self, rid: str) -> Resource:
        """Delete a resource that has no consumers any more."""
        resource = self.resources.pop(rid)
        assert not resource.consumers, "a resource with consumers cannot be removed"
        self._index.remove(resource)
        self._changes.resource_changed(rid)
        return resource

    def add_consumer(self, rid: str, query_id: str, origin_rr: str) -> None:
        """Write one more consumer id, held by registrar `origin_rr`, into a resource's row."""
        self.resources[rid].consumers[query_id] = origin_rr
        self._changes.resource_changed(rid)

    def drop_consumer(self, resource: Resource, query_id: str) -> None:
        """Delete a consumer id from a resource's row."""
        del resource.consumers[query_id]
        self._changes.resource_changed(resource.id)

    def changed(self, rid: str) -> None:
        """See `Catalog.mark_changed`."""
        self._changes.resource_changed(rid)

    # -- rows from the backup -------------------------------------------------------

    def restore(self, resources: Iterable[Resource]) -> None:
        """Take stored resources, in their stored order (nothing is marked changed)."""
        self.resources = {resource.id: resource for resource in resources}
        self._index.restore(self.resources.values())

    def take(self, resource: Resource) -> None:
        """Take a resource read back from the backup (nothing is marked changed)."""
        self.resources[resource.id] = resource
        self._unsorted = True
        self._index.add(resource)

    # -- reading --------------------------------------------------------------------

    def in_order(self) -> dict[str, Resource]:
        """`resources`, oldest first: restored ones in their stored order, then newer ones.

        Lookups read restored resources in whatever order traffic asks for them; they are
        put back in order (a stable sort) only when an ordered listing is asked for.
        """
        if self._unsorted:
            self.resources = dict(sorted(self.resources.items(), key=_stored_order))
            self._unsorted = False
        return self.resources

    def indexed(self, server: str) -> list[Resource]:
        """`server`'s resources in memory, in index order (those with a digest first)."""
        resources = self.resources
        return [resources[rid] for rid in self._index.ids_of(server)]

    def of_server(self, server: str) -> list[Resource]:
        """`server`'s resources in memory, oldest first."""
        return [r for r in self.in_order().values() if r.server == server]

    def unheld(self) -> list[Resource]:
        """Those loaded that no consumer holds, oldest first.

        A restored catalog may have some: their last consumer left, and a crash came
        before their unload began.
        """
        return [
            resource
            for resource in self.in_order().values()
            if resource.state is ResourceState.LOADED and not resource.consumers
        ]

    def consumers_from(self, origin_rr: str) -> list[str]:
        """Their consumer ids that registrar `origin_rr` holds, by resource."""
        return [
            query_id
            for resource in self.resources.values()
            for query_id, origin in resource.consumers.items()
            if origin == origin_rr
        ]

    def consumer_origins(self) -> set[str]:
        """The registrars that hold their consumer ids."""
        return {o for resource in self.resources.values() for o in resource.consumers.values()}

    def listing(self, limit: int) -> Listing | None:
        """`(sort key, row)` of each one, oldest first, and of each of their consumers.

        Args:
            limit: the most rows of either kind to return.

        Returns:
            `(resources, consumers)`: `(id, server, state, digest, failed)` per resource
            (`digest` in decimal, `""` for a request without one; `failed` `"failed"`
            if its provider reported it `FATAL`, else `""`), and `(query id, resource
            id, consumer registrar)` per consumer id, by resource, in arrival order;
            each after its sort key (`_stored_order`); `None` if either kind has more
            than `limit` rows.
        """
        resources: list[tuple[float, tuple[str, ...]]] = []
        consumers: list[tuple[float, tuple[str, ...]]] = []
        for resource in self.in_order().values():
            order = _stored_order((resource.id, resource))
            digest = resource.digest
            plain = digest is not None and digest != NO_DIGEST
            row = (
                resource.id,
                resource.server,
                resource.state.value,
                str(digest) * plain,
                "failed" * resource.failed,
            )
            resources.append((order, row))
            consumers.extend(
                (order, (qid, resource.id, o)) for qid, o in resource.consumers.items()
            )
            if len(resources) > limit or len(consumers) > limit:
                return None
        return resources, consumers

    def counts(self) -> tuple[int, int]:
        """How many there are, and how many consumer ids they have."""
        resources = self.resources.values()
        return len(resources), sum(len(resource.consumers) for resource in resources)


def _stored_order(item: tuple[str, Resource]) -> float:
    """Sort key: a restored resource's row key in its backup; one created since is newer."""
    order: float = item[1].__dict__.get("_order", math.inf)
    return order
