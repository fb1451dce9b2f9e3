"""The client records: the queries a registrar holds elsewhere, and whose dependencies they are.

```
 Catalog.add_client(record) ──► records[qid]; a dependency: owners[parent] += qid
 Catalog.client_loaded / set_client_text ──► the record changed
 Catalog.remove_client(qid) ──► gone from both
   each change ──► ChangeLog.client_changed(qid)
 Catalog.dependencies(rid) ──► the records resource `rid` owns, oldest first
```

A dependency's record names the resource of this registrar that owns it (`parent`,
rule 5): when that resource is unloaded, its dependencies are released.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from rr_actors._catalog.changes import ChangeLog
from rr_actors._catalog.records import ClientRecord
from rr_actors.errors import UnknownQueryError

__all__ = ["ClientRecords"]


class ClientRecords:
    """The client records by query id, with the dependencies of each resource.

    Attributes:
        records: query id -> its record, oldest first (`Catalog.clients`).
    """

    def __init__(self, changes: ChangeLog) -> None:
        self._changes = changes
        self.records: dict[str, ClientRecord] = {}
        self._deps: dict[str, list[str]] = {}  # resource id -> the query ids it owns

    def add(self, record: ClientRecord) -> None:
        """See `Catalog.add_client`."""
        qid = record.query.id
        if qid in self.records:
            raise ValueError(f"query id {qid} is already a client record")
        self.records[qid] = record
        if record.parent is not None:
            self._deps.setdefault(record.parent, []).append(qid)
        self._changes.client_changed(qid)

    def loaded(self, query_id: str, response: Any) -> ClientRecord | None:
        """See `Catalog.client_loaded`."""
        record = self.records.get(query_id)
        if record is None:
            return None
        record.query = record.query.with_response(response)
        record.loaded = True
        record.response_version += 1
        self._changes.client_changed(query_id)
        return record

    def set_text(self, query_id: str, request_text: str) -> None:
        """Set a record's request display text."""
        self.records[query_id].request_text = request_text
        self._changes.client_changed(query_id)

    def remove(self, query_id: str) -> ClientRecord:
        """See `Catalog.remove_client`."""
        record = self.records.pop(query_id, None)
        if record is None:
            raise UnknownQueryError(f"unknown or released query id {query_id!r}")
        if record.parent is not None:
            deps = self._deps[record.parent]
            deps.remove(query_id)
            if not deps:
                del self._deps[record.parent]
        self._changes.client_changed(query_id)
        return record

    def dependencies(self, rid: str) -> list[ClientRecord]:
        """The records owned by resource `rid`, oldest first."""
        return [self.records[qid] for qid in self._deps.get(rid, ())]

    def restore(self, records: Iterable[ClientRecord]) -> None:
        """Take stored records, in their stored order (nothing is marked changed)."""
        self.records = {record.query.id: record for record in records}
        deps = self._deps
        for qid, record in self.records.items():
            if record.parent is not None:
                deps.setdefault(record.parent, []).append(qid)

    def dependency_index(self) -> dict[str, list[str]]:
        """A copy of resource id -> the query ids it owns (for the invariants' check)."""
        return {rid: list(qids) for rid, qids in self._deps.items()}
