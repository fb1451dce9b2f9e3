"""Messages as data: what registrars tell each other and tell themselves, and what a load runs in.

```
 consumer ── Load Unload Abandon Fetch Reconcile ─────────────────────────► provider
 provider ── StatusBatch StatusNotice Revoke ResponseUpdated ReconcileAsk ─► consumer
 death watch ── ConsumerDown LostEverything ─► registrars (the wire: they pickle)
 registrar ── RunLoad RunUnload ─► its server actor; handle ── FetchVia ─► a client actor
 timers, carriers, the membership ── Flush Crash Reachable PeerLost PeerReachable
                                     YieldName ReconcileRetry Ping ─► the registrar
 the handle ── RegisterServer Release Stop ... (each with its reply) ─► the registrar
 a caller's thread ── ClientLoaded CallFailed TakeOutcomes ─► the registrar (`calls.py`)
 a load callback's thread: LOADING = LoadContext(registrar, resource, chain): a call
   made there records a dependency (rule 5) and extends the chain (rule 6)
```

Each is a frozen dataclass; a `reply` field holds where the answer goes (a carrier
replaces it by a token across processes). To add one: define it here, add it to
`DISPATCH` in `actor.py` (docs/explanation/architecture.md, "Adding a message").
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import functools
import traceback
from collections.abc import Callable
from typing import Any, Protocol, TypeAlias

import cloudpickle

from rr_actors._catalog import describe
from rr_actors._core import runtime
from rr_actors._core.directory import DIRECTORY, Reply
from rr_actors._core.replies import FutureReply
from rr_actors._core.wire import WireMessage, plain
from rr_actors._core.workers import Job
from rr_actors._platform import PLATFORM
from rr_actors._types import LoadCallback, Status, StatusCallback, UnloadCallback
from rr_actors.errors import (
    CallTimeoutError,
    ConfigError,
    DependencyCycleError,
    ErrorFrame,
    ResourceLoadError,
    RrError,
    UnknownQueryError,
)

_CLOCK = PLATFORM.monotonic_clock()
"""The name of the clock `time.monotonic()` reads here (`None`: not known): a `Load`'s
deadline crosses as itself to a process that reads the same one."""


@dataclasses.dataclass(frozen=True)
class Load(WireMessage):
    """Consumer -> provider: load `request` on `server` for consumer id `query_id`.
    `chain`: those loading further up (cycles); `life`: the run of `origin_rr` that sent it
    (fenced by a later run's `Reconcile`); `trace`: its CLIENT span's traceparent (`""`:
    none); `deadline`: when its caller gives up (monotonic; `None`: never), crossing as the
    seconds left or, to the same clock, as itself (docs/explanation/inside.md, "The
    provider"); `waits`: asks again after `OverloadedError`. Answer: the response, or an error."""

    query_id: str
    server: str
    request: Any
    origin_rr: str
    chain: tuple[str, ...]
    reply: Reply
    life: str = ""
    trace: str = ""
    deadline: float | None = None
    waits: bool = True

    def __getstate__(self) -> dict[str, Any]:
        """Its fields as it leaves: the deadline as seconds left, and as itself with `_CLOCK`."""
        state = dict(self.__dict__)
        deadline = self.deadline
        if deadline is not None:
            state["deadline"] = deadline - runtime.monotonic()
            if _CLOCK is not None:
                state["clock"] = (_CLOCK, deadline)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        """Its fields as it arrives: the deadline itself on the same clock, else seconds left."""
        left, clock = state.get("deadline"), state.pop("clock", None)
        if left is not None:
            if clock is not None and clock[0] == _CLOCK is not None:
                state["deadline"] = clock[1]
            else:
                state["deadline"] = runtime.monotonic() + left
        self.__dict__.update(state)

    def compensation(self) -> Abandon:
        """A lost answer leaves a consumer id nobody holds: release it (rule 17)."""
        return Abandon(self.query_id, self.origin_rr)

    def unreadable_answer(self, target: str, exc: BaseException) -> RrError:
        """The response cannot be unpickled in the caller's process: a failed load."""
        return ResourceLoadError(
            (
                error_frame(
                    target,
                    self.server,
                    exc,
                    f"the response cannot be unpickled in the process of "
                    f"registrar {self.origin_rr!r}: {exc}",
                ),
            )
        )

    def unsendable_answer(self, target: str, value: Any, exc: BaseException) -> RrError:
        """The response cannot be pickled to reach the caller: a failed load."""
        return ResourceLoadError(
            (
                error_frame(
                    target,
                    self.server,
                    exc,
                    f"the response is not picklable, so it cannot reach "
                    f"registrar {self.origin_rr!r}: {exc} (value: {describe(value)})",
                    with_traceback=False,
                ),
            )
        )


@dataclasses.dataclass(frozen=True)
class Unload(WireMessage):
    """Consumer -> provider: release consumer id `query_id` (`trace`: its CLIENT span's).
    Answer: the statuses still on their way to it (`StatusOnItsWay`s, rule 9), an
    `UnloadOverran` (released, its `unload` overran; or before), or an error (not released)."""

    query_id: str
    origin_rr: str
    reply: Reply
    trace: str = ""


@dataclasses.dataclass(frozen=True)
class Abandon(WireMessage):
    """Consumer -> provider: the caller gave up on `query_id`; release it when possible (if
    `withdrawn`, only what its last `Load` added). Answer (`reply` set): `None`, once done."""

    query_id: str
    origin_rr: str
    reply: Reply | None = None
    withdrawn: bool = False


@dataclasses.dataclass(frozen=True)
class Fetch(WireMessage):
    """Consumer -> provider: list the queries `origin_rr` holds at `server`."""

    server: str
    origin_rr: str
    reply: Reply


@dataclasses.dataclass(frozen=True)
class StatusNotice(WireMessage):
    """Provider -> consumer: a status about the resources behind `query_ids`.
    `event`: one `send_status` (a callback reached twice runs once); `hop`: registrars on the
    way; `sent_at`: wall clock; `patience`: seconds before a callback is given up on (`None`:
    never). Answer: the ids given up on, once delivered along the whole path."""

    query_ids: tuple[str, ...]
    status: Status
    message: str
    source: str
    event: str
    reply: Reply
    hop: int = 1
    sent_at: float = 0.0
    patience: float | None = None


@dataclasses.dataclass(frozen=True)
class StatusBatch(WireMessage):
    """Provider -> another process's registrar: one status per `(registrar, ids)` of `parts`,
    in one pass, the rest as `StatusNotice`. Answer: `({registrar: process key}, given-up ids)`."""

    parts: tuple[tuple[str, tuple[str, ...]], ...]
    status: Status
    message: str
    source: str
    event: str
    reply: Reply
    hop: int = 1
    sent_at: float = 0.0
    patience: float | None = None

    def part(self, parts: tuple[tuple[str, tuple[str, ...]], ...], reply: Reply) -> StatusBatch:
        """The same status for `parts`, answered to `reply`."""
        return StatusBatch(
            parts,
            self.status,
            self.message,
            self.source,
            self.event,
            reply,
            self.hop,
            self.sent_at,
            self.patience,
        )

    def on_its_way(self) -> StatusOnItsWay:
        """This status as an `Unload`'s answer carries it."""
        return StatusOnItsWay(
            self.status, self.message, self.source, self.event, self.hop, self.sent_at
        )


@dataclasses.dataclass(frozen=True)
class StatusOnItsWay:
    """A status sent on to a consumer id, unacknowledged when its `Unload` was answered: the
    answer carries it (rule 9); `event` makes it reach the id once."""

    status: Status
    message: str
    source: str
    event: str
    hop: int
    sent_at: float

    def notice(self, query_ids: tuple[str, ...], reply: Reply) -> StatusNotice:
        """The `StatusNotice` it would have come as, for `query_ids`, answered to `reply`."""
        return StatusNotice(
            query_ids,
            self.status,
            self.message,
            self.source,
            self.event,
            reply,
            self.hop,
            self.sent_at,
        )


@dataclasses.dataclass(frozen=True)
class UnloadOverran:
    """An `Unload` answer: released, but the `unload` overran (`error`), or by an earlier
    `Unload` (an `UnknownQueryError`); with the statuses still on their way (rule 9)."""

    on_its_way: tuple[StatusOnItsWay, ...]
    error: CallTimeoutError | UnknownQueryError


@dataclasses.dataclass(frozen=True)
class Revoke(WireMessage):
    """Provider -> consumer: these consumer ids were released by the provider."""

    query_ids: tuple[str, ...]


@dataclasses.dataclass(frozen=True)
class ResponseUpdated(WireMessage):
    """Provider -> consumer: the stored response of these ids changed. Answer: `None`."""

    query_ids: tuple[str, ...]
    response: Any
    reply: Reply


@dataclasses.dataclass(frozen=True)
class Reconcile(WireMessage):
    """Consumer -> provider: registrar `origin_rr` holds exactly `held` at you (rule 20).
    The provider releases the others of `origin_rr`'s ids, gives up its loads not listed,
    answers `Reconciled` (the listed ids it does not know), and refuses `Load`s of runs
    before `life`. `round`, `ask_life`: the `ReconcileAsk.round` it answers (0: none) and
    that ask's `life` (a round is counted afresh by each run of the provider)."""

    origin_rr: str
    held: tuple[str, ...]
    reply: Reply
    life: str = ""
    round: int = 0
    ask_life: str = ""


@dataclasses.dataclass(frozen=True)
class Reconciled(WireMessage):
    """Provider -> consumer, the answer to a `Reconcile`: the listed ids it does not know
    (nor loads), and `life`, the run that answered. The consumer applies it only if that
    run is the one it reconciles with, alive when the list left (rule 17). A wire type, so
    it crosses by the C pickler as the messages do, not by cloudpickle."""

    unknown: tuple[str, ...]
    life: str


@dataclasses.dataclass(frozen=True)
class ReconcileAsk(WireMessage):
    """Provider -> consumer: `serving_rr` (re)started with ids of yours: send a `Reconcile`
    (`holds_yours=False`: only if you hold ids there). `life`: its run's token. `round`: an
    ask after your name was heard lost (0: another); the answer echoes it. Answer (`reply`
    set, `Unloading.ask_holder`): `None` once heard; an error if you were stopped first."""

    serving_rr: str
    holds_yours: bool = True
    life: str = ""
    round: int = 0
    reply: Reply | None = None


@dataclasses.dataclass(frozen=True)
class LostEverything(WireMessage):
    """Death watch -> a registrar restarted without a backup: send every registrar of the
    system a `Reconcile`, as one restored from a backup does (rule 20)."""


@dataclasses.dataclass(frozen=True)
class ConsumerDown(WireMessage):
    """Death watch -> a registrar of another process: `origin_rr` died (or, `stopped`, was
    stopped) and will not come back; into that process's membership (rule 19)."""

    origin_rr: str
    stopped: bool = False


def give_back(serving_rr: str, query_id: str, origin_rr: str, withdrawn: bool = False) -> None:
    """Tell provider `serving_rr` to release consumer id `query_id` whenever it can: the one
    way an id its caller will not hold is given back. Best effort."""
    with contextlib.suppress(RrError):
        DIRECTORY.lookup(serving_rr).tell(Abandon(query_id, origin_rr, withdrawn=withdrawn))


# -- internal messages (never leave the process) ---------------------------------------


class LoadPlace:
    """A load's place in the queue for a worker (thread-safe): the registrar may `withdraw`
    it, its server actor `take`s it, and sheds it past `deadline` (monotonic; `None`: never)."""

    __slots__ = ("_job", "_lock", "_state", "deadline")

    def __init__(self, deadline: float | None = None) -> None:
        self._lock = runtime.Lock()
        self._state = "sent"  # "sent", "withdrawn", "queued" (`_job`) or "started"
        self._job: Job | None = None
        self.deadline = deadline

    def extend(self, deadline: float | None) -> None:
        with self._lock:
            if self.deadline is not None:
                self.deadline = None if deadline is None else max(self.deadline, deadline)

    def take(self, start: Callable[[], Job | None]) -> None:
        """On the server's thread: `start()` the load unless withdrawn (its job, or `None`)."""
        with self._lock:
            if self._state != "sent":
                return
            self._job = start()
            self._state = "started" if self._job is None else "queued"

    def withdraw(self) -> bool:
        """On the registrar's thread: whether the load was withdrawn before it started."""
        with self._lock:
            if self._state == "sent":
                self._state = "withdrawn"
                return True
            if self._state == "queued" and self._job is not None and self._job.cancel():
                self._state = "withdrawn"
                self._job = None
                return True
            return False


@dataclasses.dataclass(frozen=True)
class RunLoad:
    """Registrar -> its server actor: run `load(request)` unless withdrawn from `place`."""

    resource_id: str
    request: Any
    chain: tuple[str, ...]
    reply: Reply
    place: LoadPlace = dataclasses.field(default_factory=LoadPlace)
    trace: str = ""  # the traceparent its first caller's Load carried: the load runs under it
    origin: str = ""  # its first caller's consumer registrar: its lane for a worker


@dataclasses.dataclass(frozen=True)
class RunUnload:
    """Registrar -> its server actor: run `unload(request, response)`; past `timeout` s the
    reply gets `CallTimeoutError` and the worker is abandoned."""

    request: Any
    response: Any
    reply: Reply
    timeout: float | None = None
    trace: str = ""  # the traceparent of the Unload that caused it: its SERVER span current


@dataclasses.dataclass(frozen=True)
class FetchVia:
    """Handle -> a client actor: fetch the queries this registrar holds at `server`."""

    server: str
    reply: Reply


@dataclasses.dataclass(frozen=True)
class Flush:
    """The save-interval timer fired: write what accumulated."""


@dataclasses.dataclass(frozen=True)
class Crash:
    """Die as if a bug hit (`rr_actors.testing.crash`, a thread manager's forced stop)."""


# -- from the handle (never leave the process) ------------------------------------------
# Each carries its reply, answered through an open reply: a death fails whoever waits.


class Asked(Protocol):
    """A message from the handle whose answer the handle waits for."""

    @property
    def reply(self) -> FutureReply: ...


@dataclasses.dataclass(frozen=True)
class RegisterServer:
    """Register server `name` with its callbacks and bound (`None`: the registrar's
    `max_pending`). Answer: `None`."""

    name: str
    load: LoadCallback
    unload: UnloadCallback
    on_status: StatusCallback | None
    label: Callable[[Any], Any] | None
    reply: FutureReply
    max_pending: int | None = None


@dataclasses.dataclass(frozen=True)
class UnregisterServer:
    """Remove server `name`: FATAL to its consumers, unload what it serves. Answer: `None`."""

    name: str
    reply: FutureReply


@dataclasses.dataclass(frozen=True)
class Release:
    """Release consumer id `query_id` (`begun`: the caller's trace context). Answer: `None`."""

    query_id: str
    reply: FutureReply
    begun: tuple[str, str] | None = None


@dataclasses.dataclass(frozen=True)
class SendStatus:
    """Send a status about the resource behind `query_id`, giving up on callbacks after
    `patience` seconds. Answer: a `StatusDelivery`."""

    query_id: str
    status: Status
    message: str
    reply: FutureReply
    patience: float | None = None


@dataclasses.dataclass(frozen=True)
class ListServerQueries:
    """The queries this registrar's `server` holds. Answer: a list of `Query`."""

    server: str
    reply: FutureReply


@dataclasses.dataclass(frozen=True)
class ListClientQueries:
    """The queries this registrar holds at servers. Answer: a list of `Query`."""

    reply: FutureReply


@dataclasses.dataclass(frozen=True)
class SetStatusCallback:
    """Attach `callback` to query `query_id` this registrar holds. Answer: `None`."""

    query_id: str
    callback: StatusCallback
    reply: FutureReply


@dataclasses.dataclass(frozen=True)
class UpdateResponse:
    """Replace the response behind `query_id`. Answer: `None` once the consumers hold it."""

    query_id: str
    response: Any
    reply: FutureReply


@dataclasses.dataclass(frozen=True)
class Save:
    """Write what the catalog has pending to the backup. Answer: `None`."""

    reply: FutureReply


@dataclasses.dataclass(frozen=True)
class Stop:
    """Stop the registrar (rule 12), waiting for the unloads under way until
    `unloads_until` (monotonic; `None`: no wait). Answer: `None`."""

    reply: FutureReply
    unloads_until: float | None = None


@dataclasses.dataclass(frozen=True)
class Ready:
    """The manager's setup is done: serve. Answer: `None`."""

    reply: FutureReply


@dataclasses.dataclass(frozen=True)
class SettleInDoubt:
    """The in-doubt entry `query_id` (`None`: all) is handled: forget it. Answer: `None`."""

    query_id: str | None
    reply: FutureReply


@dataclasses.dataclass(frozen=True)
class Reachable:
    """A carrier serves the registrar: reconcile with the peers of other processes."""

    reply: Reply


@dataclasses.dataclass(frozen=True)
class PeerLost:
    """Membership: registrar `name` is gone for good (rule 19). The one local message for
    "lost" (`life.Presence`)."""

    name: str


@dataclasses.dataclass(frozen=True)
class PeersStopped:
    """Membership, or its supervisor as the tree's stop reaches it: registrars `names` were
    stopped for good (rule 12), a batch told at once (a tree's stop told a message a name to
    every registrar still running: N x N messages in a tree of N)."""

    names: tuple[str, ...]


@dataclasses.dataclass(frozen=True)
class PeerReachable:
    """A carrier: registrar `name` of another process can be reached again (a healed link)."""

    name: str


@dataclasses.dataclass(frozen=True)
class YieldName:
    """A carrier: another process's registrar of this name is kept (rule 22): unload, stop."""

    reason: str


@dataclasses.dataclass(frozen=True)
class KeepName:
    """A carrier: the one kept went for good while this one yields (rule 22): serve again
    if not stopping (`reply`: `True`), else `False`."""

    reply: Reply


@dataclasses.dataclass(frozen=True)
class KeptUnclaimed:
    """Reconciling's timer: give back those of `query_ids` `serving_rr` keeps for no retry."""

    serving_rr: str
    query_ids: tuple[str, ...]


@dataclasses.dataclass(frozen=True)
class ReconcileRetry:
    """Presence's timer: send `Reconcile` attempt `attempt` of `round` to `name`; with
    `asked`, the `Reconcile` asked of consumer `name` is due (release its ids if absent)."""

    name: str
    round: int
    attempt: int
    asked: bool = False


@dataclasses.dataclass(frozen=True)
class Snapshot:
    """Copy the catalog's rows (`check`: its invariants first). Answer: a `CatalogView`."""

    check: bool
    reply: FutureReply


@dataclasses.dataclass(frozen=True)
class Ping:
    """A manager's heartbeat: answered (`None`) as soon as the actor gets to it."""

    reply: Reply


@dataclasses.dataclass(frozen=True)
class OpenClient:
    """The client actor for `target_rr/server`, started on first use. Answer: its ref."""

    target_rr: str
    server: str
    reply: FutureReply


@dataclasses.dataclass(frozen=True)
class RunOnActor:
    """Test only (`rr_actors.testing`): run `op(actor, reply)` on the actor's thread."""

    op: Callable[[Any, Reply], None]  # (the `RegistrarActor`: no role is imported here)
    reply: Reply


TextFields: TypeAlias = tuple[tuple[str, bool], ...]


@functools.cache
def text_fields(kind: type) -> TextFields:
    fields = dataclasses.fields(kind) if dataclasses.is_dataclass(kind) else ()
    return tuple(
        (f.name, f.type == "str | None") for f in fields if f.type in ("str", "str | None")
    )


# -- what a load callback runs inside --------------------------------------------------


@dataclasses.dataclass(frozen=True)
class LoadContext:
    """What is being loaded on this thread (read by `call` to record dependencies);
    `chain`: the resources being loaded on the way here, this one last."""

    registrar: str
    resource_id: str
    chain: tuple[str, ...]


LOADING: contextvars.ContextVar[LoadContext | None] = contextvars.ContextVar(
    "rr_actors_loading", default=None
)
"""The `LoadContext` of the load callback running on this thread, if any."""


def check_picklable(value: Any, what: str) -> None:
    """`ConfigError` if `value` cannot be stored in a catalog backup (whatever pickling
    raises); small builtin data (`wire.plain`) is not pickled here."""
    if plain(value):  # (it pickles; the backup pickles it again anyway when it stores it)
        return
    try:
        cloudpickle.dumps(value)
    except BaseException as exc:  # (user code: a SystemExit from __reduce__ is contained too)
        raise ConfigError(
            f"{what} cannot be pickled, so the catalog cannot store it: {exc}"
        ) from exc


def exception_text(exc: BaseException) -> str:
    """`str(exc)`, or a placeholder if even that raises (user code too)."""
    try:
        return str(exc)
    except BaseException:  # noqa: BLE001 - the error message must not fail
        return "<str() of the exception raised>"


def error_frame(
    registrar: str,
    server: str,
    exc: BaseException,
    message: str | None = None,
    *,
    with_traceback: bool = True,
) -> ErrorFrame:
    """The frame a failed load adds to a `ResourceLoadError`'s stack: `message` (default
    `str(exc)`), with `exc`'s traceback unless `with_traceback` is false."""
    return ErrorFrame(
        registrar=registrar,
        server=server,
        exc_type=type(exc).__qualname__,
        message=exception_text(exc) if message is None else message,
        traceback="".join(traceback.format_exception(exc)) if with_traceback else "",
    )


def load_error(registrar: str, server: str, exc: BaseException) -> RrError:
    """What a `load` raised as its callers get it (rule 4): a `DependencyCycleError` as is,
    else a `ResourceLoadError` with this registrar's frame."""
    inner: BaseException | None = exc
    while inner is not None and not isinstance(inner, ResourceLoadError | DependencyCycleError):
        inner = inner.__cause__
    if isinstance(inner, DependencyCycleError):
        return inner
    frame = error_frame(registrar, server, exc)
    stack = inner.stack if isinstance(inner, ResourceLoadError) else ()
    return ResourceLoadError((*stack, frame))
