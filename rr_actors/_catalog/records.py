"""The catalog's rows: served resources, client records, and the changes to store."""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Callable
from typing import Any, Protocol

from rr_actors._types import Query

__all__ = [
    "Changes",
    "ClientRecord",
    "Decoder",
    "Listing",
    "Resource",
    "ResourceState",
    "UnreadRows",
]


class ResourceState(enum.Enum):
    """Life cycle of a served resource."""

    LOADING = "loading"
    LOADED = "loaded"
    UNLOADING = "unloading"


@dataclasses.dataclass
class Resource:
    """A resource a server of this registrar serves.

    A resource restored from a backup decodes its request and its response on first
    access (most restored resources are not looked at before traffic resumes); a stored
    value that cannot be decoded then raises `CatalogCorruptError` naming the backup.

    Attributes:
        id: resource id (UUID4 string), stable for the resource's life.
        server: name of the server that loaded it.
        request: the request that describes it.
        response: what `load` returned (`None` while loading).
        state: life-cycle state.
        consumers: consumer query id -> origin registrar name, in arrival order.
        digest: `request_digest(request)`, `NO_DIGEST` if it has none, `None` if not known
            yet (computed when the catalog indexes it).
        response_version: counts the catalog's writes of `response` (`finish_load`,
            `set_response`), so the store writes each one even when the provider passes
            the same, mutated object again; decoding a restored response leaves it alone.
        request_text, response_text: bounded `repr`s of the values, made once by the
            registrar that owns them (`None`: not made yet); what observers show.
        label: what its server's `label(request)` returned (`None`: none, or not yet).
        failed: its provider reported it `FATAL` (`Catalog.mark_failed`): it is no longer
            matched by an equal request (a new call loads a new resource), and it stays
            until its consumers released it.
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
        # Only called when `name` is not in the instance: a restored, still encoded value.
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
        """A stored resource whose request and response are decoded on first access.

        Args:
            rid: resource id.
            server: server name.
            state: life-cycle state.
            digest: the stored request digest (or `NO_DIGEST`).
            blobs: the encoded request and response.
            decode: `decode(rid, "request" | "response", blob)` returns the value or
                raises `CatalogCorruptError`.
            order: its place in the backup (row key), to list restored resources in
                their stored order.
            texts: the stored `(request_text, response_text, label)`.
            failed: the stored `failed` mark.
        """
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
"""`decode(resource_id, field, blob)`: turns a stored value back into an object."""

_LAZY = {"request": 0, "response": 1}
# Without class attributes the two values are looked up in the instance, and a missing
# (still encoded) one reaches `__getattr__`. `__init__` keeps its defaults.
del Resource.response


@dataclasses.dataclass
class ClientRecord:
    """A query this registrar holds at some server (its own servers included).

    Attributes:
        query: the query, `origin_rr` being this registrar.
        parent: id of this registrar's resource that owns the query as a dependency,
            or `None` for a top-level call.
        loaded: `False` while the call is in flight.
        response_version: counts `client_loaded` calls, so the store writes each response.
        request_text: a bounded `repr` of the request, made once by this registrar
            (`None`: not made yet); what observers show.
    """

    query: Query
    parent: str | None = None
    loaded: bool = False
    response_version: int = dataclasses.field(default=0, compare=False, repr=False)
    request_text: str | None = dataclasses.field(default=None, compare=False, repr=False)


@dataclasses.dataclass
class Changes:
    """Rows changed since the last drain: id -> new row, or `None` when deleted.

    `consumers` says which consumer ids of a changed resource may have changed (been
    added or released since the last drain), so that a write looks at those only, not
    at every holder of a widely shared resource: resource id -> those query ids, in the
    order they last changed (an empty dict: none did). A resource of `resources` not
    listed there has every consumer compared (the safe default of a `Changes` built by
    hand).
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


Listing = tuple[list[tuple[float, tuple[str, ...]]], list[tuple[float, tuple[str, ...]]]]
"""Resource rows and consumer rows as strings, each after its sort key (its resource's
row key in the backup): what `UnreadRows.listing` returns."""


class UnreadRows(Protocol):
    """Served resources of a restored catalog still in its backup (see `Catalog.restore`).

    Each method returns resources not returned before, with their consumers; once
    returned, a resource lives in the catalog's memory and is never returned again.
    """

    remaining: bool
    """Whether some may not have been returned yet (`False` once `every` returned)."""

    def by_request(self, server: str, digest: int) -> list[Resource]:
        """Those of `server` whose request digest is `digest`."""

    def by_consumer(self, query_id: str) -> Resource | None:
        """The one that has consumer `query_id`, if any."""

    def of_server(self, server: str) -> list[Resource]:
        """Every one of `server`, oldest first."""

    def with_origin(self, origin_rr: str) -> list[Resource]:
        """Every one with a consumer from registrar `origin_rr`."""

    def consumer_ids_from(self, origin_rr: str) -> list[str]:
        """Their consumer ids that registrar `origin_rr` holds (reading no resource)."""

    def sweep(self, after: int) -> tuple[list[Resource], set[str], int | None]:
        """The next slice after row key `after`: those loaded that no consumer holds
        (returned), the registrars of every consumer in it, its last row key (`None`:
        no slice is left)."""

    def listing(self, limit: int) -> Listing | None:
        """`(row key, row)` of each one and of each of their consumers, without
        returning them; `None` if either kind has more than `limit`."""

    def counts(self) -> tuple[int, int]:
        """How many there are, and how many consumer ids they have."""

    def every(self) -> list[Resource]:
        """All of them, oldest first."""
