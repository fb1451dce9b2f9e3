"""The consumer ids: which resource in memory each query id served here belongs to.

```
 Catalog.add_consumer(rid, qid) ──► add(qid, rid)        (the row: Served.add_consumer)
 Catalog.release(qid) ───────────► remove(qid)           (the row: Served.drop_consumer)
 Catalog.resource_of / has_consumer ──► rid_of(qid) ──► a resource id, or None: then the
                                                        backup is asked (Backlog)
 Backlog.take / Catalog.restore ──► take(resource): index a row's consumers
```

The rows hold their consumers (`Resource.consumers`, query id -> the registrar that holds
it); this is the index the other way round, so a release finds its resource at once.
"""

from __future__ import annotations

from collections.abc import Iterable

from rr_actors._catalog.records import Resource

__all__ = ["ConsumerIds"]


class ConsumerIds:
    """Query id -> the id of the resource in memory it is a consumer of."""

    def __init__(self) -> None:
        self._by_consumer: dict[str, str] = {}

    def __contains__(self, query_id: object) -> bool:
        return query_id in self._by_consumer

    def rid_of(self, query_id: str) -> str | None:
        """The id of the resource `query_id` is a consumer of, if that one is in memory."""
        return self._by_consumer.get(query_id)

    def add(self, query_id: str, rid: str) -> None:
        """`query_id` is now a consumer of resource `rid`."""
        self._by_consumer[query_id] = rid

    def remove(self, query_id: str) -> None:
        """`query_id` is no longer a consumer (it was one)."""
        del self._by_consumer[query_id]

    def take(self, resource: Resource) -> None:
        """Index the consumers of a resource read back from the backup."""
        for query_id in resource.consumers:
            self._by_consumer[query_id] = resource.id

    def restore(self, resources: Iterable[Resource]) -> None:
        """Index the consumers of stored resources (the index is rebuilt)."""
        self._by_consumer = {
            query_id: resource.id for resource in resources for query_id in resource.consumers
        }

    def snapshot(self) -> dict[str, str]:
        """A copy of the index (for the invariants' check)."""
        return dict(self._by_consumer)
