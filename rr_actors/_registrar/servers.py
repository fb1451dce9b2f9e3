"""A registrar's resource servers: register, unregister (rule 12), fetch, update responses.

`unregister_server` sends `FATAL` to every consumer of the server's resources, revokes
their ids and unloads the resources (through `teardown.py`); `fetch_queries` asked of
this registrar lists what a consumer holds at one of its servers (rule 10);
`update_response` replaces a stored response and tells every consumer (rule 11).
`give_up_all` closes every server of a registrar that yields its name (rule 22): its
consumers' ids are released without a word (they reconcile with the registrar kept,
which reports `FATAL` the ids it does not hold), and every resource is unloaded.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import uuid
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rr_actors import events
from rr_actors._catalog import Resource, ResourceState
from rr_actors._core.directory import DIRECTORY, Reply
from rr_actors._core.replies import Join
from rr_actors._registrar.display import show_response
from rr_actors._registrar.endpoints import ServerActor
from rr_actors._registrar.messages import (
    Fetch,
    ListServerQueries,
    RegisterServer,
    ResponseUpdated,
    Revoke,
    UnregisterServer,
    UpdateResponse,
)
from rr_actors._registrar.state import Server, Shared, consumers_by_origin
from rr_actors._types import Status, StatusUpdate
from rr_actors.errors import (
    ConfigError,
    DuplicateNameError,
    RrError,
    UnknownServerError,
    _known_names,
)

if TYPE_CHECKING:
    from rr_actors._registrar.status import StatusRelay
    from rr_actors._registrar.teardown import Teardown

__all__ = ["Servers"]

logger = logging.getLogger("rr_actors")


def _log_failure(
    what: str,
    then: Callable[[], None],
    refused: list[ConfigError],
    _: Any,
    error: BaseException | None,
) -> None:
    """A continuation that logs a failed answer, then runs `then()`; a message that could
    not be sent at all (a `ConfigError`: too large for its receiver) is added to `refused`,
    for its caller to hear of (a consumer gone is only logged)."""
    if error is not None:
        logger.warning("%s failed: %s", what, error)
        if isinstance(error, ConfigError):
            refused.append(error)
    then()


class Servers:
    """The resource servers of one registrar, and what is done to a whole server."""

    def __init__(self, shared: Shared, teardown: Teardown, status: StatusRelay) -> None:
        self.registrar = shared
        self.teardown = teardown
        self.status = status

    def on_fetch(self, message: Fetch, reply: Reply) -> None:
        if message.server not in self.registrar.servers:
            reply.set_error(
                UnknownServerError(
                    f"no resource server '{self.registrar.name}/{message.server}'"
                    + _known_names(
                        message.server,
                        (n for n, s in self.registrar.servers.items() if not s.closing),
                    )
                )
            )
            return
        reply.set_result(
            [
                query
                for query in self.registrar.catalog.server_queries(
                    message.server, self.registrar.name
                )
                if query.origin_rr == message.origin_rr
            ]
        )

    def server(self, name: str) -> Server:
        """The open server `name`.

        Raises:
            UnknownServerError: there is none (or it is closing).
        """
        server = self.registrar.servers.get(name)
        if server is None or server.closing:
            raise UnknownServerError(
                f"no resource server '{self.registrar.name}/{name}'"
                + _known_names(
                    name, (n for n, s in self.registrar.servers.items() if not s.closing)
                )
            )
        return server

    def on_register_server(self, message: RegisterServer, reply: Reply) -> None:
        name = message.name
        if name in self.registrar.servers:
            raise DuplicateNameError(
                f"resource server '{self.registrar.name}/{name}' already exists"
            )
        ref = ServerActor.start(
            self.registrar.name,
            name,
            message.load,
            message.unload,
            self.registrar.workers,
            persisted=self.registrar.saver.store is not None,
        )
        self.registrar.servers[name] = Server(name, ref, message.on_status, label=message.label)
        self.teardown.run_parked(name)
        reply.set_result(None)

    def on_unregister_server(self, message: UnregisterServer, reply: Reply) -> None:
        name = message.name
        server = self.server(name)
        server.closing = True
        resources = [
            r for r in self.registrar.catalog.resources_of(name) if r.state is ResourceState.LOADED
        ]

        def finish() -> None:
            if not self.registrar.catalog.resources_of(name) and name in self.registrar.servers:
                del self.registrar.servers[name]
                server.ref.stop(block=False)
            reply.set_result(None)

        join = Join(finish)
        for resource in resources:
            self.close_resource(resource, join.add())
        join.seal()

    def give_up_all(self, then: Callable[[], None]) -> None:
        """This registrar yields its name (rule 22): close every server, release every
        consumer id of its resources without telling the consumer (each reconciles with
        the registrar that keeps the name, rule 20), unload each resource, then `then()`.

        Unloads under way are waited for, and so are loads under way: each finishes on a
        closed server, so its callers get an error and it is unloaded (`provider.py`).
        """
        join = Join(then)
        for server in list(self.registrar.servers.values()):
            server.closing = True
            for resource in list(self.registrar.catalog.resources_of(server.name)):
                if resource.state is ResourceState.LOADED:
                    self.give_up(resource, join.add())
                elif resource.state is ResourceState.UNLOADING:
                    self.teardown.wait_for_unload(resource, self.registrar.come_back(join.add()))
                else:  # loading: refused when it finishes, then unloaded
                    self.teardown.when_gone(resource.id, join.add())
        join.seal()

    def give_up(self, resource: Resource, then: Callable[[], None]) -> None:
        """Release every consumer id of `resource` (`"name yielded"`), then unload it."""
        released = list(resource.consumers.items())
        for query_id, _ in released:
            self.registrar.catalog.release(query_id)
        if self.registrar.events.active:
            for query_id, origin in released:
                self.registrar.events.publish(
                    events.ConsumerReleased(
                        self.registrar.name, resource.id, query_id, origin, "name yielded"
                    )
                )
        self.teardown.unload_resource(resource, self.registrar.come_back(lambda *_: then()))

    def close_resource(self, resource: Resource, then: Callable[[], None]) -> None:
        """Send FATAL to a resource's consumers, revoke their ids, unload it (rule 12)."""
        self.registrar.probe("close_resource", resource)
        query_id = next(iter(resource.consumers))
        update = StatusUpdate(
            query_id,
            Status.FATAL,
            "resource server was unregistered",
            f"{self.registrar.name}/{resource.server}",
        )

        def revoke_and_unload() -> None:
            done = self.registrar.come_back(lambda *_: then())
            if resource.state is not ResourceState.LOADED:  # its consumers left meanwhile
                self.teardown.wait_for_unload(resource, done)
                return
            for origin, ids in consumers_by_origin(resource).items():
                with contextlib.suppress(RrError):
                    DIRECTORY.lookup(origin).tell(Revoke(ids))
            revoked = list(resource.consumers.items())
            for qid, _ in revoked:
                self.registrar.catalog.release(qid)
            if self.registrar.events.active:
                for qid, origin in revoked:
                    self.registrar.events.publish(
                        events.ConsumerReleased(
                            self.registrar.name, resource.id, qid, origin, "server unregistered"
                        )
                    )
            self.teardown.unload_resource(resource, done)

        event = str(uuid.uuid4())
        if self.registrar.events.active:
            self.registrar.events.publish(
                events.StatusSent(
                    self.registrar.name, query_id, update.status, update.message, event
                )
            )
        # the FATAL's acknowledgements may complete on any thread: come back to this one
        back = self.registrar.come_back(lambda *_: revoke_and_unload())
        self.status.notify(resource, update, event, query_id, lambda: back.set_result(None))

    def on_update_response(self, message: UpdateResponse, reply: Reply) -> None:
        query_id, response = message.query_id, message.response
        resource = self.registrar.catalog.resource_of(query_id)
        self.registrar.catalog.set_response(resource.id, response)
        show_response(self.registrar, resource)
        self.registrar.commit()
        refused: list[ConfigError] = []  # (a consumer that cannot take it: too large)

        def then() -> None:
            if refused:
                reply.set_error(refused[0])
            else:
                reply.set_result(None)

        join = Join(then)
        for origin, ids in consumers_by_origin(resource).items():
            self.registrar.send(
                origin,
                functools.partial(ResponseUpdated, ids, response),
                functools.partial(
                    _log_failure, f"telling {origin} about a new response", join.add(), refused
                ),
            )
        join.seal()

    def on_list_server_queries(self, message: ListServerQueries, reply: Reply) -> None:
        self.server(message.server)
        reply.set_result(self.registrar.catalog.server_queries(message.server, self.registrar.name))
