"""What a catalog holds, as the rows of a `CatalogRestored` or `RegistrarStopped` event.

Built only when someone listens (`events.active`); listing a restored catalog reads the
rows still in its backup as strings (their ids, servers and consumers, not their values),
up to `LISTED_ROWS` of each kind; above that it counts them.
"""

from __future__ import annotations

import hashlib
from typing import TYPE_CHECKING

from rr_actors import events
from rr_actors.events.kinds import LISTED_ROWS, Rows

if TYPE_CHECKING:
    from rr_actors._registrar.state import Shared

__all__ = ["publish_restored", "publish_stopped"]


def _fields(shared: Shared) -> dict[str, object]:
    """The rows, counts and digest of a catalog event (see `CatalogRestored`).

    Up to `LISTED_ROWS` rows of each kind are listed, read from the backup as plain
    strings (no resource is read into memory for it); above that only the counts are
    given, and no digest: it would cost a read of every row, which is what a restore
    no longer does before it serves (issue 34).
    """
    catalog = shared.catalog
    clients = tuple(
        (qid, record.query.serving_rr, record.query.server, record.parent or "")
        for qid, record in catalog.clients.items()
    )
    rows = catalog.rows(LISTED_ROWS)
    if rows is None or len(clients) > LISTED_ROWS:
        return {
            "resources": (),
            "consumers": (),
            "clients": (),
            "counts": (*catalog.counts(), len(clients)),
            "complete": False,
            "digest": "",
        }
    kinds: tuple[Rows, Rows, Rows] = (tuple(rows[0]), tuple(rows[1]), clients)
    digest = hashlib.sha256()
    for listed in kinds:
        for row in sorted(listed):
            digest.update("\x1f".join(row).encode())
            digest.update(b"\x1e")
        digest.update(b"\x1d")
    return {
        "resources": kinds[0],
        "consumers": kinds[1],
        "clients": kinds[2],
        "counts": tuple(len(listed) for listed in kinds),
        "complete": True,
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
