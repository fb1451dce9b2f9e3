"""A supervisor's awaitable twins: start, stop and wait for children from an event loop.

```
 await sup.astart() / astop() / aregistrar(...) ──► the blocking step on a thread of its
     own for that one operation (it forks processes, joins threads): never on the loop
 await sup.await_restarted(name) ──► the tree's condition, checked at each publish: a
     watcher wakes the loop (call_soon_threadsafe); no thread waits
 async with sup: ... ──► astart() ... astop() (and the give-up re-raised, as `with`)
```

Starting and stopping a tree are rare and short and block in code written for threads
(process starts, joins): each holds one thread of its own while it runs, so the loop
goes on. A wait for a child, which may be long, holds none. A cancelled `astart` stops
what it started once the start is done: nothing is left running.
"""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING, Any

from rr_actors._core import runtime
from rr_actors._core.loops import run_steps_async
from rr_actors._core.replies import on_own_thread
from rr_actors._supervision.tree import RestartWait
from rr_actors.config import RegistrarConfig, check_seconds

if TYPE_CHECKING:
    from rr_actors._registrar import ResourceRegistrar
    from rr_actors._supervision.children import ChildInfo

__all__ = ["AsyncSupervision"]


class AsyncSupervision:
    """The awaitable twins of `Supervisor`'s start, stop, waits and `registrar`."""

    @property
    def name(self) -> str:
        raise NotImplementedError

    def start(self) -> Any:
        raise NotImplementedError

    def stop(self, *, timeout: float | None = None) -> None:
        raise NotImplementedError

    def registrar(self, config: RegistrarConfig | str) -> ResourceRegistrar:
        raise NotImplementedError

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
            ConfigError: `name` is not a str, or `timeout` not a positive number of seconds.
        """
        waiting = self._restart_wait(name, timeout, restarts)
        tree = waiting.tree
        loop = asyncio.get_running_loop()
        deadline = runtime.monotonic() + timeout
        while True:
            changed = asyncio.Event()

            def wake(changed: asyncio.Event = changed) -> None:
                try:
                    loop.call_soon_threadsafe(changed.set)
                except RuntimeError:  # (the loop was closed: nobody waits)
                    return

            with tree.cond:  # (held for the check only, as a publish holds it)
                if waiting.settled():
                    break
                tree.watchers.add(wake)
            try:
                async with asyncio.timeout(max(0.0, deadline - runtime.monotonic())):
                    await changed.wait()
            except TimeoutError:
                with tree.cond:
                    if waiting.settled():
                        break
                    raise waiting.timed_out(timeout) from None
            finally:
                with tree.cond:
                    tree.watchers.discard(wake)
        return waiting.result()

    def _restart_wait(self, name: str, timeout: float, restarts: int | None) -> RestartWait:
        raise NotImplementedError

    async def __aenter__(self) -> Any:
        return await self.astart()

    async def __aexit__(self, exc_type: object, *_: object) -> None:
        await self.astop()
        gave_up = self.gave_up
        if exc_type is None and gave_up is not None:
            raise gave_up

    @property
    def gave_up(self) -> Any:
        raise NotImplementedError
