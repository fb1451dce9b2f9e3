"""The registrar API as a typed protocol: one contract, two placements.

`ResourceRegistrar` (a registrar in this process) and `RemoteRegistrar` (a registrar in a
manager process, reached over the system's transport) both implement `Registrar`, so code
written against it (an application's actions, `Supervisor.call_with_retry`, the tests)
does not change between the placements. Each blocking method has an awaitable twin
(`acall` for `call`, ...), written once for both handles in `aio.py`. The full
documentation of each method, with its errors, is on
[`ResourceRegistrar`][rr_actors.ResourceRegistrar].
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any, Protocol, runtime_checkable

from rr_actors._types import Query, Status, StatusCallback, StatusUpdate
from rr_actors.config import RegistrarConfig

__all__ = ["LoadCallback", "Registrar", "UnloadCallback"]

LoadCallback = Callable[[Any], Any]
"""`load(request) -> response`: a resource server's load callback (or a coroutine
function, `async def load(request)`)."""

UnloadCallback = Callable[[Any, Any], Awaitable[None] | None]
"""`unload(request, response) -> None`: a resource server's unload callback (or a
coroutine function)."""


@runtime_checkable
class Registrar(Protocol):
    """What every registrar handle offers, wherever the registrar runs.

    Every blocking method takes a keyword-only `timeout` in seconds (default: the
    registrar's `call_timeout`) and raises `CallTimeoutError` when it runs out.
    """

    @property
    def name(self) -> str:
        """The registrar's name."""
        ...

    @property
    def config(self) -> RegistrarConfig:
        """The configuration it was started with."""
        ...

    @property
    def restored(self) -> bool:
        """Whether its catalog was restored from an existing backup at start."""
        ...

    @property
    def in_doubt(self) -> tuple[Query, ...]:
        """Loads or unloads a crash cut short in the last run (rule 16)."""
        ...

    def is_alive(self) -> bool:
        """Whether the registrar is running."""
        ...

    def register_server(
        self,
        name: str,
        *,
        load: LoadCallback,
        unload: UnloadCallback,
        on_status: StatusCallback | None = None,
        timeout: float | None = None,
        label: Callable[[Any], str] | None = None,
    ) -> None:
        """Register a resource server `"<registrar>/<name>"`."""
        ...

    def unregister_server(self, name: str, *, timeout: float | None = None) -> None:
        """Remove a server: `FATAL` to its consumers, unload all it serves (rule 12)."""
        ...

    def call(
        self,
        target_rr: str,
        server: str,
        request: Any,
        *,
        on_status: StatusCallback | None = None,
        timeout: float | None = None,
        query_id: str | None = None,
    ) -> Query:
        """Ask `target_rr/server` for the resource `request` describes (rules 1-6, 17)."""
        ...

    def unload(self, query_id: str, *, timeout: float | None = None) -> None:
        """Release one consumer id obtained from `call` (rules 7-8)."""
        ...

    def send_status(
        self, query_id: str, status: Status, message: str = "", *, timeout: float | None = None
    ) -> None:
        """Tell every consumer of the resource behind `query_id` its status (rule 9)."""
        ...

    def server_queries(self, server: str, *, timeout: float | None = None) -> list[Query]:
        """Every consumer query of this registrar's `server` (rule 10)."""
        ...

    def fetch_queries(
        self, target_rr: str, server: str, *, timeout: float | None = None
    ) -> list[Query]:
        """The queries this registrar holds at `target_rr/server` (rule 10)."""
        ...

    def client_queries(self, *, timeout: float | None = None) -> list[Query]:
        """Every query this registrar holds at servers, oldest first."""
        ...

    def set_status_callback(
        self, query_id: str, callback: StatusCallback, *, timeout: float | None = None
    ) -> None:
        """Re-attach the client status callback of a query this registrar holds (rule 11)."""
        ...

    def update_response(
        self, query_id: str, response: Any, *, timeout: float | None = None
    ) -> None:
        """Replace the stored response of a resource served here (rule 11)."""
        ...

    def save_catalog(self, *, timeout: float | None = None) -> None:
        """Write every pending change of the catalog to the backup now."""
        ...

    def stop(self, *, timeout: float | None = None) -> None:
        """Stop the registrar (rule 12)."""
        ...

    # -- the awaitable twins (`aio.py`): the same operations, awaited ------------------

    async def acall(
        self,
        target_rr: str,
        server: str,
        request: Any,
        *,
        on_status: StatusCallback | None = None,
        timeout: float | None = None,
        query_id: str | None = None,
    ) -> Query:
        """`call`, awaited."""
        ...

    async def aunload(self, query_id: str, *, timeout: float | None = None) -> None:
        """`unload`, awaited."""
        ...

    async def asend_status(
        self, query_id: str, status: Status, message: str = "", *, timeout: float | None = None
    ) -> None:
        """`send_status`, awaited."""
        ...

    async def aserver_queries(self, server: str, *, timeout: float | None = None) -> list[Query]:
        """`server_queries`, awaited."""
        ...

    async def afetch_queries(
        self, target_rr: str, server: str, *, timeout: float | None = None
    ) -> list[Query]:
        """`fetch_queries`, awaited."""
        ...

    async def aclient_queries(self, *, timeout: float | None = None) -> list[Query]:
        """`client_queries`, awaited."""
        ...

    async def aset_status_callback(
        self, query_id: str, callback: StatusCallback, *, timeout: float | None = None
    ) -> None:
        """`set_status_callback`, awaited."""
        ...

    async def aupdate_response(
        self, query_id: str, response: Any, *, timeout: float | None = None
    ) -> None:
        """`update_response`, awaited."""
        ...

    async def asave_catalog(self, *, timeout: float | None = None) -> None:
        """`save_catalog`, awaited."""
        ...

    async def aregister_server(
        self,
        name: str,
        *,
        load: LoadCallback,
        unload: UnloadCallback,
        on_status: StatusCallback | None = None,
        timeout: float | None = None,
        label: Callable[[Any], str] | None = None,
    ) -> None:
        """`register_server`, awaited."""
        ...

    async def aunregister_server(self, name: str, *, timeout: float | None = None) -> None:
        """`unregister_server`, awaited."""
        ...

    async def astop(self, *, timeout: float | None = None) -> None:
        """`stop`, awaited."""
        ...

    def watch(self, query_id: str, *, maxsize: int = 256) -> AsyncIterator[StatusUpdate]:
        """A query's status updates as an async iterator."""
        ...
