"""The catalog: what a registrar serves and holds, as data (no threads, no files opened).

```
 catalog   Catalog: the resources, their consumers, the client records and the changes
    │      the store drains; written only by its registrar actor; RequestIndex: which
    │      resources of a server may serve a request, by digest
 records   the rows (Resource, ClientRecord, Changes) and UnreadRows (the backlog of a
           restored catalog: the store's reader of the backup)
 digest    request digests, so that equal (`==`) requests meet without comparing all
 texts     display texts of requests and responses
```
"""

from rr_actors._catalog.catalog import Catalog
from rr_actors._catalog.digest import (
    DIGEST_SCHEME,
    NO_DIGEST,
    describe,
    request_bucket,
    request_digest,
    runtime_key,
)
from rr_actors._catalog.records import (
    Changes,
    ClientRecord,
    Decoder,
    Listing,
    Resource,
    ResourceState,
    UnreadRows,
)

__all__ = [
    "DIGEST_SCHEME",
    "NO_DIGEST",
    "Catalog",
    "Changes",
    "ClientRecord",
    "Decoder",
    "Listing",
    "Resource",
    "ResourceState",
    "UnreadRows",
    "describe",
    "request_bucket",
    "request_digest",
    "runtime_key",
]
