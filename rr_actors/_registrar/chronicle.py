"""What a catalog holds, as the rows of a `CatalogRestored` or `RegistrarStopped` event.

Built only when someone listens (`events.active`); listing a restored catalog reads the
rows still in its backup (their ids, servers and consumers, not their values).
"""

from __future__ import annotations

import hashlib
from typing import TYPE_CHECKING

from rr_actors import events
from rr_actors._catalog import NO_DIGEST
from rr_actors.events.kinds import LISTED_ROWS, Rows

if TYPE_CHECKING:
    from rr_actors._registrar.state import Shared

__all__ = ["publish_restored", "publish_stopped"]


def _rows(shared: Shared) -> tuple[Rows, Rows, Rows]:
    catalog = shared.catalog
    resources: list[tuple[str, ...]] = []
    consumers: list[tuple[str, ...]] = []
    for resource in catalog.read_all().values():
        digest = resource.digest
        plain = digest is not None and digest != NO_DIGEST
        resources.append((resource.id, resource.server, resource.state.value, str(digest) * plain))
        consumers.extend((qid, resource.id, origin) for qid, origin in resource.consumers.items())
    clients = [
        (qid, record.query.serving_rr, record.query.server, record.parent or "")
        for qid, record in catalog.clients.items()
    ]
    return tuple(resources), tuple(consumers), tuple(clients)


def _fields(shared: Shared) -> dict[str, object]:
    resources, consumers, clients = _rows(shared)
    kinds = (resources, consumers, clients)
    digest = hashlib.sha256()
    for rows in kinds:
        for row in sorted(rows):
            digest.update("\x1f".join(row).encode())
            digest.update(b"\x1e")
        digest.update(b"\x1d")
    complete = all(len(rows) <= LISTED_ROWS for rows in kinds)
    return {
        "resources": resources if complete else (),
        "consumers": consumers if complete else (),
        "clients": clients if complete else (),
        "counts": tuple(len(rows) for rows in kinds),
        "complete": complete,
        "digest": digest.hexdigest()[:16],
    }


def publish_restored(shared: Shared) -> None:
    """Publish `CatalogRestored` (a registrar with a backup starts; its actor thread)."""
    if shared.events.active and shared.saver.store is not None:
        shared.events.publish(events.CatalogRestored(shared.name, **_fields(shared)))  # type: ignore[arg-type]


def publish_stopped(shared: Shared) -> None:
    """Publish `RegistrarStopped` (a clean stop gave back what it held; its actor thread)."""
    if shared.events.active:
        shared.events.publish(events.RegistrarStopped(shared.name, **_fields(shared)))  # type: ignore[arg-type]
