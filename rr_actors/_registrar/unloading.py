"""The provider side of a registrar actor, releasing: consumer ids given back, reconciling.

```
 Unload/Abandon ──► release ── load under way? ──► Provider.give_up
                                     └── last consumer? ──► Teardown.unload_resource
 after a restart: ReconcileAsk ──► consumers ──► Reconcile ──► on_reconcile: the ids a
      consumer no longer holds are released; those it holds and this one lost, named
```

Rules 7-8 (a consumer id is released once; the resource is unloaded when its last one
is, by the teardown role) and the reconcile after a restart
(`docs/explanation/failure-semantics.md`). This role holds no state of its own: what it
changes is the catalog's consumers, and the provider's loads through its methods.
"""

from __future__ import annotations

import contextlib
import logging
from typing import TYPE_CHECKING

from rr_actors import events
from rr_actors._catalog import ResourceState
from rr_actors._core.directory import DIRECTORY, Reply
from rr_actors._registrar.messages import (
    Abandon,
    Reconcile,
    ReconcileAsk,
    Unload,
)
from rr_actors._registrar.state import Shared
from rr_actors.errors import RegistrarStoppedError, RrError, UnknownQueryError

if TYPE_CHECKING:
    from rr_actors._registrar.provider import Provider
    from rr_actors._registrar.teardown import Teardown

__all__ = ["Unloading"]

logger = logging.getLogger("rr_actors")


class Unloading:
    """Releases consumer ids; a resource nobody holds any more is unloaded (`Teardown`)."""

    def __init__(self, shared: Shared, provider: Provider, teardown: Teardown) -> None:
        self.registrar = shared
        self.provider = provider
        self.teardown = teardown

    def on_unload(self, message: Unload, reply: Reply) -> None:
        self.release(message.query_id, reply, "unload")

    def on_abandon(self, message: Abandon, _reply: Reply) -> None:
        self.release(message.query_id, None, "abandoned")

    def release_all_of(self, origin_rr: str) -> None:
        """Consumer `origin_rr` is gone for good (`presence.py`: the death watch, or a
        carrier's `peer_lost`): release every id it held here (each `unload` runs once;
        a second call finds none), and give up its loads under way here (each is
        unloaded once it ends: an answer to a lost consumer may be dropped unseen, as
        over Zenoh before its token goes, so that answer failing is not counted on)."""
        for query_id in self.provider.under_way_of(origin_rr):
            self.provider.give_up(query_id)
        for query_id in self.registrar.catalog.consumers_from(origin_rr):
            if self.registrar.catalog.has_consumer(query_id):  # (a release may have cascaded)
                self.release(query_id, None, "death watch")

    def release(self, query_id: str, reply: Reply | None, reason: str) -> None:
        """Release consumer id `query_id` (rules 7-8); answer `reply` when it is done.

        `reason` is what the `ConsumerReleased` event says (see its `reason`).

        While a durable registrar's backup cannot be written an `Unload` is refused
        (nothing changes; the consumer keeps the id and may try again); a give-up
        (`reply` is `None`) is carried out and written with the next write that succeeds.
        """
        unwritable = self.registrar.unwritable() if reply is not None else None
        if unwritable is not None:
            reply.set_error(unwritable)  # type: ignore[union-attr]
            return
        if self.provider.give_up(query_id):  # its load had not finished: it never holds it
            if reply is not None:
                reply.set_result(None)
            return
        catalog = self.registrar.catalog
        try:
            resource = catalog.resource_of(query_id)
        except UnknownQueryError as exc:
            if reply is not None:
                reply.set_error(exc)
            return
        origin = resource.consumers[query_id]
        catalog.release(query_id)
        shared = self.registrar
        told = (
            (events.ConsumerReleased(shared.name, resource.id, query_id, origin, reason),)
            if shared.events.active
            else ()
        )
        failed = shared.commit(*told)  # (written with it)
        if failed is not None and reply is not None:  # not durable: nothing changes
            catalog.add_consumer(resource.id, query_id, origin)
            shared.commit()
            reply.set_error(failed)
            return
        if failed is not None:  # a give-up: carried out, written with the next write
            shared.publish(*told)
        if resource.consumers or resource.state is not ResourceState.LOADED:
            if reply is not None:
                reply.set_result(None)
            return
        self.teardown.unload_resource(resource, reply)

    def ask_to_reconcile(self, swept: set[str]) -> None:
        """This registrar serves (again): ask every registrar holding ids here to
        `Reconcile` (one that cannot be reached reconciles at its own start); release
        the ids of one that was stopped for good meanwhile; and, with a backup (which
        may have lost ids: a save interval, a truncated WAL), tell every other
        registrar of the system, which may hold ids this one lost (rule 20). `swept`:
        the registrars holding ids in the restored rows still in the backup."""
        origins = self.registrar.catalog.consumer_origins() | swept
        for origin in sorted(origins):
            try:
                DIRECTORY.lookup(origin).tell(ReconcileAsk(self.registrar.name))
            except RegistrarStoppedError:
                self.release_stopped(origin)
            except RrError:
                pass
        if self.registrar.saver.store is not None:
            self.ask_everyone(set(origins))

    def ask_everyone(self, asked: set[str]) -> None:
        """Tell every registrar of the system not in `asked` that this one (re)started:
        those that hold ids here reconcile (the ids this one lost are reported `FATAL`)."""
        for name in sorted(DIRECTORY.names() - asked - {self.registrar.name}):
            with contextlib.suppress(RrError):
                DIRECTORY.lookup(name).tell(ReconcileAsk(self.registrar.name, holds_yours=False))

    def release_stopped(self, origin: str) -> None:
        """Consumer `origin` was stopped for good while this registrar was down: it holds
        nothing (rule 12), so every id of it here is released (each `unload` runs once)."""
        ids = self.registrar.catalog.consumers_from(origin)
        if ids:
            logger.warning(
                "registrar %s: consumer %s was stopped while this registrar was down; "
                "releasing the %d ids it held here",
                self.registrar.name,
                origin,
                len(ids),
            )
        for query_id in ids:
            if self.registrar.catalog.has_consumer(query_id):  # (a release may have cascaded)
                self.release(query_id, None, "consumer stopped")

    def on_reconcile(self, message: Reconcile, reply: Reply) -> None:
        """Release the ids of `origin_rr` it no longer holds; name those held here unknown.

        An id whose load is still under way here (waiting, parked, matched) is neither.
        """
        catalog = self.registrar.catalog
        held = set(message.held)
        mine = catalog.consumer_ids_from(message.origin_rr)
        stale = sorted(mine - held)
        if stale:
            logger.warning(
                "registrar %s: %s no longer holds %d of its ids here (released while this "
                "registrar was down, or lost in its own restart): releasing them",
                self.registrar.name,
                message.origin_rr,
                len(stale),
            )
        for query_id in stale:
            if catalog.has_consumer(query_id):  # (still: a release above may have cascaded)
                self.release(query_id, None, "reconcile")
        under_way = self.provider.under_way()
        unknown = tuple(q for q in message.held if q not in mine and q not in under_way)
        reply.set_result(unknown)
