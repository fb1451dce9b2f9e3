"""The catalog: what a registrar serves and holds, as data (no threads, no files opened).

- `records`: the rows (`Resource`, `ClientRecord`) and the `Changes` to store;
- `digest`: request digests, so that equal (`==`) requests meet without comparing all;
- `catalog`: the `Catalog`, written only by its registrar actor: the one name the
  registrar and the store use, over its roles, each owning its own state:
  - `served`: the resources in memory, their life's steps and listings, matched
    through `index` (`RequestIndex`: by request digest);
  - `consumers`: query id -> resource id (`ConsumerIds`);
  - `clients`: the client records and each resource's dependencies (`ClientRecords`);
  - `backlog`: a restored catalog's rows still in the backup, read in when a lookup
    needs them, through the store (`UnreadRows`);
  - `changes`: the rows changed since the store last drained them (`ChangeLog`);
  - `invariants`: the check that every index agrees with the rows (for tests);
- `texts`: display texts of requests and responses.
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
