"""The catalog's rows: served resources, client records, and the changes to store."""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Callable
from typing import Any, Protocol

from rr_actors._types import Query


class ResourceState(enum.Enum):
    """Life cycle of a served resource."""

    LOADING = "loading"
    LOADED = "loaded"
    UNLOADING = "unloading"


@dataclasses.dataclass
class Resource:
    """A resource a server of this registrar serves (a restored one decodes its request and
    response on first access, or raises `CatalogCorruptError`).

    `consumers`: query id -> origin registrar, in arrival order; `digest`: `NO_DIGEST` if
    it has none, `None` if not known yet; `response_version`: counts the catalog's writes
    of `response` (the store writes each, even the same mutated object); `*_text`,
    `label`: made once by its registrar (`None`: not yet); `failed`: reported `FATAL`,
    never matched again.
    """

    id: str
    server: str
    request: Any
    response: Any = None
    state: ResourceState = ResourceState.LOADING
    consumers: dict[str, str] = dataclasses.field(default_factory=dict)
    digest: int | None = dataclasses.field(default=None, compare=False, repr=False)
    response_version: int = dataclasses.field(default=0, compare=False, repr=False)
    request_text: str | None = dataclasses.field(default=None, compare=False, repr=False)
    response_text: str | None = dataclasses.field(default=None, compare=False, repr=False)
    label: str | None = dataclasses.field(default=None, compare=False, repr=False)
    failed: bool = False

    def __getattr__(self, name: str) -> Any:
        # (only for a name not in the instance: a restored, still encoded value)
        if name in _LAZY:
            encoded = self.__dict__.get("_encoded")
            if encoded is not None:
                decode, blobs = encoded
                value = decode(self.id, name, blobs[_LAZY[name]])
                values = self.__dict__
                values[name] = value
                if "request" in values and "response" in values:
                    del values["_encoded"]  # both decoded: free the blobs
                return value
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    @classmethod
    def encoded(
        cls,
        rid: str,
        server: str,
        state: ResourceState,
        digest: int,
        blobs: tuple[bytes | None, bytes | None],
        decode: Decoder,
        order: int = 0,
        texts: tuple[str | None, str | None, str | None] = (None, None, None),
        *,
        failed: bool = False,
    ) -> Resource:
        """A stored resource whose request and response (`blobs`) are decoded on first
        access; `order`: its row key in the backup."""
        resource = cls.__new__(cls)
        resource.__dict__ = {
            "id": rid,
            "server": server,
            "state": state,
            "consumers": {},
            "digest": digest,
            "response_version": 0,
            "request_text": texts[0],
            "response_text": texts[1],
            "label": texts[2],
            "failed": failed,
            "_encoded": (decode, blobs),
            "_order": order,
        }
        return resource


Decoder = Callable[[str, str, "bytes | None"], Any]
"""`decode(resource_id, field, blob)`: a stored value back (or `CatalogCorruptError`)."""

_LAZY = {"request": 0, "response": 1}
del Resource.response  # (no class attribute: a still encoded one reaches `__getattr__`)


@dataclasses.dataclass
class ClientRecord:
    """A query this registrar holds at some server (`parent`: the resource of its own that
    owns it as a dependency, `None` for a top-level call)."""

    query: Query
    parent: str | None = None
    loaded: bool = False
    response_version: int = dataclasses.field(default=0, compare=False, repr=False)
    request_text: str | None = dataclasses.field(default=None, compare=False, repr=False)


@dataclasses.dataclass
class Changes:
    """Rows changed since the last drain: id -> new row, or `None` when deleted.

    `consumers`: resource id -> the consumer ids added or released since, in the order
    they last changed; a resource not listed has every consumer compared.
    """

    resources: dict[str, Resource | None]
    clients: dict[str, ClientRecord | None]
    consumers: dict[str, dict[str, None]] = dataclasses.field(default_factory=dict)

    def __bool__(self) -> bool:
        return bool(self.resources or self.clients)

    def update(self, later: Changes) -> None:
        """Merge `later` (changes made after these) into these, as if drained at once."""
        mine = self.consumers
        for rid in later.resources:
            ids = later.consumers.get(rid)
            known = mine.get(rid)
            if ids is None or (known is None and rid in self.resources):
                mine.pop(rid, None)  # either side compares every consumer
            elif known is None:
                mine[rid] = dict(ids)
            else:
                for query_id in ids:  # (in the order they last changed)
                    known.pop(query_id, None)
                    known[query_id] = None
        self.resources.update(later.resources)
        self.clients.update(later.clients)


Listing = tuple[list[tuple[Any, ...]], list[tuple[Any, ...]]]
"""Resource rows and consumer rows as strings, each after its resource's row key (as the
backup's rows come: no pair built per row)."""


class UnreadRows(Protocol):
    """Served resources of a restored catalog still in its backup: each method returns
    resources not returned before, with their consumers (`remaining`: some may be left)."""

    remaining: bool

    def by_request(self, server: str, digest: int) -> list[Resource]: ...

    def by_consumer(self, query_id: str) -> Resource | None: ...

    def of_server(self, server: str) -> list[Resource]: ...

    def with_origin(self, origin_rr: str) -> list[Resource]: ...

    def consumer_ids_from(self, origin_rr: str) -> list[str]:
        """Their consumer ids that `origin_rr` holds, reading no resource."""
        ...

    def sweep(self, after: int) -> tuple[list[Resource], set[str], int | None]:
        """As `Catalog.sweep`."""
        ...

    def listing(self, limit: int) -> Listing | None:
        """As `Catalog.rows`, without returning them."""
        ...

    def counts(self) -> tuple[int, int]: ...

    def every(self) -> list[Resource]: ...
