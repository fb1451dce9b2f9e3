"""The workload: client threads that load and unload resources while faults hit the tree.

Each client has a consumer registrar of its own (`Supervisor.registrar`) and one thread:

    next call due? ──► pick a call of the mix (weighted), a shared or a unique key ──► call
                         (retried through restarts and cut connections, same query id)
    a resource's hold ran out? ──► unload it (retried likewise)
    a call again due (`again`)? ──► call it again with its held id, as a user unsure of it
    a status came (its callback queues it) ──► FATAL: unload, load again (a recovery)
                                               UPDATE: the manager replaced it (a recovery)

Calls come at `rate` per second per client on a schedule fixed in advance (an open-loop
load: calls due while one waited out a restart follow it back to back). What came due
while a call blocked is handled before the next call, statuses first (a `FATAL` about a
resource still held is acted on). `awaited`, `cancel`, `fetch_every`, `status_wait` and
`again`: docs/reference/plan.md. Every call is recorded (`CallRecord`), and so are `recoveries`.
A request the client cannot build is a mistake in the plan, not a failed call: the client
stops, keeps it in `failure`, calls `on_failure`, and the run fails with it.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import dataclasses
import functools
import heapq
import itertools
import os
import queue
import random
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import rr_actors as rr
from rr_actors._core import runtime
from rr_actors.errors import ConfigError
from rr_actors_lab.experiments.metrics import ClientRecovery
from rr_actors_lab.experiments.plan import CallMix, Plan, Workload
from rr_actors_lab.experiments.reading import import_object
from rr_actors_lab.experiments.results import CallRecord

__all__ = ["Client", "RequestContext", "render_request", "retrying"]

T = TypeVar("T")

_RETRY_PAUSE = 0.01
"""Seconds before the first retry of a call whose provider is running (a cut connection);
the pause doubles up to `_RETRY_PAUSE_MAX`."""

_RETRY_PAUSE_MAX = 0.2


@dataclasses.dataclass(frozen=True)
class RequestContext:
    """What a request factory (`factory = "module:function"`) is told besides the key.

    Attributes:
        client: the client's index (0, 1, ...).
        run_dir: a directory of this run (for files a resource may need).
        pid: the run process's pid (for programs that should exit with the run).
        manager: the provider the call goes to.
        server: the server on it.
    """

    client: int
    run_dir: str
    pid: int
    manager: str
    server: str


def render_request(template: Any, key: str, context: RequestContext) -> Any:
    """Fill a request template: `{key}`, `{client}`, `{run_dir}` in strings; `"{pid}"` -> pid.

    Args:
        template: the template from the plan (any TOML value; not changed).
        key: the request's key (`"shared-2"`, `"unique-0-17"`).
        context: the call's context.

    Raises:
        ValueError, KeyError, IndexError: a string `str.format` cannot fill (another field,
            a bad format spec); no rr_actors error.
    """
    if isinstance(template, dict):
        return {k: render_request(v, key, context) for k, v in template.items()}
    if isinstance(template, list):
        return [render_request(v, key, context) for v in template]
    if isinstance(template, str):
        if template == "{pid}":
            return context.pid
        return template.format(
            key=key, client=context.client, run_dir=context.run_dir, pid=context.pid
        )
    return template


def retrying(
    sup: rr.Supervisor,
    provider: str,
    action: Callable[[], T],
    *,
    deadline: float,
    retried: Callable[[], None] = lambda: None,
) -> T:
    """Run `action` until it succeeds, waiting out restarts of `provider` and cut connections.

    On `RegistrarUnavailableError` or `RegistrarStoppedError`: wait for the provider's next
    restart if it was restarted or is down, else (a cut connection) retry after a pause.

    Args:
        sup: the supervisor of `provider`.
        provider: the manager `action` talks to.
        action: the call or unload (with a fixed query id, so a retry is idempotent).
        deadline: monotonic time after which the last error is raised.
        retried: called before each retry.

    Raises:
        CallTimeoutError: the provider was not back before `deadline`.
        RrError: what `action` raised otherwise, or its last failure.
    """
    pause = _RETRY_PAUSE
    remote = _elsewhere(sup, provider)
    while True:
        before = None if remote else sup.child(provider)
        try:
            return action()
        except (
            rr.RegistrarUnavailableError,
            rr.RegistrarStoppedError,
            rr.errors.UnknownServerError,
        ):
            # (a provider on another host: lost while its link was down, so unknown here
            # until it is seen again; its own host's supervisor restarts it, not this one)
            left = deadline - runtime.monotonic()
            if left <= 0 or (before is not None and not _unavailable(sys.exc_info()[1])):
                raise
            retried()
            now = None if before is None else sup.child(provider)
            if now is None or before is None:
                runtime.Event().wait(min(pause, left))  # a short pause, not a sync point
                pause = min(2 * pause, _RETRY_PAUSE_MAX)
                continue
            if now.state == "running" and now.restarts == before.restarts:
                runtime.Event().wait(min(pause, left))  # a short pause, not a sync point
                pause = min(2 * pause, _RETRY_PAUSE_MAX)
                continue
            sup.wait_restarted(provider, timeout=left, restarts=before.restarts + 1)


def _elsewhere(sup: rr.Supervisor, provider: str) -> bool:
    """Whether `provider` is a manager of another host (not in `sup`'s tree)."""
    try:
        sup.child(provider)
    except rr.errors.UnknownServerError:
        return True
    return False


def _unavailable(exc: BaseException | None) -> bool:
    """Whether a local provider's error is one to wait out (not an unknown name)."""
    return isinstance(exc, rr.RegistrarUnavailableError | rr.RegistrarStoppedError)


@dataclasses.dataclass
class _Held:
    unload_at: float
    seq: int
    query: rr.Query = dataclasses.field(compare=False)
    mix: CallMix = dataclasses.field(compare=False)
    request: Any = dataclasses.field(compare=False)

    def __lt__(self, other: _Held) -> bool:
        return (self.unload_at, self.seq) < (other.unload_at, other.seq)


_STOP = object()


class Client:
    """One client of the workload: a consumer registrar and the thread that drives it.

    Args:
        index: the client's index.
        sup: the run's supervisor.
        plan: the plan (its `workload` says what to do).
        seed: the run's seed (each client draws from its own generator).
        run_dir: the run's directory (for `{run_dir}`).
        on_failure: called on the client's thread when it stopped on an error of its own
            (kept in `failure`); the runner ends the run early with it.
        step_span: with `--trace`, what each step (a call with its retries, an unload, a
            fetch, a reload) runs under: `otel.Exporting.root_span`.
    """

    def __init__(
        self,
        index: int,
        sup: rr.Supervisor,
        plan: Plan,
        seed: int,
        *,
        run_dir: Path,
        on_failure: Callable[[], None] = lambda: None,
        step_span: Callable[..., contextlib.AbstractContextManager[object]] | None = None,
    ) -> None:
        self.index = index
        self._step_span = step_span
        self.sup = sup
        self.workload: Workload = plan.workload
        self.base_dir = plan.base_dir
        self.t0 = 0.0
        self.deadline = 0.0
        self.run_dir = run_dir
        self.registrar = sup.registrar(
            rr.RegistrarConfig(name=f"client-{index}", call_timeout=self.workload.timeout)
        )
        self.rng = random.Random(f"rr-actors/{seed}/client/{index}")  # noqa: S311
        self.calls: list[CallRecord] = []
        self.recoveries: list[ClientRecovery] = []
        """Each time this client got a resource back after a failure: the manager it
        called, when it heard of the failure and when it had the resource back (seconds
        from `t0`)."""
        self.heard: list[float] = []
        """Times (from `t0`) at which a `FATAL` or `UPDATE` about a resource it held came."""
        self.unload_failures = 0
        self.failure: Exception | None = None
        """Why this client stopped calling before the end, or `None`: a `ConfigError` for
        a request it could not build (naming the call and the cause), else the bug."""
        self._on_failure = on_failure
        self._notes: queue.SimpleQueue[Any] = runtime.SimpleQueue()
        self._pending: collections.deque[tuple[str, rr.Status, float]] = collections.deque()
        self._held: list[_Held] = []
        self._given_up: list[tuple[CallMix, Any, str]] = []
        self._release_later: list[tuple[str, str]] = []  # (manager, query id)
        self._again: list[tuple[float, int, _Held]] = []  # (when, seq, held): `again`
        self._by_id: dict[str, _Held] = {}
        self._seq = itertools.count()
        self._unique = itertools.count()
        self._since_fetch = 0  # calls since the last fetch (`fetch_every`)
        self._due = 0  # the calls that came due (`only` numbers them from 1)
        only = self.workload.only
        self._only = None if only is None else frozenset(n for c, n in only if c == index)
        self._slow = self.workload.status_wait > 0 and index < self.workload.slow_clients
        self._stopping = runtime.Event()
        self._loop: asyncio.AbstractEventLoop | None = None  # (made at the first awaited calls)
        self._factories: dict[str, Callable[..., Any]] = {}
        self._thread = runtime.Thread(target=self._run, name=f"rr-client-{index}", daemon=True)

    # -- life cycle -----------------------------------------------------------------------

    def start(self, *, t0: float, deadline: float) -> None:
        """Start calling.

        Args:
            t0: the monotonic start of the workload (the first call comes one gap after).
            deadline: the monotonic end of the workload (no call starts after it).
        """
        self.t0, self.deadline = t0, deadline
        self._thread.start()

    def stop(self, *, timeout: float) -> None:
        """Stop calling, unload everything held (retrying for up to `timeout` s), return."""
        self._stopping.set()
        self._notes.put(_STOP)
        self._thread.join(timeout + self.workload.timeout + 5.0)
        deadline = runtime.monotonic() + timeout
        while self._held:
            held = heapq.heappop(self._held)
            self._unload(held, deadline)
        for mix, request, query_id in self._given_up:
            self._release_given_up(mix, request, query_id, deadline)
        for manager, query_id in self._release_later:
            with contextlib.suppress(rr.RrError):
                retrying(
                    self.sup,
                    manager,
                    functools.partial(self.registrar.unload, query_id),
                    deadline=max(deadline, runtime.monotonic() + 1e-3),
                )

    def _release_given_up(self, mix: CallMix, request: Any, query_id: str, deadline: float) -> None:
        """Release the id of a call that gave up during an outage, in case the provider took it.

        Calling again with the same id is idempotent, and the unload that follows releases it.
        """
        call = functools.partial(self.registrar.call, mix.manager, mix.server, request)
        with contextlib.suppress(rr.RrError):
            retrying(
                self.sup,
                mix.manager,
                lambda: call(query_id=query_id, timeout=max(1e-3, deadline - runtime.monotonic())),
                deadline=max(deadline, runtime.monotonic() + 1e-3),
            )
            retrying(
                self.sup,
                mix.manager,
                functools.partial(self.registrar.unload, query_id),
                deadline=max(deadline, runtime.monotonic() + 1e-3),
            )

    # -- the thread -----------------------------------------------------------------------

    def _gap(self) -> float:
        rate = self.workload.rate
        if rate is None:
            return 0.0
        if self.workload.arrivals == "fixed":
            return 1.0 / rate
        return self.rng.expovariate(rate)

    def _run(self) -> None:
        try:
            self._calls()
        except Exception as exc:  # noqa: BLE001 - kept in `failure`: the run fails with it
            self.failure = exc
            self._on_failure()
        finally:
            if self._loop is not None:
                self._loop.close()

    def _calls(self) -> None:
        next_call = self.t0 + self._gap()
        while not self._stopping.is_set():
            if not self._catch_up():
                break
            now = runtime.monotonic()
            if now >= next_call:
                if now >= self.deadline:
                    break
                self._due += 1
                if self._only is None or self._due in self._only:
                    self._call_one()
                else:
                    self._draw_one()
                next_call += self._gap()
                if self.workload.rate is None:
                    next_call = runtime.monotonic()
                if self._only is not None and self._due >= max(self._only, default=0):
                    next_call = max(next_call, self.deadline)  # (none left: the end, not a spin)
                continue
            wake = next_call
            if self._held:
                wake = min(wake, self._held[0].unload_at)
            if self._again:
                wake = min(wake, self._again[0][0])
            try:
                note = self._notes.get(timeout=max(0.0, wake - runtime.monotonic()))
            except runtime.Empty:
                continue
            if note is _STOP:
                break
            self._pending.append(note)
        # Statuses that came after the end: nothing more to do than unload at stop().

    def _catch_up(self) -> bool:
        """Handle the statuses heard, then unload the holds that ran out; False once `stop` was
        asked.

        A `FATAL` heard while a call blocked is acted on even if the hold ran out meanwhile: the
        client has not released it, so the provider still counts it among the consumers.
        """
        while True:
            try:
                note = self._notes.get_nowait()
            except runtime.Empty:
                break
            if note is _STOP:
                return False
            self._pending.append(note)
        while self._pending:
            self._handle(self._pending.popleft())
        while self._again and self._again[0][0] <= runtime.monotonic():
            self._call_again(heapq.heappop(self._again)[2])
        now = runtime.monotonic()
        while self._held and self._held[0].unload_at <= now:
            self._unload(heapq.heappop(self._held), now + self.workload.timeout)
        return True

    def _now(self) -> float:
        return runtime.monotonic() - self.t0

    def _choose(self) -> CallMix:
        mix = self.workload.calls
        if len(mix) == 1:
            return mix[0]
        return self.rng.choices(mix, weights=[m.weight for m in mix])[0]

    def _request(self, mix: CallMix) -> Any:
        """A request of `mix` with a shared or a unique key.

        Raises:
            ConfigError: the factory (or template) raised; names the call, the key and the cause.
        """
        if self.rng.random() < mix.shared:
            key = f"shared-{self.rng.randrange(mix.keys)}"
        else:
            key = f"unique-{self.index}-{next(self._unique)}"
        context = RequestContext(
            self.index, str(self.run_dir), os.getpid(), mix.manager, mix.server
        )
        try:
            if mix.factory is not None:
                factory = self._factories.get(mix.factory)
                if factory is None:
                    factory = self._factories[mix.factory] = import_object(
                        mix.factory, base_dir=self.base_dir
                    )
                return factory(key, context)
            return render_request(mix.request, key, context)
        except Exception as exc:
            how = f"factory {mix.factory!r}" if mix.factory else "its request template"
            number = self.workload.calls.index(mix)
            raise ConfigError(
                f"workload.calls[{number}]: {how} raised {exc!r} for key {key!r} "
                f"(client {self.index})"
            ) from exc

    def _step(self, verb: str, mix: CallMix) -> contextlib.AbstractContextManager[object]:
        """The context one step runs in: with `--trace`, a span `<verb> <manager>/<server>`,
        the root of a trace of its own (the step's calls its descendants)."""
        if self._step_span is None:
            return contextlib.nullcontext()
        attributes = {"rr_actors.client": self.index, "rr_actors.step": verb}
        return self._step_span(f"{verb} {mix.manager}/{mix.server}", attributes=attributes)

    def _call_one(self) -> None:
        if self.workload.awaited:
            mix = self._await_calls()
        else:
            mix = self._choose()
            request = self._request(mix)
            with self._step("call", mix):
                query = self._call(mix, request)
            self._hold(mix, request, query)
        self._since_fetch += self.workload.awaited or 1
        every = self.workload.fetch_every
        if every and self._since_fetch >= every:
            self._since_fetch = 0
            self._fetch(mix)

    def _draw_one(self) -> None:
        """The draws of a call not made (`only`): the calls made after it are as they were."""
        for _ in range(self.workload.awaited or 1):
            self._request(self._choose())
            if self.workload.awaited and self.rng.random() < self.workload.cancel:
                self.rng.uniform(0.0, self.workload.cancel_within)

    def _fetch(self, mix: CallMix) -> None:
        """Ask `mix`'s provider for the ids this client holds there (only its `QueriesFetched`
        counts)."""
        with contextlib.suppress(rr.RrError), self._step("fetch", mix):
            self.registrar.fetch_queries(mix.manager, mix.server, timeout=self.workload.timeout)

    def _hold(self, mix: CallMix, request: Any, query: rr.Query | None) -> None:
        """Keep `query` (an answered call) for the workload's `hold`, then unload it; a share
        `again` of them is called again a seeded while within the hold."""
        if query is not None:
            held = _Held(
                runtime.monotonic() + self.workload.hold, next(self._seq), query, mix, request
            )
            heapq.heappush(self._held, held)
            self._by_id[query.id] = held
            if mix.again > 0 and self.rng.random() < mix.again:  # (no draw without `again`)
                at = runtime.monotonic() + self.rng.uniform(0.0, self.workload.hold)
                heapq.heappush(self._again, (at, held.seq, held))

    def _call_again(self, held: _Held) -> None:
        """Call `held`'s call again with its id, if it is still held, as a user unsure of it
        would; its hold starts over. Answered, the answer is the one held (the same resource,
        or one a restart loaded anew); failed or timed out, the client keeps what it held (it
        releases nothing; its consumer tells `FATAL` if the provider lost it meanwhile)."""
        if self._by_id.get(held.query.id) is not held:
            return  # (unloaded, or reloaded after a FATAL, meanwhile)
        with self._step("call", held.mix):
            query = self._call(held.mix, held.request, query_id=held.query.id)
        if self._by_id.get(held.query.id) is held:
            held.query = held.query if query is None else query
            held.unload_at = runtime.monotonic() + self.workload.hold
            heapq.heapify(self._held)

    def _await_calls(self) -> CallMix:
        """`awaited` calls at once on this client's loop, a share cancelled; the last one's kind.

        Every draw is made before any call is sent (the same seed, the same calls); a cancelled
        call is withdrawn (rule 17) and not recorded.
        """
        work = self.workload
        batch = []
        for _ in range(work.awaited):
            mix = self._choose()
            request = self._request(mix)
            cancel = self.rng.random() < work.cancel
            batch.append(
                (mix, request, self.rng.uniform(0.0, work.cancel_within) if cancel else None)
            )
        if self._loop is None:
            self._loop = runtime.new_event_loop()
        outcomes = self._loop.run_until_complete(self._gathered(batch))
        for (mix, request, _), query in zip(batch, outcomes, strict=True):
            self._hold(mix, request, query)
        return batch[-1][0]

    async def _gathered(self, batch: list[tuple[CallMix, Any, float | None]]) -> list[Any]:
        return await asyncio.gather(*(self._awaited(*call) for call in batch))

    async def _awaited(self, mix: CallMix, request: Any, cancel_after: float | None) -> Any:
        """One awaited call (retried through restarts), cancelled after `cancel_after` s
        if given; its query, or `None` if it failed or was cancelled."""
        with self._step("call", mix):  # (this task's context: the call's task copies it)
            return await self._awaited_call(mix, request, cancel_after)

    async def _awaited_call(self, mix: CallMix, request: Any, cancel_after: float | None) -> Any:
        start = self._now()
        task = asyncio.ensure_future(
            self.sup.acall_with_retry(
                self.registrar,
                mix.manager,
                mix.server,
                request,
                on_status=self._on_status,
                timeout=self.workload.timeout,
                query_id=runtime.new_id(),
            )
        )
        if cancel_after is not None:
            asyncio.get_running_loop().call_later(cancel_after, task.cancel)
        try:
            query = await task
        except asyncio.CancelledError:
            return None  # (withdrawn by its caller: not a failure of the tree)
        except rr.RrError as exc:
            error: str | None = type(exc).__name__
            query = None
        else:
            error = None
        # (`retried` is not known: `acall_with_retry` retries inside)
        record = CallRecord(
            self.index, mix.manager, mix.server, start, self._now(), error is None, False, error
        )
        self.calls.append(record)
        return query

    def _call(self, mix: CallMix, request: Any, query_id: str | None = None) -> rr.Query | None:
        """One call with retries (a new id, or `query_id`: one held, `again`); recorded;
        returns the query, or `None` if it failed."""
        start = self._now()
        retried = False

        def again() -> None:
            nonlocal retried
            retried = True

        held_id = query_id is not None
        query_id = query_id or runtime.new_id()
        call = functools.partial(
            self.registrar.call,
            mix.manager,
            mix.server,
            request,
            on_status=self._on_status,
            query_id=query_id,
        )
        deadline = runtime.monotonic() + self.workload.timeout
        try:
            if not self.workload.retry:  # (once: a failed id is kept for a retry never made)
                query = call(timeout=self.workload.timeout)
            else:
                query = retrying(
                    self.sup,
                    mix.manager,
                    lambda: call(timeout=max(1e-3, deadline - runtime.monotonic())),
                    deadline=deadline,
                    retried=again,
                )
        except rr.RrError as exc:
            self.calls.append(
                CallRecord(
                    self.index,
                    mix.manager,
                    mix.server,
                    start,
                    self._now(),
                    False,
                    retried,
                    type(exc).__name__,
                )
            )
            if retried and not held_id:  # its provider may have taken the id before it died
                self._given_up.append((mix, request, query_id))
            return None
        self.calls.append(
            CallRecord(self.index, mix.manager, mix.server, start, self._now(), True, retried)
        )
        return query

    def _unload(self, held: _Held, deadline: float) -> None:
        with self._step("unload", held.mix):
            self._unload_in_step(held, deadline)

    def _unload_in_step(self, held: _Held, deadline: float) -> None:
        self._by_id.pop(held.query.id, None)
        try:
            retrying(
                self.sup,
                held.mix.manager,
                functools.partial(self.registrar.unload, held.query.id),
                deadline=max(deadline, runtime.monotonic() + 1e-3),
            )
        except rr.UnknownQueryError:
            pass  # released already (its provider sent FATAL and forgot it, say)
        except rr.RrError:
            self.unload_failures += 1

    # -- statuses ---------------------------------------------------------------------------

    def _on_status(self, query: rr.Query, update: rr.StatusUpdate) -> None:
        """Client status callback (a worker thread of this client's registrar): queue it;
        a slow client's waits `status_wait` seconds first."""
        if self._slow:
            runtime.sleep(self.workload.status_wait)
        if update.status in (rr.Status.FATAL, rr.Status.UPDATE):
            self.heard.append(self._now())
            self._notes.put((query.id, update.status, self._now()))

    def _handle(self, note: tuple[str, rr.Status, float]) -> None:
        query_id, status, heard = note
        held = self._by_id.get(query_id)
        if held is None:
            return
        if status is rr.Status.UPDATE:
            self.recoveries.append(ClientRecovery(held.mix.manager, heard, self._now()))
            return
        with self._step("reload", held.mix):
            self._recover(held, heard)

    def _recover(self, held: _Held, heard: float) -> None:
        """A FATAL: the resource is gone. Release every id this client holds of it (the
        same resource may be held twice: equal requests), then load it again once and
        give each of them the new one."""
        dead = [
            h for h in self._held if h.mix is held.mix and h.query.response == held.query.response
        ]
        for entry in dead:
            self._by_id.pop(entry.query.id, None)
            self._release(entry.mix.manager, entry.query.id)
        self._held = [h for h in self._held if h not in dead]
        heapq.heapify(self._held)
        recovered = False
        for entry in dead:
            query = self._reload(entry)
            if query is None:
                continue
            if not recovered:
                self.recoveries.append(ClientRecovery(entry.mix.manager, heard, self._now()))
                recovered = True
            renewed = dataclasses.replace(entry, query=query, seq=next(self._seq))
            heapq.heappush(self._held, renewed)
            self._by_id[query.id] = renewed

    def _release(self, manager: str, query_id: str) -> None:
        """Unload `query_id` now; if its provider is out, again when the run ends."""
        try:
            self.registrar.unload(query_id)
        except rr.UnknownQueryError:
            pass  # released already
        except rr.RrError:
            self._release_later.append((manager, query_id))

    def _reload(self, held: _Held) -> rr.Query | None:
        """Load a failed resource again until the answer is not the dead one (bounded by `timeout`).

        While another consumer still holds the dead one, an equal request gets it back: release
        it and retry after a pause.
        """
        deadline = runtime.monotonic() + self.workload.timeout
        pause = _RETRY_PAUSE
        while not self._stopping.is_set() and runtime.monotonic() < self.deadline:
            query = self._call(held.mix, held.request)
            if query is not None and query.response != held.query.response:
                return query
            if query is not None:
                self._release(held.mix.manager, query.id)
            if runtime.monotonic() + pause > deadline:
                return None
            self._stopping.wait(pause)
            pause = min(2 * pause, _RETRY_PAUSE_MAX)
        return None
