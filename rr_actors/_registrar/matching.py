"""Matching a request with the ones a server serves, with user code off the actor thread.

```
 Load ──► Provider.serve: a plain request (a digest), plain candidates ──► decided here
                │ a request without a digest, or stored ones without one
                ▼
 Matching.run(load, work) ──► a worker: work() = the request's __hash__, pickling it,
        │   its __eq__ with the candidates          (bounded by compare_timeout)
        │   meanwhile later loads of that server queue here, in order
        ▼
 then(result, error) back on the actor (Shared.come_back) ──► Matching.finish(server):
        the queued loads of the server are served again, one after the other
```

The registrar's actor must never wait for user code: an `__eq__` that hangs would stall
every server, status and unload of the registrar, and one that raises `SystemExit` would
end pykka's actor loop (which then stops every actor of the process). Plain values (those
with a digest: built-in strings, numbers, containers of them; see
`rr_actors._catalog.digest`) are compared on the actor, since their `==` runs no user
code. Whatever else must be judged by user code runs on a worker of the registrar:

- it may raise: an `Exception` from `__eq__` means "different" (rule 1 as it always was);
  anything else (`SystemExit`, ...) fails that one call with `ConfigError`;
- it may hang: past `RegistrarConfig.compare_timeout` seconds the worker is abandoned
  (`Workers`), the call fails with `CallTimeoutError`, and the loads queued behind it
  go on. The cost: one thread for as long as the comparison hangs, and the wait of the
  server's later loads until the bound.

Loads of one server are matched one at a time while user code decides: two equal
requests without a digest can then not both miss each other and load twice (rule 3),
and a match's candidates stay valid until its answer is back (resources of the server
can only leave, change state or be reported `FATAL` meanwhile, never appear; the
provider checks the one matched again).
"""

from __future__ import annotations

import collections
import logging
from collections.abc import Callable
from typing import Any

from rr_actors._catalog import runtime_key
from rr_actors._catalog.digest import requests_equal
from rr_actors._registrar.loading import check_picklable
from rr_actors._registrar.messages import Load
from rr_actors._registrar.state import Shared
from rr_actors.errors import CallTimeoutError, ConfigError, RrError

__all__ = ["Matching", "first_equal", "prepare"]

logger = logging.getLogger("rr_actors")

Then = Callable[[Any, BaseException | None], None]


def prepare(request: Any, *, pickled: str | None) -> Any:
    """On a worker: a request's `runtime_key` (its `__hash__`), and a check that it pickles.

    Args:
        request: a request without a digest.
        pickled: what to call the request in the error if it must pickle (the registrar
            keeps a backup), else `None`.

    Raises:
        ConfigError: it must pickle and does not.
    """
    key = runtime_key(request)
    if pickled is not None:
        check_picklable(request, pickled)
    return key


def first_equal(request: Any, candidates: list[Any]) -> int | None:
    """On a worker: the index of the first candidate request `== request`, if any.

    A comparison that raises an `Exception` (or whose result has no truth value) means
    "different", as `rr_actors._catalog.digest.requests_equal` has it; any other
    `BaseException` propagates (its call fails).
    """
    for index, stored in enumerate(candidates):
        if requests_equal(stored, request):
            return index
    return None


class Matching:
    """The loads whose match user code decides, per server (the provider's helper).

    Args:
        shared: the registrar actor's shared state.
        serve: serves a load (`Provider.serve`); called here for the loads that queued
            behind a match, once it is done.

    Attributes:
        in_flight: server -> the load whose user code runs on a worker now.
        queued: server -> loads of that server that arrived meanwhile, in order.
        given_up: query ids of loads in flight whose caller gave up (an `Abandon`).
    """

    def __init__(self, shared: Shared, serve: Callable[[Load], None]) -> None:
        self.registrar = shared
        self.serve = serve
        self.in_flight: dict[str, Load] = {}
        self.queued: dict[str, collections.deque[Load]] = {}
        self.given_up: set[str] = set()

    def busy(self, server: str) -> bool:
        """Whether a match of `server` runs: its loads must `queue`."""
        return server in self.in_flight or server in self.queued

    def queue(self, load: Load) -> None:
        """Hold `load` until the matches before it for its server are done."""
        self.queued.setdefault(load.server, collections.deque()).append(load)

    def run(self, load: Load, what: str, work: Callable[[], Any], then: Then) -> None:
        """Run `work()` (user code) on a worker for `load`; then `then(result, error)` here.

        `then` runs on the actor thread, unless the load's caller gave up meanwhile (it
        is then answered as given up) or the registrar failed it (`fail_waiting`).
        `error` is what `work` raised if that was an `Exception`; a `ConfigError` if it
        raised anything else (`SystemExit`, ...); `CallTimeoutError` if it overran
        `compare_timeout`; `RuntimeError` if no thread could run it. Once `then`
        returned, the loads queued behind this one are served, in order, until one of
        them needs a match of its own.

        Args:
            load: the load being matched.
            what: what the work does, for error messages ("comparing the request").
            work: runs on a worker thread.
            then: the continuation, on the actor thread.
        """
        server = load.server
        self.in_flight[server] = load
        where = f"'{self.registrar.name}/{server}'"
        limit = self.registrar.config.compare_timeout

        def back(value: Any, error: BaseException | None) -> None:
            if self.in_flight.get(server) is not load:  # failed by `fail_waiting` already
                return
            del self.in_flight[server]
            try:
                if load.query_id in self.given_up:
                    self.given_up.discard(load.query_id)
                    load.reply.set_error(CallTimeoutError(f"call {load.query_id} was given up"))
                else:
                    then(value, error)
            finally:
                self.next_in_line(server)

        done = self.registrar.come_back(back)

        def task() -> None:
            try:
                value = work()
            except Exception as exc:  # noqa: BLE001 - handed to the actor
                done.set_error(exc)
            except BaseException as exc:  # noqa: BLE001 - SystemExit & co: contained here
                done.set_error(
                    ConfigError(
                        f"{what} for a call to {where} raised {type(exc).__qualname__}: "
                        f"{_text(exc)}; the call fails, the registrar goes on"
                    )
                )
            else:
                done.set_result(value)

        def overdue() -> None:
            done.set_error(
                CallTimeoutError(
                    f"{what} for a call to {where} did not finish within {limit:g} s "
                    "(compare_timeout); the call fails, the registrar goes on"
                )
            )

        try:
            self.registrar.workers.submit(task, timeout=limit, on_overdue=overdue)
        except RuntimeError as exc:
            done.set_error(RuntimeError(f"no worker thread could start for {what}: {exc}"))

    def next_in_line(self, server: str) -> None:
        """Serve the loads queued for `server`, until one starts a match of its own."""
        while server not in self.in_flight:
            waiting = self.queued.get(server)
            if not waiting:
                self.queued.pop(server, None)
                return
            load = waiting.popleft()
            if not waiting:
                del self.queued[server]
            self.serve(load)

    def take(self, query_id: str) -> Load | None:
        """Take the queued load of `query_id` out (its caller gave up), if it is queued."""
        for server, loads in self.queued.items():
            for load in loads:
                if load.query_id == query_id:
                    loads.remove(load)
                    if not loads:
                        del self.queued[server]
                    return load
        return None

    def give_up(self, query_id: str) -> bool:
        """Whether `query_id`'s load is in flight here; it is answered as given up if so."""
        if any(load.query_id == query_id for load in self.in_flight.values()):
            self.given_up.add(query_id)
            return True
        return False

    def named(self, query_id: str) -> Load | None:
        """The load with `query_id` in flight or queued here, if any."""
        if not self.in_flight and not self.queued:  # (the usual case: nothing here)
            return None
        return next((load for load in self.waiting() if load.query_id == query_id), None)

    def waiting(self) -> list[Load]:
        """Every load here: the ones in flight, then the queued ones."""
        return [*self.in_flight.values(), *(load for q in self.queued.values() for load in q)]

    def fail_waiting(self, error: RrError) -> None:
        """Answer every load here with `error` (the registrar stops or died)."""
        for load in self.waiting():
            load.reply.set_error(error)
        self.in_flight.clear()
        self.queued.clear()
        self.given_up.clear()


def _text(exc: BaseException) -> str:
    """`str(exc)`, or a placeholder if even that raises (it is user code too)."""
    try:
        return str(exc)
    except Exception:  # noqa: BLE001 - the error message must not fail
        return "<str() of the exception raised>"
