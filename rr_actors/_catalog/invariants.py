"""The catalog's invariants, checked for tests: every index agrees with the rows.

```
 Catalog.check_invariants ──► every row read in from the backup ──► check:
   ConsumerIds.snapshot()          == the rows' consumers, by query id
   Served.of_server(server)        no request loaded twice (but a failed one's)
   ClientRecords.dependency_index() == the records' parents; each parent is served here
```
"""

from __future__ import annotations

from rr_actors._catalog.clients import ClientRecords
from rr_actors._catalog.consumers import ConsumerIds
from rr_actors._catalog.digest import requests_equal
from rr_actors._catalog.records import ResourceState
from rr_actors._catalog.served import Served

__all__ = ["check"]


def check(served: Served, consumers: ConsumerIds, clients: ClientRecords) -> None:
    """Raise `AssertionError` if an index disagrees with the rows in memory.

    Args:
        served: the resources (every one in memory: the caller read the backlog in).
        consumers: their consumer ids' index.
        clients: the client records and their dependency index.
    """
    resources = served.resources
    by_consumer = {q: r.id for r in resources.values() for q in r.consumers}
    assert by_consumer == consumers.snapshot(), "consumer index out of sync"
    for resource in resources.values():
        if resource.state is ResourceState.LOADED and not resource.failed:
            equal = [
                r
                for r in served.of_server(resource.server)
                if r.id != resource.id
                and not r.failed
                and requests_equal(r.request, resource.request)
            ]
            assert not equal, f"resource {resource.id} is loaded twice"
    deps: dict[str, list[str]] = {}
    for qid, record in clients.records.items():
        if record.parent is not None:
            assert record.parent in resources, f"dependency {qid} has no owner"
            deps.setdefault(record.parent, []).append(qid)
    assert deps == clients.dependency_index(), "dependency index out of sync"
