"""The catalog: what a registrar serves and holds, as data (no threads, no files opened).

- `records`: the rows (`Resource`, `ClientRecord`) and the `Changes` to store;
- `digest`: request digests, so that equal (`==`) requests meet without comparing all;
- `catalog`: the `Catalog` with its indexes, written only by its registrar actor; a
  restored one reads rows it has not read yet through the store (`UnreadRows`).
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
