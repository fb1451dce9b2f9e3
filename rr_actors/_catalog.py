"""The resource catalog: pure data, no threads, no I/O.

The catalog records what a registrar serves (resources, each with its consumers' query
ids) and what it holds elsewhere (client records, some of them dependencies of its own
resources). Only the registrar actor writes it, so it has no locks. Every change marks
the touched rows dirty; the persistence layer drains them as one transaction.

Dedup is by `==` on the request value, also for unhashable values: requests are bucketed
by `request_digest`, a deterministic digest of a canonical form (mappings as item sets,
sequences in order, numbers by their value), and within a bucket compared with `==`. The
digest covers only built-in values whose `==` it mirrors (and subclasses that keep their
base's `==`), so two such requests that are `==` meet in the same bucket. The digest may
be stored: a restored catalog indexes its resources from their stored digests without
decoding a request. Any other request (a custom class, a subclass with its own `__eq__`
such as `Counter`, a value whose comparison raises) has no digest: it is bucketed by its
in-process `hash()` when its class defines one together with its `__eq__`, otherwise with
the unhashable ones, and compared with `==` against every candidate that could equal it.
Finding a request never raises because of its value: a comparison that raises means
"different".
"""

from __future__ import annotations

import dataclasses
import decimal
import enum
import fractions
import hashlib
import math
import sys
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator, Mapping, Set
from typing import Any, Protocol

from rr_actors._types import Query
from rr_actors.errors import UnknownQueryError

__all__ = [
    "DIGEST_SCHEME",
    "NO_DIGEST",
    "Catalog",
    "Changes",
    "ClientRecord",
    "Resource",
    "ResourceState",
    "UnreadRows",
    "request_bucket",
    "request_digest",
]

_UNHASHABLE = ("<unhashable>",)

NO_DIGEST = -1
"""`Resource.digest` of a request that has no digest (`hash()` never returns -1 either)."""

_TAG_NONE, _TAG_SEQ, _TAG_MAP, _TAG_SET, _TAG_NAN, _TAG_ENUM = range(0x5F3A_0000, 0x5F3A_0006)
_NUMBERS = (int, float, complex, decimal.Decimal, fractions.Fraction)
_STRINGS: dict[str, int] = {}  # str -> digest; strings repeat (keys, command names)
_STRINGS_MAX = 4096

DIGEST_SCHEME = (
    f"rr3-py{sys.version_info[0]}.{sys.version_info[1]}-w{sys.hash_info.width}"
    f"-{sys.hash_info.modulus}"
)
"""Names the digest function. It combines parts with `hash()` of tuples and frozensets
of integers, which is deterministic but may change with Python's version or word size:
a backup written under another scheme has its digests recomputed when it is opened."""


def _blake(data: bytes) -> int:
    digest = int.from_bytes(hashlib.blake2b(data, digest_size=8).digest(), "little", signed=True)
    return -2 if digest == NO_DIGEST else digest


def _number(value: Any) -> int:
    # NaN != NaN, and its hash() is its address: every NaN gets one constant instead.
    return _TAG_NAN if value != value else hash(value)  # noqa: PLR0124


class _Opaque(Exception):  # noqa: N818 - control flow inside _digest, never escapes
    pass


def _digest(value: Any) -> int:  # noqa: PLR0911 - one return per kind of value
    cls = type(value)
    if cls is str:
        digest = _STRINGS.get(value)
        if digest is None:
            if len(_STRINGS) >= _STRINGS_MAX:
                _STRINGS.clear()
            digest = _STRINGS[value] = _blake(value.encode("utf-8", "surrogatepass"))
        return digest
    if cls is int or cls is bool:
        return hash(value)
    if cls is float or cls is complex:
        return _number(value)
    if value is None:
        return _TAG_NONE
    if cls is dict or (isinstance(value, Mapping) and _keeps_eq(cls, _MAPPING_EQ)):
        return hash((_TAG_MAP, frozenset([(_digest(k), _digest(v)) for k, v in value.items()])))
    if cls is list or cls is tuple or (isinstance(value, list | tuple) and _keeps_eq(cls, _SEQ_EQ)):
        return hash((_TAG_SEQ, *[_digest(item) for item in value]))
    if isinstance(value, Set) and _keeps_eq(cls, _SET_EQ):
        return hash((_TAG_SET, frozenset([_digest(item) for item in value])))
    if cls is bytes or cls is bytearray:  # bytearray(b"a") == b"a"
        return hash((_TAG_SEQ, _blake(value)))  # not the digest of the equal str
    if isinstance(value, enum.Enum) and _identity_equality(value):
        return _enum_member(value, cls)
    return _digest_subclass(value, cls)


def _enum_member(value: enum.Enum, cls: type) -> int:
    """A plain enum member equals only itself: its class's path and its name name it.

    Members are pickled by name, so the same member has the same digest in every process.
    (IntEnum and StrEnum keep their base's `==` and are digested as that value.)
    """
    name = value._name_
    if type(name) is not str:  # a composite Flag without a name: leave it to `==`
        raise _Opaque
    where = _blake(f"{cls.__module__}:{cls.__qualname__}".encode("utf-8", "surrogatepass"))
    return hash((_TAG_ENUM, where, _blake(name.encode("utf-8", "surrogatepass"))))


# The `==` of containers the digest mirrors: a subclass that overrides `__eq__` (Counter,
# a case-insensitive dict, a tuple with a tolerance) may call values equal whose digests
# differ, so it has no digest. OrderedDict's `==` is dict's when either side is a plain
# dict and stricter (order too) between two OrderedDicts, so equal ones have equal items.
_MAPPING_EQ: tuple[object, ...] = (dict.__eq__, OrderedDict.__eq__, Mapping.__eq__)
_SEQ_EQ: tuple[object, ...] = (list.__eq__, tuple.__eq__)
_SET_EQ: tuple[object, ...] = (set.__eq__, frozenset.__eq__, Set.__eq__)


def _keeps_eq(cls: type, eqs: tuple[object, ...]) -> bool:
    eq: object = cls.__eq__
    return eq in eqs


def _digest_subclass(value: Any, cls: type) -> int:
    """Subclasses that keep their base's `==` and `hash()` (IntEnum, StrEnum, ...)."""
    bases: tuple[type, ...] = (str, bytes, *_NUMBERS)
    for base in bases:
        same: object = (cls.__eq__, cls.__hash__) == (base.__eq__, base.__hash__)
        if issubclass(cls, base) and same:
            if base is str:
                return _blake(str.encode(value, "utf-8", "surrogatepass"))
            if base is bytes:
                return hash((_TAG_SEQ, _blake(bytes(value))))
            return _number(value)
    raise _Opaque


def request_digest(request: Any) -> int | None:
    """A deterministic 64-bit digest of a request, such that `a == b` implies equal digests.

    The same in every process (it may be stored): strings and bytes are digested with
    BLAKE2b, numbers by their `hash()` (which Python defines from the value, so that
    `1`, `1.0` and `True` agree, and which is not randomised), mappings as an
    order-free combination of their items, sets likewise, lists and tuples in order.

    Only values whose `==` the digest mirrors get one: built-in strings, bytes, numbers,
    `None`, members of enums that keep identity equality (digested by class path and
    name), and dicts, lists, tuples, sets (and other mappings and sets) of them, including
    subclasses that keep their base's `__eq__` and `__hash__` (IntEnum, StrEnum,
    namedtuple, OrderedDict, defaultdict).

    Returns:
        The digest (never `NO_DIGEST`), or `None` for a value with other parts (a
        custom class, a container subclass with its own `__eq__` such as `Counter`, an
        enum with its own `__eq__`) or one that raises while being digested (`Decimal("sNaN")`, a
        mapping whose `items()` raises), whose equality only `==` can judge; the catalog
        indexes those by their in-process `hash()` instead, which is never stored.
    """
    try:
        return _digest(request)
    except Exception:  # noqa: BLE001 - _Opaque, RecursionError, whatever user code raises
        return None


def _runtime_key(request: Any) -> Any:
    """The in-process bucket of a request that has no digest (never stored).

    A class that overrides `__eq__` but keeps a built-in `__hash__` (a tuple subclass
    with a tolerance, say) hashes inconsistently with its `==`: it goes with the
    unhashable requests, which are compared with every candidate.
    """
    cls = type(request)
    hasher: object = cls.__hash__
    owner = getattr(hasher, "__objclass__", None)
    if isinstance(owner, type) and owner is not cls:
        base_eq: object = owner.__eq__
        own_eq: object = cls.__eq__
        if base_eq is not own_eq:
            return _UNHASHABLE
    try:
        return ("h", hash(request))
    except Exception:  # noqa: BLE001 - unhashable, or a __hash__ that raises: compare by ==
        return _UNHASHABLE


def request_bucket(request: Any) -> Any:
    """Return a hashable key such that `a == b` implies equal keys (for the usual types).

    The key is the request's digest (`request_digest`); values without one fall back to
    their `hash()`, and unhashable ones share one bucket compared by `==` alone.
    """
    digest = request_digest(request)
    return digest if digest is not None else _runtime_key(request)


def requests_equal(a: Any, b: Any) -> bool:
    """`a == b`, made total: a comparison that raises or is ambiguous means "different"."""
    try:
        return bool(a == b)
    except Exception:  # noqa: BLE001 - user __eq__ may raise anything; then they differ
        return False


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
    """

    id: str
    server: str
    request: Any
    response: Any = None
    state: ResourceState = ResourceState.LOADING
    consumers: dict[str, str] = dataclasses.field(default_factory=dict)
    digest: int | None = dataclasses.field(default=None, compare=False, repr=False)
    response_version: int = dataclasses.field(default=0, compare=False, repr=False)

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
        """
        resource = cls.__new__(cls)
        resource.__dict__ = {
            "id": rid,
            "server": server,
            "state": state,
            "consumers": {},
            "digest": digest,
            "response_version": 0,
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
    """

    query: Query
    parent: str | None = None
    loaded: bool = False
    response_version: int = dataclasses.field(default=0, compare=False, repr=False)


@dataclasses.dataclass
class Changes:
    """Rows changed since the last drain: id -> new row, or `None` when deleted."""

    resources: dict[str, Resource | None]
    clients: dict[str, ClientRecord | None]

    def __bool__(self) -> bool:
        return bool(self.resources or self.clients)


class _DirtySet(dict[str, None]):
    """An insertion-ordered set of row ids (so the store can keep the rows' order)."""

    def add(self, key: str) -> None:
        self[key] = None


class _NoDirt(_DirtySet):
    """The changed rows of a catalog nobody persists: none are kept (nobody drains them)."""

    def add(self, key: str) -> None:
        pass


class UnreadRows(Protocol):
    """Served resources of a restored catalog still in its backup (see `Catalog.restore`).

    Each method returns resources not returned before, with their consumers; once
    returned, a resource lives in the catalog's memory and is never returned again.
    """

    remaining: int
    """How many resources have not been returned yet."""

    def by_request(self, server: str, digest: int) -> list[Resource]:
        """Those of `server` whose request digest is `digest`."""

    def by_consumer(self, query_id: str) -> Resource | None:
        """The one that has consumer `query_id`, if any."""

    def of_server(self, server: str) -> list[Resource]:
        """Every one of `server`, oldest first."""

    def with_origin(self, origin_rr: str) -> list[Resource]:
        """Every one with a consumer from registrar `origin_rr`."""

    def every(self) -> list[Resource]:
        """All of them, oldest first."""


class Catalog:
    """The bookkeeping of one registrar (thesis 4.3.2), without the locks.

    A restored catalog may hold only part of its resources in memory (`resources`); the
    others are read from the backup (`UnreadRows`) when a lookup first needs them, so a
    restore does not cost a read of every row. Methods that look resources up (`find`,
    `resource_of`, `has_consumer`, `resources_of`, ...) see both.
    """

    def __init__(self, *, track_changes: bool = True) -> None:
        self.track_changes = track_changes
        self.resources: dict[str, Resource] = {}
        self.clients: dict[str, ClientRecord] = {}
        self._by_consumer: dict[str, str] = {}
        # Dedup index, per server: request digest -> resource ids (most requests), and
        # in-process key (`_runtime_key`) -> resource ids for requests without a digest.
        self._index: dict[str, dict[int, list[str]]] = {}
        self._others: dict[str, dict[Any, list[str]]] = {}
        self._other_keys: dict[str, Any] = {}  # resource id -> its key in `_others`
        self._deps: dict[str, list[str]] = {}
        # ordered: new rows drain in creation order
        self._dirty_resources = _DirtySet() if track_changes else _NoDirt()
        self._dirty_clients = _DirtySet() if track_changes else _NoDirt()
        self._unread: UnreadRows | None = None  # a restored catalog's resources still on disk
        self._unsorted = False  # resources read from disk since `resources` was last ordered

    # -- served resources -------------------------------------------------------------

    def find(self, server: str, request: Any) -> Resource | None:
        """Return the resource of `server` whose request `== request`, if any."""
        found = self._find(server, request)
        if found is None and self._unread is not None:
            digest = request_digest(request)
            if digest is not None:
                self._read(self._unread.by_request(server, digest))
            elif not _identity_equality(request):  # may equal any value: read them all
                self._read(self._unread.of_server(server))
            else:
                return None  # equal only to itself: never to a value read back from disk
            found = self._find(server, request)
        return found

    def _find(self, server: str, request: Any) -> Resource | None:
        digested = self._index.get(server)
        others = self._others.get(server)
        digest = request_digest(request)
        candidates: Iterable[str]
        if digest is not None:
            candidates = digested.get(digest, ()) if digested else ()
            if others:  # a request without a digest may still be equal (rare)
                candidates = [*candidates, *_candidates(others, request)]
        else:
            candidates = _candidates(others, request) if others else []
            if digested and not _identity_equality(request):
                # A custom `__eq__` may equal a plain value: compare with every one.
                candidates = [*candidates, *(r for b in digested.values() for r in b)]
        for rid in candidates:
            resource = self.resources[rid]
            if requests_equal(resource.request, request):
                return resource
        return None

    def begin_load(self, rid: str, server: str, request: Any) -> Resource:
        """Add a resource in the `LOADING` state."""
        resource = Resource(rid, server, request)
        self._insert(resource)
        return resource

    def finish_load(self, rid: str, response: Any) -> Resource:
        """Mark a loading resource `LOADED` with its response."""
        resource = self.resources[rid]
        resource.response = response
        resource.response_version += 1
        resource.state = ResourceState.LOADED
        self._dirty_resources.add(rid)
        return resource

    def set_response(self, rid: str, response: Any) -> None:
        """Replace a resource's stored response."""
        resource = self.resources[rid]
        resource.response = response
        resource.response_version += 1
        self._dirty_resources.add(rid)

    def begin_unload(self, rid: str) -> Resource:
        """Mark a resource `UNLOADING` (its last consumer left)."""
        resource = self.resources[rid]
        resource.state = ResourceState.UNLOADING
        self._dirty_resources.add(rid)
        return resource

    def remove_resource(self, rid: str) -> Resource:
        """Delete a resource that has no consumers any more."""
        resource = self.resources.pop(rid)
        assert not resource.consumers, "a resource with consumers cannot be removed"
        key = self._other_keys.pop(rid, None)
        buckets: dict[Any, list[str]]
        if key is None:
            key, buckets = resource.digest, self._index[resource.server]
        else:
            buckets = self._others[resource.server]
        bucket = buckets[key]
        bucket.remove(rid)
        if not bucket:
            del buckets[key]
        self._dirty_resources.add(rid)
        return resource

    def add_consumer(self, rid: str, query_id: str, origin_rr: str) -> None:
        """Record one more consumer id of a resource."""
        if self.has_consumer(query_id):
            raise ValueError(f"query id {query_id} is already a consumer")
        self.resources[rid].consumers[query_id] = origin_rr
        self._by_consumer[query_id] = rid
        self._dirty_resources.add(rid)

    def release(self, query_id: str) -> Resource:
        """Remove one consumer id and return its resource.

        Raises:
            UnknownQueryError: the id is not a consumer of any resource here.
        """
        resource = self.resource_of(query_id)
        del resource.consumers[query_id]
        del self._by_consumer[query_id]
        self._dirty_resources.add(resource.id)
        return resource

    def resource_of(self, query_id: str) -> Resource:
        """Return the resource a consumer id belongs to.

        Raises:
            UnknownQueryError: the id is not a consumer of any resource here.
        """
        rid = self._by_consumer.get(query_id)
        if rid is None and self._unread is not None:
            resource = self._unread.by_consumer(query_id)
            if resource is not None:
                self._read([resource])
                rid = resource.id
        if rid is None:
            raise UnknownQueryError(f"unknown or released query id {query_id!r}")
        return self.resources[rid]

    def has_consumer(self, query_id: str) -> bool:
        """Whether `query_id` is a consumer id of one of the resources served here."""
        if query_id in self._by_consumer:
            return True
        if self._unread is not None:
            resource = self._unread.by_consumer(query_id)
            if resource is not None:
                self._read([resource])
                return True
        return False

    def queries(self, resource: Resource, serving_rr: str) -> Iterator[Query]:
        """Yield one `Query` per consumer id of `resource`."""
        for qid, origin in resource.consumers.items():
            yield Query(
                qid, resource.server, serving_rr, origin, resource.request, resource.response
            )

    def server_queries(self, server: str, serving_rr: str) -> list[Query]:
        """Every consumer query of every loaded resource of `server`."""
        if self._unread is not None:
            self._read(self._unread.of_server(server))
        return [
            query
            for index in (self._index, self._others)
            for bucket in index.get(server, {}).values()
            for rid in bucket
            for query in self.queries(self.resources[rid], serving_rr)
        ]

    def resources_of(self, server: str) -> list[Resource]:
        """Every resource of `server`, oldest first."""
        if self._unread is not None:
            self._read(self._unread.of_server(server))
        return [r for r in self._in_order().values() if r.server == server]

    def consumers_from(self, origin_rr: str) -> list[str]:
        """The consumer ids, of any resource here, that registrar `origin_rr` holds."""
        if self._unread is not None:
            self._read(self._unread.with_origin(origin_rr))
        return [
            query_id
            for resource in self.resources.values()
            for query_id, origin in resource.consumers.items()
            if origin == origin_rr
        ]

    def read_all(self) -> dict[str, Resource]:
        """Every resource (reading those still in the backup), by id, oldest first."""
        if self._unread is not None:
            self._read(self._unread.every())
        return self._in_order()

    def _in_order(self) -> dict[str, Resource]:
        """`resources`, oldest first: restored ones in their stored order, then newer ones.

        Lookups read restored resources in whatever order traffic asks for them; they are
        put back in order (a stable sort) only when an ordered listing is asked for.
        """
        if self._unsorted:
            self.resources = dict(sorted(self.resources.items(), key=_stored_order))
            self._unsorted = False
        return self.resources

    # -- client records ---------------------------------------------------------------

    def add_client(self, record: ClientRecord) -> None:
        """Record an outbound query (in flight until `client_loaded`)."""
        qid = record.query.id
        if qid in self.clients:
            raise ValueError(f"query id {qid} is already a client record")
        self.clients[qid] = record
        if record.parent is not None:
            self._deps.setdefault(record.parent, []).append(qid)
        self._dirty_clients.add(qid)

    def client_loaded(self, query_id: str, response: Any) -> ClientRecord | None:
        """Mark an outbound query answered; `None` if the record is gone."""
        record = self.clients.get(query_id)
        if record is None:
            return None
        record.query = record.query.with_response(response)
        record.loaded = True
        record.response_version += 1
        self._dirty_clients.add(query_id)
        return record

    def remove_client(self, query_id: str) -> ClientRecord:
        """Delete an outbound query record.

        Raises:
            UnknownQueryError: no such record.
        """
        record = self.clients.pop(query_id, None)
        if record is None:
            raise UnknownQueryError(f"unknown or released query id {query_id!r}")
        if record.parent is not None:
            deps = self._deps[record.parent]
            deps.remove(query_id)
            if not deps:
                del self._deps[record.parent]
        self._dirty_clients.add(query_id)
        return record

    def dependencies(self, rid: str) -> list[ClientRecord]:
        """The client records owned by resource `rid`, oldest first."""
        return [self.clients[qid] for qid in self._deps.get(rid, ())]

    # -- persistence ------------------------------------------------------------------

    def drain_changes(self) -> Changes:
        """Return and forget the rows changed since the last drain.

        Without `track_changes` (a catalog nobody persists) this is always empty, and
        nothing is kept meanwhile (a registrar without a backup never drains).
        """
        changes = Changes(
            {rid: self.resources.get(rid) for rid in self._dirty_resources},
            {qid: self.clients.get(qid) for qid in self._dirty_clients},
        )
        self._dirty_resources.clear()
        self._dirty_clients.clear()
        return changes

    @classmethod
    def restore(
        cls,
        resources: Iterable[Resource],
        clients: Iterable[ClientRecord],
        unread: UnreadRows | None = None,
    ) -> Catalog:
        """Build a catalog from stored rows (nothing is marked dirty).

        Resources whose `digest` is known are indexed without looking at their request
        (a restored request stays encoded until first used). `unread` holds the stored
        resources not given in `resources`: lookups read them when they need them.
        """
        catalog = cls(track_changes=True)
        if unread is not None and unread.remaining:
            catalog._unread = unread
        catalog.resources = {resource.id: resource for resource in resources}
        catalog._by_consumer = {
            qid: rid for rid, resource in catalog.resources.items() for qid in resource.consumers
        }
        index = catalog._index
        for rid, resource in catalog.resources.items():
            digest = resource.digest
            if digest is not None and digest != NO_DIGEST:
                server = index.get(resource.server)
                if server is None:
                    server = index[resource.server] = {}
                bucket = server.get(digest)
                if bucket is None:
                    server[digest] = [rid]
                else:
                    bucket.append(rid)
            else:
                catalog._index_request(resource)
        deps = catalog._deps
        catalog.clients = {record.query.id: record for record in clients}
        for qid, record in catalog.clients.items():
            if record.parent is not None:
                deps.setdefault(record.parent, []).append(qid)
        return catalog

    def check_invariants(self) -> None:
        """Raise `AssertionError` if the indexes disagree with the rows (for tests)."""
        self.read_all()
        by_consumer = {q: r.id for r in self.resources.values() for q in r.consumers}
        assert by_consumer == self._by_consumer, "consumer index out of sync"
        for resource in self.resources.values():
            if resource.state is ResourceState.LOADED:
                equal = [
                    r
                    for r in self.resources_of(resource.server)
                    if r.id != resource.id and requests_equal(r.request, resource.request)
                ]
                assert not equal, f"resource {resource.id} is loaded twice"
        deps: dict[str, list[str]] = {}
        for qid, record in self.clients.items():
            if record.parent is not None:
                assert record.parent in self.resources, f"dependency {qid} has no owner"
                deps.setdefault(record.parent, []).append(qid)
        assert deps == self._deps, "dependency index out of sync"

    def _read(self, resources: list[Resource]) -> None:
        """Take resources read from the backup into memory (and into the indexes)."""
        for resource in resources:
            self.resources[resource.id] = resource
            self._unsorted = True
            for query_id in resource.consumers:
                self._by_consumer[query_id] = resource.id
            self._index_request(resource)
        if self._unread is not None and not self._unread.remaining:
            self._unread = None  # everything is in memory: stop asking

    def _insert(self, resource: Resource) -> None:
        self.resources[resource.id] = resource
        self._index_request(resource)
        self._dirty_resources.add(resource.id)

    def _index_request(self, resource: Resource) -> None:
        digest = resource.digest
        if digest is None:
            digest = request_digest(resource.request)
            resource.digest = NO_DIGEST if digest is None else digest
        if digest is not None and digest != NO_DIGEST:
            index = self._index.setdefault(resource.server, {})
            index.setdefault(digest, []).append(resource.id)
        else:
            key = self._other_keys[resource.id] = _runtime_key(resource.request)
            self._others.setdefault(resource.server, {}).setdefault(key, []).append(resource.id)


def _stored_order(item: tuple[str, Resource]) -> float:
    """Sort key: a restored resource's row key in its backup; one created since is newer."""
    order: float = item[1].__dict__.get("_order", math.inf)
    return order


def _identity_equality(value: Any) -> bool:
    """Whether `value` can only equal itself (its class keeps `object.__eq__`)."""
    eq: object = type(value).__eq__
    return eq is object.__eq__


def _candidates(others: dict[Any, list[str]], request: Any) -> list[str]:
    """The resource ids among requests without a digest that may `== request`."""
    key = _runtime_key(request)
    if key == _UNHASHABLE:
        return [rid for bucket in others.values() for rid in bucket]
    # Equal hashable values have equal hashes; unhashable stored ones are compared anyway.
    return [*others.get(key, ()), *others.get(_UNHASHABLE, ())]
