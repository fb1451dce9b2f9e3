"""The catalog's change log: which rows changed since the store last drained them.

```
 Served, ClientRecords ──► resource_changed(rid) / client_changed(qid)
 Catalog.mark_changed(rid) ──► resource_changed(rid)     (a write held back)
 the store (_store/saver.py) ──► Catalog.drain_changes ──► drain(resources, clients)
                                  ──► Changes: each changed row as it is now, or None
```

Row ids are kept in the order they first changed, so new rows drain in creation order.
A catalog nobody persists keeps none (nobody would drain them).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from rr_actors._catalog.records import Changes, ClientRecord, Resource

__all__ = ["ChangeLog"]


class _DirtySet(dict[str, None]):
    """An insertion-ordered set of row ids (so the store can keep the rows' order)."""

    # `add(key)`: `self[key] = None`, in C (it is on every change's path); a key already
    # in keeps its place either way
    add: Any = dict.setdefault


class _NoDirt(_DirtySet):
    """The changed rows of a catalog nobody persists: none are kept (nobody drains them)."""

    def add(self, key: str) -> None:
        pass


class ChangeLog:
    """The ids of the rows changed since the last drain, resources and client records apart.

    Attributes:
        resources: the ids of the resources changed (read by tests only).
        clients: the query ids of the client records changed (read by tests only).
        resource_changed: `resource_changed(rid)`: have the next drain report resource
            `rid` as it is then (its row, or its removal).
        client_changed: `client_changed(query_id)`: the same for a client record.
    """

    def __init__(self, *, track_changes: bool) -> None:
        self.resources = _DirtySet() if track_changes else _NoDirt()
        self.clients = _DirtySet() if track_changes else _NoDirt()
        # the sets' own `add`, bound once: every change of the catalog calls one
        self.resource_changed: Callable[[str], object] = self.resources.add
        self.client_changed: Callable[[str], object] = self.clients.add

    def drain(
        self, resources: Mapping[str, Resource], clients: Mapping[str, ClientRecord]
    ) -> Changes:
        """Return and forget the rows changed since the last drain.

        Args:
            resources: the catalog's resources in memory, by id (a changed one that is
                not in it was removed).
            clients: its client records, by query id (likewise).
        """
        changes = Changes(
            {rid: resources.get(rid) for rid in self.resources},
            {qid: clients.get(qid) for qid in self.clients},
        )
        self.resources.clear()
        self.clients.clear()
        return changes
