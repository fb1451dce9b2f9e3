"""The provider side of a registrar actor, unloading: releases, unloads, reconciling.

```
 Unload/Abandon/ConsumerDown ──► release ── last consumer? ──► unload_resource:
      release the resource's dependencies (consumer side), then RunUnload ──► server
      ──► remove_resource ──► the loads parked behind it are served (provider.py)
 after a restart: ReconcileAsk ──► consumers ──► Reconcile ──► on_reconcile: the ids a
      consumer no longer holds are released; those it holds and this one lost, named
```

Rules 7-8 (an unload runs when the last consumer id is released, after the resource's
dependencies), rule 12 (`unregister_server` unloads through here) and the reconcile
after a restart (`docs/explanation/failure-semantics.md`).
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rr_actors import events
from rr_actors._catalog import Resource, ResourceState, describe
from rr_actors._core.directory import DIRECTORY, Reply
from rr_actors._registrar.messages import (
    Abandon,
    ConsumerDown,
    Reconcile,
    ReconcileAsk,
    RunUnload,
    Unload,
)
from rr_actors._registrar.state import Shared
from rr_actors.errors import (
    CallTimeoutError,
    CatalogWriteError,
    RegistrarStoppedError,
    RrError,
    UnknownQueryError,
)

if TYPE_CHECKING:
    from rr_actors._registrar.consumer import Consumer
    from rr_actors._registrar.provider import Provider

__all__ = ["Unloading"]

logger = logging.getLogger("rr_actors")


class Unloading:
    """Releases consumer ids and unloads resources nobody holds any more.

    Attributes:
        unload_waiters: resource id -> replies waiting for its unload to finish.
        parked_unloads: server name -> unloads of restored resources waiting for the
            server to be registered again.
    """

    def __init__(self, shared: Shared, provider: Provider, consumer: Consumer) -> None:
        self.s = shared
        self.provider = provider
        self.consumer = consumer
        self.unload_waiters: dict[str, list[Reply]] = {}
        self.parked_unloads: dict[str, list[Callable[[], None]]] = {}

    def on_unload(self, message: Unload) -> None:
        self.release(message.query_id, message.reply)

    def on_abandon(self, message: Abandon) -> None:
        self.release(message.query_id, None)

    def on_consumer_down(self, message: ConsumerDown) -> None:
        for query_id in self.s.catalog.consumers_from(message.origin_rr):
            self.release(query_id, None)

    def release(self, query_id: str, reply: Reply | None) -> None:
        """Release consumer id `query_id` (rules 7-8); answer `reply` when it is done.

        While a durable registrar's backup cannot be written an `Unload` is refused
        (nothing changes; the consumer keeps the id and may try again); a give-up
        (`reply` is `None`) is carried out and written with the next write that succeeds.
        """
        unwritable = self.s.unwritable() if reply is not None else None
        if unwritable is not None:
            reply.set_error(unwritable)  # type: ignore[union-attr]
            return
        parked = self.provider.unpark(query_id)
        if parked is not None:  # it waited behind an unload or for setup: it never loads
            parked.reply.set_error(CallTimeoutError(f"call {query_id} was given up"))
        # (or user code compares its request now: it is answered as given up when done)
        if parked is not None or self.provider.matching.give_up(query_id):
            if reply is not None:
                reply.set_result(None)
            return
        if query_id in self.provider.loading_ids:  # its caller gave up while it loads
            self.provider.abandoned.add(query_id)
            if reply is not None:
                reply.set_result(None)
            return
        catalog = self.s.catalog
        try:
            resource = catalog.resource_of(query_id)
        except UnknownQueryError as exc:
            if reply is not None:
                reply.set_error(exc)
            return
        origin = resource.consumers[query_id]
        catalog.release(query_id)
        failed = self.s.commit()
        if failed is not None and reply is not None:  # not durable: nothing changes
            catalog.add_consumer(resource.id, query_id, origin)
            self.s.commit()
            reply.set_error(failed)
            return
        if self.s.events.active:
            self.s.events.publish(
                events.ConsumerReleased(self.s.name, resource.id, query_id, origin)
            )
        if resource.consumers or resource.state is not ResourceState.LOADED:
            if reply is not None:
                reply.set_result(None)
            return
        self.unload_resource(resource, reply)

    def unload_resource(self, resource: Resource, reply: Reply | None) -> None:
        """The last consumer left: release the dependencies, then run `unload` (rule 7)."""
        self.s.probe("unload_resource", resource)
        self.s.catalog.begin_unload(resource.id)
        self.s.commit()
        self.unload_waiters[resource.id] = [] if reply is None else [reply]

        def run_unload() -> None:
            server = self.s.servers.get(resource.server)
            if server is None and self.s.servers_settled:  # setup did not bring it back
                unloaded(None, None)
                return
            if server is None:  # restored, and no one has registered the server yet
                self.parked_unloads.setdefault(resource.server, []).append(run_unload)
                return
            done = self.s.come_back(unloaded)
            timeout = self.s.config.unload_timeout
            server.ref.tell(RunUnload(resource.request, resource.response, done, timeout))

        def unloaded(_: Any, error: BaseException | None) -> None:
            overdue = isinstance(error, CallTimeoutError)
            if overdue:  # it hangs: the resource is dropped as failed, its callers told
                logger.error(
                    "registrar %s: %s; resource %s (request %s) is dropped as failed, and "
                    "whatever it still holds is the server's to clean up",
                    self.s.name,
                    error,
                    resource.id,
                    describe(resource.request),
                )
            elif error is not None:
                logger.error(
                    "unload callback of '%s/%s' raised; the resource is released anyway",
                    self.s.name,
                    resource.server,
                    exc_info=error,
                )
            self.remove_resource(resource)
            self.record_unloaded()
            if self.s.events.active:
                self.s.events.publish(
                    events.ResourceUnloaded(self.s.name, resource.server, resource.id)
                )
            for waiting in self.unload_waiters.pop(resource.id):
                if overdue:
                    waiting.set_error(error)  # type: ignore[arg-type]
                else:
                    waiting.set_result(None)

        self.consumer.release_dependencies(resource.id, run_unload)

    def record_unloaded(self) -> None:
        """An `unload` ran: write it before anyone hears of it, also without
        `save_on_modify` (a crash before the next flush would restore the resource, and
        reconciling with its consumers would run its `unload` a second time)."""
        saver = self.s.saver
        if saver.store is None or saver.durable or not saver.pending:
            return
        try:
            saver.flush()
        except CatalogWriteError as exc:  # pending: the next flush tries again
            logger.warning("registrar %s: writing an unload failed: %s", self.s.name, exc)

    def remove_resource(self, resource: Resource) -> None:
        """Forget a resource that is gone; serve the loads parked behind its unload."""
        self.s.catalog.remove_resource(resource.id)
        self.s.commit()
        self.provider.after_unloaded(resource.id)
        server = self.s.servers.get(resource.server)
        if server is not None and server.closing and not self.s.catalog.resources_of(server.name):
            del self.s.servers[server.name]
            server.ref.stop(block=False)

    def ask_to_reconcile(self) -> None:
        """This registrar serves (again): ask every registrar holding ids here to
        `Reconcile` (one that cannot be reached reconciles at its own start); release
        the ids of one that was stopped for good meanwhile; and, with a backup (which
        may have lost ids: a save interval, a truncated WAL), tell every other
        registrar of the system, which may hold ids this one lost (rule 20)."""
        origins = self.s.catalog.consumer_origins()
        for origin in sorted(origins):
            try:
                DIRECTORY.lookup(origin).tell(ReconcileAsk(self.s.name))
            except RegistrarStoppedError:
                self.release_stopped(origin)
            except RrError:
                pass
        if self.s.saver.store is not None:
            self.ask_everyone(set(origins))

    def ask_everyone(self, asked: set[str]) -> None:
        """Tell every registrar of the system not in `asked` that this one (re)started:
        those that hold ids here reconcile (the ids this one lost are reported `FATAL`)."""
        for name in sorted(DIRECTORY.names() - asked - {self.s.name}):
            with contextlib.suppress(RrError):
                DIRECTORY.lookup(name).tell(ReconcileAsk(self.s.name, holds_yours=False))

    def release_stopped(self, origin: str) -> None:
        """Consumer `origin` was stopped for good while this registrar was down: it holds
        nothing (rule 12), so every id of it here is released (each `unload` runs once)."""
        ids = self.s.catalog.consumers_from(origin)
        if ids:
            logger.warning(
                "registrar %s: consumer %s was stopped while this registrar was down; "
                "releasing the %d ids it held here",
                self.s.name,
                origin,
                len(ids),
            )
        for query_id in ids:
            if self.s.catalog.has_consumer(query_id):  # (a release may have cascaded)
                self.release(query_id, None)

    def on_reconcile(self, message: Reconcile) -> None:
        """Release the ids of `origin_rr` it no longer holds; name those held here unknown.

        An id whose load is still under way here (waiting, parked, matched) is neither.
        """
        catalog = self.s.catalog
        held = set(message.held)
        mine = catalog.consumer_ids_from(message.origin_rr)
        stale = sorted(mine - held)
        if stale:
            logger.warning(
                "registrar %s: %s no longer holds %d of its ids here (released while this "
                "registrar was down, or lost in its own restart): releasing them",
                self.s.name,
                message.origin_rr,
                len(stale),
            )
        for query_id in stale:
            if catalog.has_consumer(query_id):  # (still: a release above may have cascaded)
                self.release(query_id, None)
        under_way = self.provider.under_way()
        unknown = tuple(q for q in message.held if q not in mine and q not in under_way)
        message.reply.set_result(unknown)

    def wait_for_unload(self, resource: Resource, reply: Reply) -> None:
        """Answer `reply` once `resource`'s unload is done (at once if it is not unloading)."""
        if resource.id in self.unload_waiters:
            self.unload_waiters[resource.id].append(reply)
        else:
            reply.set_result(None)

    def run_parked(self, server: str) -> None:
        """Server `server` was registered: run the unloads of its restored resources."""
        for run_unload in self.parked_unloads.pop(server, ()):
            run_unload()

    def settle_parked(self) -> None:
        """Setup is done: release restored resources of servers it did not bring back."""
        for server, unloads in list(self.parked_unloads.items()):
            if server not in self.s.servers:  # setup did not bring it back: release anyway
                logger.warning(
                    "registrar %s: server %r was not registered by setup; its restored "
                    "resources are released without their unload callback",
                    self.s.name,
                    server,
                )
                del self.parked_unloads[server]
                for run_unload in unloads:
                    run_unload()

    def fail_waiting(self, error: RrError) -> None:
        """Answer every caller waiting on an unload here with `error`."""
        for replies in self.unload_waiters.values():
            for reply in replies:
                reply.set_error(error)
