"""A supervisor's awaitable twins: start, stop, wait for children and call from a loop.

```
 await sup.astart() / astop() / aregistrar(...) ──► the blocking step on a thread of its
     own for that one operation (it forks processes, joins threads): never on the loop
 await sup.await_restarted(name) ──► the restart wait's steps (`tree.RestartWait`): a
     tree watcher settles a future at the publish that decides it, and wakes the loop
     (call_soon_threadsafe); no thread waits
 await sup.acall_with_retry(...) ──► the retry's steps (`retry.py`): the consumer's call
     and the restart wait, both awaited; no thread waits
 async with sup: ... ──► astart() ... astop() (and the give-up re-raised, as `with`)
```

Starting and stopping a tree are rare and short and block in code written for threads
(process starts, joins): each holds one thread of its own while it runs, so the loop
goes on. A wait for a child, which may be long, holds none; nor does a call that waits
out a restart. A cancelled `astart` stops what it started once the start is done:
nothing is left running.

Two blocking methods have no twin. `run_in` runs `fn(registrar)`, blocking code by its
contract (handed a `ResourceRegistrar`, it calls its blocking methods), on the calling
thread for a thread manager: from a loop it belongs on a thread,
`await asyncio.to_thread(sup.run_in, name, fn)`; to reach a manager from a loop, await
a registrar's twins instead (`aregistrar`, then `acall`). `flush_events` synchronises
with subscriptions whose callbacks run on subscriber threads, never on a loop, for code
that then blocks on `Subscription.wait_delivered` (a test, a script); it is bounded by
its `timeout`: from a loop, `await asyncio.to_thread(sup.flush_events)`.
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

__all__ = ["AsyncSupervision"]


class AsyncSupervision:
    """The awaitable twins of `Supervisor`'s start, stop, waits, `registrar` and
    `call_with_retry`."""

    if TYPE_CHECKING:  # what `Supervisor` (the one subclass) provides, for the checker only

        @property
        def name(self) -> str: ...

        @property
        def gave_up(self) -> Any: ...

        def start(self) -> Any: ...

        def stop(self, *, timeout: float | None = None) -> None: ...

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
        """`start`, awaited: every child started in order; the loop runs meanwhile.

        Cancelled, it stops the supervisor once the start is done (nothing is left).

        Raises:
            SupervisorGaveUpError: a child failed to start (see `start`).
            ConfigError: as for `start`.
        """
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

    async def astop(self, *, timeout: float | None = None) -> None:
        """`stop`, awaited: its registrars, then every child in reverse order.

        Raises:
            ConfigError: `timeout` is not a positive number of seconds.
        """
        if timeout is not None:
            check_seconds("timeout", timeout)
        await run_steps_async(
            on_own_thread(lambda: self.stop(timeout=timeout), f"rr-stop-{self.name}")
        )

    async def aregistrar(self, config: RegistrarConfig | str) -> ResourceRegistrar:
        """`registrar`, awaited: a consumer registrar in this process, on the tree's carrier.

        Raises:
            DuplicateNameError: a registrar of that name runs in this process.
            ConfigError: the configuration is invalid or the supervisor is not running.
        """
        registrar: ResourceRegistrar = await run_steps_async(
            on_own_thread(lambda: self.registrar(config), f"rr-registrar-{self.name}")
        )
        return registrar

    async def await_restarted(
        self, name: str, *, timeout: float, restarts: int | None = None
    ) -> ChildInfo:
        """`wait_restarted`, awaited ("a" + `wait_restarted`): no thread waits for it.

        Returns:
            The child's snapshot, running.

        Raises:
            CallTimeoutError: not restarted within `timeout` seconds.
            SupervisorGaveUpError: the tree gave up on it (see `wait_restarted`).
            RegistrarUnavailableError: it exited for good, or its supervisor was stopped.
            UnknownServerError: no child of that name.
            ConfigError: `name` is not a str, `timeout` not a positive number of seconds,
                or `restarts` neither an int nor `None`.
        """
        info: ChildInfo = await run_steps_async(self._restart_wait(name, timeout, restarts))
        return info

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
        """`call_with_retry`, awaited: the consumer's call awaited, a restart of
        `target_rr` awaited (the tree wakes the loop when it publishes it), the same call
        again with the same query id; no thread is held while it waits.

        The same arguments, result, errors and `timeout` (for the whole call, restarts
        included) as `call_with_retry`. Cancelling the awaiting task withdraws the call
        as a timeout would: an attempt in flight is withdrawn (its id given back), and
        while it waits for the restart the id is abandoned at the provider (at once if
        it runs again, else when it is back).

        Raises:
            RegistrarUnavailableError: the provider died and will not be restarted.
            SupervisorGaveUpError: the tree gave up on the provider while the call waited.
            CallTimeoutError: no answer (restart included) within `timeout` seconds.
            ResourceLoadError: as for `Registrar.acall`.
            DependencyCycleError: as for `Registrar.acall`.
            UnknownServerError: as for `Registrar.acall`.
            RegistrarStoppedError: as for `Registrar.acall` (not when the supervisor
                stopped the provider to restart it).
            ConfigError: as for `call_with_retry`; nothing was sent.
            asyncio.CancelledError: the awaiting task was cancelled (see above).
        """
        steps = self._retry(consumer, target_rr, server, request, on_status, timeout, query_id)
        query: Query = await run_steps_async(steps)
        return query

    async def __aenter__(self) -> Any:
        return await self.astart()

    async def __aexit__(self, exc_type: object, *_: object) -> None:
        await self.astop()
        gave_up = self.gave_up
        if exc_type is None and gave_up is not None:
            raise gave_up
