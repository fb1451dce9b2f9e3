"""Messages as data: what registrars tell each other and tell themselves, and what a load runs in.

```
 consumer ── Load Unload Abandon Fetch Reconcile ─────────────────────────► provider
 provider ── StatusBatch StatusNotice Revoke ResponseUpdated ReconcileAsk ─► consumer
 death watch ── ConsumerDown ─► every registrar of the other processes
 death watch ── LostEverything ─► a registrar restarted without a backup
                                              (the wire: `WireMessage`s, they pickle)
 registrar ── RunLoad RunUnload ─► its server actor; handle ── FetchVia ─► a client actor
 timers, carriers, the membership ── Flush Crash Reachable PeerLost PeerReachable
                                     YieldName ReconcileRetry Ping ─► the registrar
 the handle ── RegisterServer Release Stop ... (each with its reply) ─► the registrar
 a caller's thread ── ClientLoaded CallFailed TakeOutcomes ─► the registrar
                                              (the call protocol's own: `calls.py`)

 a load callback's thread: LOADING = LoadContext(registrar, resource, chain)
   ─► a call made there records a dependency (rule 5) and extends the chain (rule 6)
   ─► what it raised: load_error ─► ResourceLoadError, one error_frame per registrar
```

Each is a frozen dataclass. A `reply` field holds where the answer goes: a local object
in-process; a carrier replaces it by a token when the message crosses processes. A
message from the handle carries its reply, and the handle sends it with `_ask`.

To add a message: define it here, add it to the actor's one dispatch table (`DISPATCH`
in `actor.py`: its step name and the role that handles it), and, for a wire message,
make sure what it carries pickles (`docs/explanation/architecture.md`, "Adding a
message").
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
)

__all__ = [
    "LOADING",
    "Abandon",
    "Asked",
    "ConsumerDown",
    "Crash",
    "Fetch",
    "FetchVia",
    "Flush",
    "KeepName",
    "ListClientQueries",
    "ListServerQueries",
    "Load",
    "LoadContext",
    "LoadPlace",
    "LostEverything",
    "OpenClient",
    "PeerLost",
    "PeerReachable",
    "Ping",
    "Reachable",
    "Ready",
    "Reconcile",
    "ReconcileAsk",
    "ReconcileRetry",
    "RegisterServer",
    "Release",
    "ResponseUpdated",
    "Revoke",
    "RunLoad",
    "RunOnActor",
    "RunUnload",
    "Save",
    "SendStatus",
    "SetStatusCallback",
    "SettleInDoubt",
    "Snapshot",
    "StatusBatch",
    "StatusNotice",
    "StatusOnItsWay",
    "Stop",
    "TextFields",
    "Unload",
    "UnloadOverran",
    "UnregisterServer",
    "UpdateResponse",
    "YieldName",
    "check_picklable",
    "error_frame",
    "exception_text",
    "give_back",
    "load_error",
    "misfit",
    "text_fields",
]

_CLOCK = PLATFORM.monotonic_clock()
"""The name of the clock `time.monotonic()` reads here (`None`: not known): a `Load`'s
deadline crosses as itself to a process that reads the same one."""


@dataclasses.dataclass(frozen=True)
class Load(WireMessage):
    """Consumer -> provider: load `request` on `server` for consumer id `query_id`.

    `chain` holds the ids of the resources being loaded further up the call chain
    (for cycle detection). `life`: the run of `origin_rr` that sent it (`Shared.life`;
    "": not known); a provider that heard a `Reconcile` of a later run refuses it
    (presumed abort: that run does not hold the id, `provider.py`'s `Lives`). `trace`:
    the W3C traceparent of the call's CLIENT span (`_core/traces.py`), `""` untraced.
    `deadline`: when its caller gives up (`time.monotonic()` seconds of this process;
    `None`: never), by which a provider sheds a load that cannot finish in time
    (`DeadlineExceededError`). It crosses as the seconds left, as gRPC's `grpc-timeout`
    does (`__getstate__`), and becomes a deadline of the receiving process's clock when
    it is unpickled there (`__setstate__`): the time on the way (in a pipe or socket
    before the receiver reads it) is not counted. So beside it crosses the deadline
    itself with the name of the sender's clock (`Platform.monotonic_clock`: on Linux
    the boot and time namespace), and a receiver that reads the same clock (any process
    of that host) keeps the deadline exact; another host's clock is never compared.
    (Seconds left alone, 21 of 23,164 loads started up to 36 ms after their caller gave
    up under a 10x overload across processes: `bench_overload.py`.) `waits`: whether its
    caller asks again after an `OverloadedError` (`if_overloaded="wait"`): one that does
    not is told when a slot may be free but keeps no place (`provider.Admission`).
    Answer: the response, or an error.
    """

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
        """Its fields as it leaves this process: the deadline as the seconds left, and as
        itself on this process's clock, named (`_CLOCK`), where the platform names it."""
        state = dict(self.__dict__)
        deadline = self.deadline
        if deadline is not None:
            state["deadline"] = deadline - runtime.monotonic()
            if _CLOCK is not None:
                state["clock"] = (_CLOCK, deadline)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        """Its fields as it arrives: the deadline itself if it was taken on this
        process's clock, else the seconds left as a deadline of this process's clock."""
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
    """Consumer -> provider: release consumer id `query_id`.

    Answer: the statuses about it still on their way to the consumer (`StatusOnItsWay`s,
    a tuple, mostly empty: rule 9, a release crossing a status); an `UnloadOverran` when
    the release unloaded the resource and its `unload` overran `unload_timeout` (released
    all the same, so it carries them too); or an error (nothing released). `trace`: the
    W3C traceparent of the unload's CLIENT span (`_core/traces.py`), `""` untraced.
    """

    query_id: str
    origin_rr: str
    reply: Reply
    trace: str = ""


@dataclasses.dataclass(frozen=True)
class Abandon(WireMessage):
    """Consumer -> provider: the caller gave up on `query_id`; release it when possible.

    Answer (to a stopping consumer, which waits for it: `reply` set): `None` once it was
    released here, or was not held."""

    query_id: str
    origin_rr: str
    reply: Reply | None = None


@dataclasses.dataclass(frozen=True)
class Fetch(WireMessage):
    """Consumer -> provider: list the queries `origin_rr` holds at `server`."""

    server: str
    origin_rr: str
    reply: Reply


@dataclasses.dataclass(frozen=True)
class StatusNotice(WireMessage):
    """Provider -> consumer: a status about the resources behind `query_ids`.

    `event` identifies one `send_status` so that a callback reached twice (diamond
    dependencies) runs once; `hop` counts the registrars it reached on the way (1: the
    sender's own consumers) and `sent_at` is when it was sent (wall clock, seconds), for
    the `StatusDelivered` event. `patience`: seconds from its arrival after which a
    callback that has not returned is given up on (`None`: wait for it). Answer: the ids
    given up on, on the way (a tuple, maybe empty), once delivered along the whole path.
    """

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
    """Provider -> a registrar of another process: one status for consumer registrars there.

    `parts` holds (consumer registrar, its query ids) for each registrar of that process
    (as far as the provider knows) that holds the resource; the registrar it is sent to
    delivers them all in one pass (`status.py`). The other fields are a `StatusNotice`'s.
    Answer: `({registrar: its process's key} for every registrar reached, the ids given
    up on)`, once the status was delivered along the whole path.
    """

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
    """A status a provider sent on to a consumer id, not acknowledged yet when that id's
    `Unload` was answered: the answer carries it (rule 9). The other fields are a
    `StatusNotice`'s; `event` makes it reach the id once whichever way comes first."""

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
    """The answer to an `Unload` that released its id, whose resource's `unload` then
    overran `unload_timeout` (`error`, for the consumer's caller): the id is released all
    the same, so the answer carries the statuses still on their way to it (rule 9)."""

    on_its_way: tuple[StatusOnItsWay, ...]
    error: CallTimeoutError


@dataclasses.dataclass(frozen=True)
class Revoke(WireMessage):
    """Provider -> consumer: these consumer ids were released by the provider."""

    query_ids: tuple[str, ...]


@dataclasses.dataclass(frozen=True)
class ResponseUpdated(WireMessage):
    """Provider -> consumer: the stored response of these consumer ids changed.

    Answer: `None` once the consumer's client records hold the new response.
    """

    query_ids: tuple[str, ...]
    response: Any
    reply: Reply


@dataclasses.dataclass(frozen=True)
class Reconcile(WireMessage):
    """Consumer -> provider: registrar `origin_rr` holds exactly `held` at you.

    Sent after a restart of either side (a consumer's start, or a provider's
    `ReconcileAsk`). `held` lists the consumer's client records at this provider, its
    calls whose answer is due, and its calls that failed as this provider died (they may
    be retried with the same id); not the ids whose `Unload` failed so (released). The
    provider releases every consumer id of `origin_rr` it holds that is not in `held`,
    and gives up its loads under way for `origin_rr` that are not in it (an earlier
    run's: presumed abort); it answers with the ids of `held` it neither holds nor has
    a load under way for. `life`: the run of `origin_rr` that sent it (`Shared.life`;
    "": not known): from then on the provider refuses the `Load`s of earlier runs.
    `round`: the `ReconcileAsk.round` it answers (0: none).
    """

    origin_rr: str
    held: tuple[str, ...]
    reply: Reply
    life: str = ""
    round: int = 0


@dataclasses.dataclass(frozen=True)
class ReconcileAsk(WireMessage):
    """Provider -> consumer: `serving_rr` (re)started with ids of yours: send a `Reconcile`.

    With `holds_yours=False` it names none of yours (it tells every registrar of the
    system: its restart may have lost ids you hold): send one only if you hold ids there.
    `life`: a token drawn at each start of `serving_rr` (`Shared.life`), the same in
    every ask of that run ("": not known); the ids it kept for a retry in that life are
    listed again, those an earlier life kept are not (released: rule 17). `round`: a
    provider's ask after your name was heard lost (0: another ask); the answer echoes it.
    """

    serving_rr: str
    holds_yours: bool = True
    life: str = ""
    round: int = 0


@dataclasses.dataclass(frozen=True)
class LostEverything(WireMessage):
    """Death watch -> a registrar its supervisor restarted without a backup: you restarted
    with an empty catalog, so no row names the providers where your last run held ids
    (held there for nobody now): send every registrar of the system a `Reconcile`, as one
    restored from a backup does (rule 20)."""


@dataclasses.dataclass(frozen=True)
class ConsumerDown(WireMessage):
    """Death watch -> a registrar of another process: registrar `origin_rr` died (or, with
    `stopped`, was stopped) and will not come back: the mark on the wire.

    Its receiver feeds it into its process's membership (`life.py`'s presence), which tells
    every registrar there `PeerLost`: the ids `origin_rr` held there are released, and
    (not `stopped`) the ids held at it get `FATAL` and are forgotten (rule 19)."""

    origin_rr: str
    stopped: bool = False


def give_back(serving_rr: str, query_id: str, origin_rr: str) -> None:
    """Tell provider `serving_rr` to release consumer id `query_id` whenever it can.

    The one way a registrar gives an id back that its caller will not hold (a call given
    up, an answer that cannot be kept, a dependency whose resource is gone). Best effort:
    a provider that cannot be reached holds nothing this registrar could release (if it
    died it restores the id, and its consumer's restart or death watch settles it).
    """
    with contextlib.suppress(RrError):
        DIRECTORY.lookup(serving_rr).tell(Abandon(query_id, origin_rr))


# -- internal messages (never leave the process) ---------------------------------------


class LoadPlace:
    """A load's place in the queue for a worker, shared by the registrar (which may
    `withdraw` it: its callers all gave up) and its server actor (which `takes` it).

    `deadline`: when the last of its callers gives up (`time.monotonic()` seconds;
    `None`: one never does), which the server reads as a worker takes the load, to shed
    it if it cannot finish in time (`ServerActor.shed`).

    Thread-safe: the registrar's and the server's threads both use it.
    """

    __slots__ = ("_job", "_lock", "_state", "deadline")

    def __init__(self, deadline: float | None = None) -> None:
        self._lock = runtime.Lock()
        self._state = "sent"  # "sent", "withdrawn", "queued" (`_job`) or "started"
        self._job: Job | None = None
        self.deadline = deadline

    def extend(self, deadline: float | None) -> None:
        """On the registrar's thread: one more caller waits for it, until `deadline`."""
        with self._lock:
            if self.deadline is not None:
                self.deadline = None if deadline is None else max(self.deadline, deadline)

    def take(self, start: Callable[[], Job | None]) -> None:
        """On the server's thread: `start()` the load (its worker job, or `None` if it
        started at once), unless it was withdrawn meanwhile."""
        with self._lock:
            if self._state != "sent":
                return
            self._job = start()
            self._state = "started" if self._job is None else "queued"

    def withdraw(self) -> bool:
        """On the registrar's thread: whether the load was withdrawn before it started
        (it never runs, and its reply is never answered by the server)."""
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
    """Registrar -> its server actor: run `load(request)` for resource `resource_id`
    (unless the registrar withdraws it from `place` before a worker takes it)."""

    resource_id: str
    request: Any
    chain: tuple[str, ...]
    reply: Reply
    place: LoadPlace = dataclasses.field(default_factory=LoadPlace)
    trace: str = ""  # the traceparent its first caller's Load carried: the load runs under it
    origin: str = ""  # its first caller's consumer registrar: its lane for a worker


@dataclasses.dataclass(frozen=True)
class RunUnload:
    """Registrar -> its server actor: run `unload(request, response)`.

    Past `timeout` seconds (`None`: no bound) the reply gets `CallTimeoutError` and the
    callback's worker is abandoned.
    """

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
# Each carries its reply: the handle waits on it (a `FutureReply`), or, for `Reachable`
# and `Ping`, nobody or the manager's control loop does. The actor answers them through an
# open reply, so a death fails whoever still waits.


class Asked(Protocol):
    """A message from the handle whose answer the handle waits for."""

    @property
    def reply(self) -> FutureReply: ...


@dataclasses.dataclass(frozen=True)
class RegisterServer:
    """Register resource server `name` with its callbacks and its bound of new loads
    under way (`None`: the registrar's `max_pending`). Answer: `None`."""

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
    """Release consumer id `query_id` this registrar holds (`unload`). Answer: `None`.

    `begun`: the trace context of the caller of `unload` (`_core/traces.py`'s `begin`)."""

    query_id: str
    reply: FutureReply
    begun: tuple[str, str] | None = None


@dataclasses.dataclass(frozen=True)
class SendStatus:
    """Send a status about the resource behind `query_id`, giving up on callbacks that
    have not returned within `patience` seconds. Answer: a `StatusDelivery`."""

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
    """Replace the response of the resource behind `query_id`. Answer: `None` once the
    consumers hold it too."""

    query_id: str
    response: Any
    reply: FutureReply


@dataclasses.dataclass(frozen=True)
class Save:
    """Write what the catalog has pending to the backup. Answer: `None`."""

    reply: FutureReply


@dataclasses.dataclass(frozen=True)
class Stop:
    """Stop the registrar (rule 12). Answer: `None` once stopped.

    `unloads_until`: until when (`time.monotonic()` seconds, in this process) the stop
    waits for the unloads under way here (`None`: it does not wait).
    """

    reply: FutureReply
    unloads_until: float | None = None


@dataclasses.dataclass(frozen=True)
class Ready:
    """The manager's setup is done: serve. Answer: `None`."""

    reply: FutureReply


@dataclasses.dataclass(frozen=True)
class SettleInDoubt:
    """The manager handled in-doubt entry `query_id` (`None`: all of them): the backup
    forgets it. Answer: `None`."""

    query_id: str | None
    reply: FutureReply


@dataclasses.dataclass(frozen=True)
class Reachable:
    """A carrier serves the registrar: reconcile with the peers of other processes."""

    reply: Reply


@dataclasses.dataclass(frozen=True)
class PeerLost:
    """This process's membership (`rr_actors._core.membership`): registrar `name` is gone
    and nobody will restart it (rule 19), or, with `stopped`, it was stopped for good (it
    holds nothing: rule 12). The one local message for "lost"; handled by `life.py`'s `Presence`."""

    name: str
    stopped: bool = False


@dataclasses.dataclass(frozen=True)
class PeerReachable:
    """A carrier: registrar `name` of another process can be reached again after it could
    not be (a healed link, not a restart). Handled by `life.py`'s `Presence`."""

    name: str


@dataclasses.dataclass(frozen=True)
class YieldName:
    """A carrier: another process serves this registrar's name too and is kept (rule 22);
    the carrier stopped serving this one. It unloads what it serves, then stops (`reason`
    says why). Handled by `life.py`'s `Lifecycle`."""

    reason: str


@dataclasses.dataclass(frozen=True)
class KeepName:
    """A carrier: the registrar kept in this one's place went for good while this one
    yields (rule 22): if it has not begun to stop, it serves its name again once what it
    unloads is gone, and `reply` gets `True`; else `False`. Handled by `life.py`'s
    `Lifecycle`."""

    reply: Reply


@dataclasses.dataclass(frozen=True)
class ReconcileRetry:
    """Presence's own timer: send `Reconcile` attempt `attempt` of round `round` to `name`
    (the last one failed, or was not answered in time). With `asked`: the `Reconcile`
    asked of consumer `name` by round `round` (`Presence.lose`) was due: if it did not
    come, release every id of `name`. Handled by `life.py`'s `Presence`."""

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
"""`(name, may be None)` of a message type's fields declared `str` or `str | None`."""


@functools.cache
def text_fields(kind: type) -> TextFields:
    """The fields of message type `kind` that `misfit` checks (found once a type)."""
    fields = dataclasses.fields(kind) if dataclasses.is_dataclass(kind) else ()
    return tuple(
        (f.name, f.type == "str | None") for f in fields if f.type in ("str", "str | None")
    )


def misfit(message: object, names: TextFields) -> ConfigError | None:
    """A `ConfigError` naming the field of `message` among `names` (`text_fields`) that
    holds something else than a str (`None` if none does).

    A careless caller (`unload(["id"])`) or a buggy peer must not make a registrar die of
    a `TypeError` deep in a handler (an unhashable id, a name `difflib` cannot read): the
    registrar refuses the message instead. Only the value's type is shown: its `repr` is
    a peer's code.
    """
    for name, optional in names:
        value = getattr(message, name)
        if (
            type(value) is not str
            and not isinstance(value, str)
            and not (optional and value is None)
        ):
            return ConfigError(
                f"{name} must be a str{' or None' * optional}, not "
                f"{type(value).__qualname__[:80]} ({type(message).__name__} refused)"
            )
    return None


# -- what a load callback runs inside --------------------------------------------------


@dataclasses.dataclass(frozen=True)
class LoadContext:
    """What is being loaded on the current thread (read by `call` to record dependencies):
    `chain` holds the ids of the resources being loaded on the way here, this one last."""

    registrar: str
    resource_id: str
    chain: tuple[str, ...]


LOADING: contextvars.ContextVar[LoadContext | None] = contextvars.ContextVar(
    "rr_actors_loading", default=None
)
"""The `LoadContext` of the load callback running on this thread, if any."""


def check_picklable(value: Any, what: str) -> None:
    """Raise `ConfigError` if `value` cannot be stored in a catalog backup.

    Whatever pickling it raises (a user `__reduce__` raising `SystemExit` too) is that.
    Small builtin data (`wire.plain`: most requests and responses) is not pickled here.
    """
    if plain(value):  # (it pickles; the backup pickles it again anyway when it stores it)
        return
    try:
        cloudpickle.dumps(value)
    except BaseException as exc:  # (user code: a SystemExit from __reduce__ is contained too)
        raise ConfigError(
            f"{what} cannot be pickled, so the catalog cannot store it: {exc}"
        ) from exc


def exception_text(exc: BaseException) -> str:
    """`str(exc)`, or a placeholder if even that raises (it is user code too: a
    `SystemExit` from `__str__` is contained as well)."""
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
    """The frame a failed load adds to a `ResourceLoadError`'s stack (the one builder):
    `message` says what failed (`str(exc)` by default), with `exc`'s formatted traceback
    unless `with_traceback` is false."""
    return ErrorFrame(
        registrar=registrar,
        server=server,
        exc_type=type(exc).__qualname__,
        message=exception_text(exc) if message is None else message,
        traceback="".join(traceback.format_exception(exc)) if with_traceback else "",
    )


def load_error(registrar: str, server: str, exc: BaseException) -> RrError:
    """Turn what a `load` callback raised into the error its callers get (rule 4).

    A `DependencyCycleError` raised further down passes through unchanged; anything else
    becomes a `ResourceLoadError` whose stack gains this registrar's frame.
    """
    inner: BaseException | None = exc
    while inner is not None and not isinstance(inner, ResourceLoadError | DependencyCycleError):
        inner = inner.__cause__
    if isinstance(inner, DependencyCycleError):
        return inner
    frame = error_frame(registrar, server, exc)
    stack = inner.stack if isinstance(inner, ResourceLoadError) else ()
    return ResourceLoadError((*stack, frame))
