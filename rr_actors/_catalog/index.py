"""The request index: which resources of a server may serve a request, by digest.

```
 Catalog.begin_load, a row read in, restore
   ──► add(resource, key) ─┬─► digested: server -> digest -> ids
                           └─► others: server -> runtime key -> ids
 Catalog.lookup(server, request, digest, key)
   ──► with_digest(server, digest): ids whose plain request may be equal (compared there)
   ──► undecided(server, request, digest, key): ids only a `==` can judge
 Catalog.remove_resource ──► remove(resource)
```

Most requests have a digest (`digest.request_digest`): equal plain values have equal
digests, so one bucket holds every candidate. A request without one (a custom class, a
value holding one) is indexed by its `runtime_key`, which runs its `__hash__`: the
caller computes it off the actor thread and passes it in; a request read back from the
backup goes with the unhashable ones, so no code of its class runs to index it.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from typing import Any

from rr_actors._catalog.digest import (
    NO_DIGEST,
    UNHASHABLE,
    candidates_without_digest,
    identity_equality,
    request_digest,
    runtime_key,
)
from rr_actors._catalog.records import Resource

__all__ = ["RequestIndex"]


class RequestIndex:
    """The resource ids of each server, by request digest or by in-process key.

    It holds ids only; the resources are the `Catalog`'s. It writes one field of a
    resource: its `digest`, computed once when a resource new here is indexed.
    """

    def __init__(self) -> None:
        # per server: request digest -> resource ids (most requests), and in-process
        # key (`runtime_key`) -> resource ids for requests without a digest
        self._digested: dict[str, dict[int, list[str]]] = {}
        self._others: dict[str, dict[Any, list[str]]] = {}
        self._other_keys: dict[str, Any] = {}  # resource id -> its key in `_others`

    def add(self, resource: Resource, key: Any = None) -> None:
        """Index a resource new here (`key`: see `Catalog.begin_load`) or read back (no key).

        A request read back from the backup without a digest is indexed with the
        unhashable ones rather than by its `hash()`: no code of its class runs for that.
        """
        digest = resource.digest
        if digest is None:
            digest = request_digest(resource.request)
            resource.digest = NO_DIGEST if digest is None else digest
            if key is None and digest is None:
                key = runtime_key(resource.request)
        if digest is not None and digest != NO_DIGEST:
            index = self._digested.setdefault(resource.server, {})
            index.setdefault(digest, []).append(resource.id)
        else:
            key = self._other_keys[resource.id] = UNHASHABLE if key is None else key
            self._others.setdefault(resource.server, {}).setdefault(key, []).append(resource.id)

    def restore(self, resources: Iterable[Resource]) -> None:
        """Index stored resources; those whose digest is known without looking at their
        request (a restored request stays encoded until first used)."""
        index = self._digested
        for resource in resources:
            digest = resource.digest
            if digest is not None and digest != NO_DIGEST:
                server = index.get(resource.server)
                if server is None:
                    server = index[resource.server] = {}
                bucket = server.get(digest)
                if bucket is None:
                    server[digest] = [resource.id]
                else:
                    bucket.append(resource.id)
            else:
                self.add(resource)

    def remove(self, resource: Resource) -> None:
        """Take a resource out of the index."""
        key = self._other_keys.pop(resource.id, None)
        buckets: dict[Any, list[str]]
        if key is None:
            key, buckets = resource.digest, self._digested[resource.server]
        else:
            buckets = self._others[resource.server]
        bucket = buckets[key]
        bucket.remove(resource.id)
        if not bucket:
            del buckets[key]

    def with_digest(self, server: str, digest: int) -> Sequence[str]:
        """The ids of `server`'s resources whose request digest is `digest`."""
        digested = self._digested.get(server)
        return digested.get(digest, ()) if digested else ()

    def undecided(self, server: str, request: Any, digest: int | None, key: Any) -> list[str]:
        """The ids of `server`'s resources whose requests only a `==` can compare with
        `request` (one of user code, or a plain value against a custom `__eq__`);
        `digest`: the request's (`None`: it has none), `key`: else its `runtime_key`."""
        others = self._others.get(server)
        if digest is not None:
            # A stored request without a digest may still be equal (rare). A plain
            # request's `runtime_key` is a built-in `hash()` (or none): no user code.
            return candidates_without_digest(others, runtime_key(request)) if others else []
        undecided = candidates_without_digest(others, key) if others else []
        digested = self._digested.get(server)
        if digested and not identity_equality(request):
            # A custom `__eq__` may equal a plain value: compare with every one.
            undecided += [rid for bucket in digested.values() for rid in bucket]
        return undecided

    def ids_of(self, server: str) -> Iterator[str]:
        """The ids of every resource of `server`: those with a digest first."""
        for index in (self._digested, self._others):
            for bucket in index.get(server, {}).values():
                yield from bucket
