"""A supervisor's awaitable twins: start, stop, wait for children and call from a loop.

```
 await sup.astart() / astop() / aregistrar(...) ──► the blocking step on a thread of its
     own for that one operation (it forks processes, joins threads): never on the loop
 await sup.await_restarted(name) ──► the restart wait's steps (`tree.RestartWait`): a
     tree watcher settles a future at the publish that decides it; no thread waits
 await sup.acall_with_retry(...) ──► the retry's steps (`retry.py`), awaited
 async with sup: ... ──► astart() ... astop() (and the give-up re-raised, as `with`)
```

`run_in` and `flush_events` have no twin (blocking by contract): from a loop,
`await asyncio.to_thread(sup.run_in, name, fn)`.
"""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING, Any

from rr_actors._core import runtime
from rr_actors._core.loops import run_steps_async
from rr_actors._core.replies import Steps, on_own_thread
from rr_actors._supervision.retry import MISSING
from rr_actors.config import RegistrarConfig, check_seconds

if TYPE_CHECKING:
    from rr_actors._registrar import Registrar, ResourceRegistrar
    from rr_actors._supervision.children import ChildInfo
    from rr_actors._types import Query, StatusCallback


class AsyncSupervision:
    """The awaitable twins of `Supervisor`'s methods."""

    if TYPE_CHECKING:  # what `Supervisor` (the one subclass) provides, for the checker only

        @property
        def name(self) -> str: ...

        @property
        def gave_up(self) -> Any: ...

        def start(self) -> Any: ...

        def stop(self, *, timeout: float | None = None, parallel: bool = False) -> None: ...

        def registrar(self, config: RegistrarConfig | str) -> ResourceRegistrar: ...

        def _restart_wait(
            self, name: str, timeout: float, restarts: int | None
        ) -> Steps[ChildInfo]: ...

        def _retry(
            self,
            consumer: Registrar,
            target_rr: str,
            server: str,
            request: Any,
            on_status: StatusCallback | None,
            timeout: float | None,
            query_id: str | None,
        ) -> Steps[Query]: ...

    async def astart(self) -> Any:
        """As `start`, awaitable; cancelled, it stops the supervisor once the start is done."""
        lock = runtime.Lock()
        state = {"cancelled": False, "started": False}

        def start() -> None:
            self.start()
            with lock:
                state["started"] = True
                stop = state["cancelled"]
            if stop:
                self.stop()

        try:
            await run_steps_async(on_own_thread(start, f"rr-start-{self.name}"))
        except asyncio.CancelledError:
            with lock:
                state["cancelled"] = True
                stop = state["started"]
            if stop:  # (it started just before the cancel: stopped here, on a thread)
                runtime.Thread(target=self.stop, name=f"rr-stop-{self.name}").start()
            raise
        return self

    async def astop(self, *, timeout: float | None = None, parallel: bool = False) -> None:
        """As `stop`, awaitable."""
        if timeout is not None:
            check_seconds("timeout", timeout)
        await run_steps_async(
            on_own_thread(
                lambda: self.stop(timeout=timeout, parallel=parallel), f"rr-stop-{self.name}"
            )
        )

    async def aregistrar(self, config: RegistrarConfig | str) -> ResourceRegistrar:
        """As `registrar`, awaitable."""
        return await run_steps_async(
            on_own_thread(lambda: self.registrar(config), f"rr-registrar-{self.name}")
        )

    async def await_restarted(
        self, name: str, *, timeout: float, restarts: int | None = None
    ) -> ChildInfo:
        """As `wait_restarted`, awaitable; no thread waits for it."""
        return await run_steps_async(self._restart_wait(name, timeout, restarts))

    async def acall_with_retry(
        self,
        consumer: Registrar,
        target_rr: str,
        server: str,
        request: Any = MISSING,
        *,
        on_status: StatusCallback | None = None,
        timeout: float | None = None,
        query_id: str | None = None,
    ) -> Query:
        """As `call_with_retry`, awaitable; no thread is held while it waits. Cancelling
        the task withdraws the call as a timeout would (the id given back or abandoned)."""
        steps = self._retry(consumer, target_rr, server, request, on_status, timeout, query_id)
        return await run_steps_async(steps)

    async def __aenter__(self) -> Any:
        return await self.astart()

    async def __aexit__(self, exc_type: object, *_: object) -> None:
        await self.astop()
        gave_up = self.gave_up
        if exc_type is None and gave_up is not None:
            raise gave_up
