"""The provider side of a registrar actor, tearing down: a resource's unload, run once (rule 7).

```
 last consumer released (unloading.py), a server closed (servers.py), a load that failed
 or that nobody waits for any more (provider.py), a restored resource in doubt:
   unload_resource ──► the resource's dependencies (releases.py) ──► RunUnload ──► server
       ──► remove_resource: written at once with its ResourceUnloaded (one transaction),
           then published ──► `when_gone` (loads parked behind the unload, `Provider`),
           then the callers waiting for it
```

Callers that wait for an unload, unloads parked until their server is registered again,
and what runs once a resource is gone are this role's state; the loads themselves are
`provider.py`'s, releasing consumer ids `unloading.py`'s.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rr_actors import events
from rr_actors._catalog import Resource, describe
from rr_actors._core.directory import Reply
from rr_actors._registrar.messages import RunUnload
from rr_actors._registrar.state import Shared
from rr_actors.errors import CallTimeoutError, RrError

if TYPE_CHECKING:
    from rr_actors._registrar.releases import Releases

__all__ = ["Teardown"]

logger = logging.getLogger("rr_actors")


class Teardown:
    """Unloads this registrar's resources and forgets them once they are gone.

    Attributes:
        unload_waiters: resource id -> replies waiting for its unload to finish.
        parked_unloads: server name -> unloads of restored resources waiting for the
            server to be registered again.
        gone: resource id -> what runs once it is gone (`when_gone`).
        under_way: resource id -> resource, of the unloads under way: their dependencies
            being released or their `unload` callback running (not those parked).
        idle: what runs once no unload is under way (`when_idle`).
    """

    def __init__(self, shared: Shared, releases: Releases) -> None:
        self.registrar = shared
        self.releases = releases
        self.unload_waiters: dict[str, list[Reply]] = {}
        self.parked_unloads: dict[str, list[Callable[[], None]]] = {}
        self.gone: dict[str, list[Callable[[], None]]] = {}
        self.under_way: dict[str, Resource] = {}
        self.idle: list[Callable[[], None]] = []

    def unload_resource(self, resource: Resource, reply: Reply | None) -> None:
        """The last consumer left: release the dependencies, then run `unload` (rule 7)."""
        self.registrar.probe("unload_resource", resource)
        self.registrar.catalog.begin_unload(resource.id)
        self.registrar.commit()
        self.unload_waiters[resource.id] = [] if reply is None else [reply]
        self.under_way[resource.id] = resource

        def run_unload() -> None:
            self.under_way[resource.id] = resource
            server = self.registrar.servers.get(resource.server)
            if server is None and self.registrar.servers_settled:  # setup did not bring it back
                unloaded(None, None)
                return
            if server is None:  # restored, and no one has registered the server yet
                del self.under_way[resource.id]
                self.parked_unloads.setdefault(resource.server, []).append(run_unload)
                self.check_idle()
                return
            done = self.registrar.come_back(unloaded)
            timeout = self.registrar.config.unload_timeout
            server.ref.tell(RunUnload(resource.request, resource.response, done, timeout))

        def unloaded(_: Any, error: BaseException | None) -> None:
            overdue = isinstance(error, CallTimeoutError)
            if overdue:  # it hangs: the resource is dropped as failed, its callers told
                logger.error(
                    "registrar %s: %s; resource %s (request %s) is dropped as failed, and "
                    "whatever it still holds is the server's to clean up",
                    self.registrar.name,
                    error,
                    resource.id,
                    describe(resource.request),
                )
            elif error is not None:
                logger.error(
                    "unload callback of '%s/%s' raised; the resource is released anyway",
                    self.registrar.name,
                    resource.server,
                    exc_info=error,
                )
            self.remove_resource(resource, unloaded=True)
            for waiting in self.unload_waiters.pop(resource.id):
                if overdue:
                    waiting.set_error(error)  # type: ignore[arg-type]
                else:
                    waiting.set_result(None)
            self.under_way.pop(resource.id, None)
            self.check_idle()

        self.releases.release_dependencies(resource.id, run_unload)

    def when_idle(self, then: Callable[[], None]) -> None:
        """Run `then()` once no unload is under way here (now if none is)."""
        self.idle.append(then)
        self.check_idle()

    def check_idle(self) -> None:
        """Run what waits for no unload to be under way, if none is."""
        while not self.under_way and self.idle:
            self.idle.pop(0)()

    def remove_resource(self, resource: Resource, *, unloaded: bool = False) -> None:
        """Forget a resource that is gone (unloaded, or its load failed); serve the loads
        parked behind its unload.

        An unload (`unloaded`) is written at once, also without `save_on_modify` (a
        crash before the next flush would restore the resource, and reconciling with
        its consumers would run its `unload` a second time), with its
        `ResourceUnloaded` in the same transaction, published before anyone hears of it.
        """
        shared = self.registrar
        shared.catalog.remove_resource(resource.id)
        told = (
            (events.ResourceUnloaded(shared.name, resource.server, resource.id),)
            if unloaded and shared.events.active
            else ()
        )
        if shared.commit(*told, now=unloaded) is not None:  # pending: the next write tries
            shared.publish(*told)  # (it was unloaded all the same)
        for then in self.gone.pop(resource.id, ()):  # e.g. loads parked behind its unload
            then()
        server = self.registrar.servers.get(resource.server)
        if (
            server is not None
            and server.closing
            and not self.registrar.catalog.resources_of(server.name)
        ):
            del self.registrar.servers[server.name]
            server.ref.stop(block=False)

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
            if server not in self.registrar.servers:  # setup did not bring it back: release anyway
                logger.warning(
                    "registrar %s: server %r was not registered by setup; its restored "
                    "resources are released without their unload callback",
                    self.registrar.name,
                    server,
                )
                del self.parked_unloads[server]
                for run_unload in unloads:
                    run_unload()

    def when_gone(self, rid: str, then: Callable[[], None]) -> None:
        """Run `then()` once resource `rid` (unloading) is gone (`remove_resource`)."""
        self.gone.setdefault(rid, []).append(then)

    def fail_waiting(self, error: RrError) -> None:
        """Answer every caller waiting on an unload here with `error`."""
        for replies in self.unload_waiters.values():
            for reply in replies:
                reply.set_error(error)
