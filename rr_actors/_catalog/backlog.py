"""The backlog of a restored catalog: the resources still in the backup, read in when needed.

```
 Catalog.lookup / resource_of / resources_of / ... ──► read_*(...)
   ──► UnreadRows (the store's reader of the backup, _store/restore.py)
   ──► each resource read: ConsumerIds.take, then Served.take (never read again)
 Catalog.rows / counts / consumer_ids_from ──► listing, counts, consumer_ids_from
   (asked of the backup without reading a resource in)
 once the backup has returned every one: done, nothing is asked any more
```

A restore does not read every row: the resources traffic needs are read when a lookup
first needs them, and the rest by the registrar's sweep (`sweep`), one slice at a time.
"""

from __future__ import annotations

from rr_actors._catalog.consumers import ConsumerIds
from rr_actors._catalog.records import Listing, Resource, UnreadRows
from rr_actors._catalog.served import Served

__all__ = ["Backlog"]


class Backlog:
    """What of a restored catalog is still in its backup (nothing, for any other).

    Attributes:
        rows: the backup's reader, `None` once nothing is left in it (or for a catalog
            not restored, or restored whole).
    """

    def __init__(self, served: Served, consumers: ConsumerIds) -> None:
        self._served = served
        self._consumers = consumers
        self.rows: UnreadRows | None = None

    def remaining(self) -> bool:
        """Whether some resources may still be in the backup."""
        return self.rows is not None

    def read_request(self, server: str, digest: int) -> None:
        """Read in `server`'s resources whose request digest is `digest`."""
        if self.rows is not None:
            self._take(self.rows.by_request(server, digest))

    def read_server(self, server: str) -> None:
        """Read in every resource of `server`."""
        if self.rows is not None:
            self._take(self.rows.of_server(server))

    def read_origin(self, origin_rr: str) -> None:
        """Read in every resource with a consumer id that registrar `origin_rr` holds."""
        if self.rows is not None:
            self._take(self.rows.with_origin(origin_rr))

    def read_consumer(self, query_id: str) -> str | None:
        """Read in the resource `query_id` is a consumer of; its id, or `None` if the
        backup has none."""
        if self.rows is None:
            return None
        resource = self.rows.by_consumer(query_id)
        if resource is None:
            return None
        self._take([resource])
        return resource.id

    def read_all(self) -> None:
        """Read in every resource left."""
        if self.rows is not None:
            self._take(self.rows.every())

    def sweep(self, after: int) -> tuple[list[Resource], set[str], int | None]:
        """Look at the next slice of the resources still in the backup (row keys above
        `after`, a bounded number of them).

        Returns:
            `(unheld, origins, last)`: those in it loaded and held by no consumer (read
            into memory now), the registrars holding consumer ids in it, and the row
            key to sweep on from (`None`: nothing is left to sweep).
        """
        if self.rows is None:
            return [], set(), None
        unheld, origins, last = self.rows.sweep(after)
        self._take(unheld)
        return unheld, origins, last

    def consumer_ids_from(self, origin_rr: str) -> list[str]:
        """The consumer ids left in the backup that `origin_rr` holds."""
        return [] if self.rows is None else self.rows.consumer_ids_from(origin_rr)

    def merged(self, memory: Listing, limit: int) -> Listing | None:
        """The rows in memory (`Served.listing`) merged with those left in the backup,
        without reading any in; `None` if either kind has more than `limit` rows."""
        if self.rows is None:
            return memory
        unread = self.rows.listing(limit)
        if unread is None:
            return None
        resources = sorted([*memory[0], *unread[0]], key=_first)  # stable: arrival order kept
        consumers = sorted([*memory[1], *unread[1]], key=_first)
        if len(resources) > limit or len(consumers) > limit:
            return None
        return resources, consumers

    def counts(self) -> tuple[int, int]:
        """How many resources are left, and how many consumer ids they have."""
        return (0, 0) if self.rows is None else self.rows.counts()

    def _take(self, resources: list[Resource]) -> None:
        for resource in resources:
            self._consumers.take(resource)
            self._served.take(resource)
        if self.rows is not None and not self.rows.remaining:
            self.rows = None  # everything is in memory: stop asking


def _first(item: tuple[float, tuple[str, ...]]) -> float:
    return item[0]
