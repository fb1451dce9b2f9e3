"""The registrar actor: started (`launch`), its parts built, each message dispatched.

```
 launch(config): the name claimed, the catalog opened (restored), the actor started

              ┌─────────────────── RegistrarActor (one mailbox, one thread) ───────────────┐
 message ───► │ the call outcomes handed over before it are taken first (`calls.py`)      │
              │ DISPATCH: type ─► (step name, the part's on_<step>)                        │
              │  life.py      Lifecycle, Restoring, Presence                              │
              │  provider.py  Provider, Unloading, Servers, Teardown                      │
              │  status.py    StatusRelay                                                 │
              │  consumer.py  Answers, Holdings, Releases, Reconciling, Flights           │
              │  state.py     Shared: config, catalog, saver, servers, phase, workers      │
              └────────────────────────────────────────────────────────────────────────────┘
```

The actor fills one record (`life.RegistrarRecord`: `Shared` widened by each side's
parts) and builds each part from it alone; a part reaches another through the record,
and only the parts of its own module and the modules below (a layers contract in
`pyproject.toml`).
The actor never blocks: what it needs from another actor arrives later as a message
(`Shared.send`, `Join`), and user callbacks run on worker threads. Every clause of
`DISPATCH` is `on_<step>(message, reply)`; the step names are what
`rr_actors.testing.intercept` accepts. A durable registrar commits once per turn
(docs/explanation/architecture.md, "One turn's transaction").
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import pykka

from rr_actors import events
from rr_actors._catalog import Catalog
from rr_actors._catalog.texts import plain_text
from rr_actors._core import runtime
from rr_actors._core.actor import Actor, OneShotFuture
from rr_actors._core.bus import Publisher
from rr_actors._core.directory import DIRECTORY, LocalPeer, Reply
from rr_actors._core.replies import Answer, Tokens
from rr_actors._core.throttle import LogThrottle
from rr_actors._platform import forkserver
from rr_actors._registrar.calls import (
    CallFailed,
    ClientLoaded,
    DueAnswers,
    DurableLoaded,
    TakeOutcomes,
)
from rr_actors._registrar.consumer import Answers, Clients, Flights, Holdings, Reconciling, Releases
from rr_actors._registrar.display import ClientTexts
from rr_actors._registrar.life import Lifecycle, Presence, RegistrarRecord, Restoring, cut_short
from rr_actors._registrar.messages import (
    Abandon,
    ConsumerDown,
    Crash,
    Fetch,
    Flush,
    KeepName,
    KeptUnclaimed,
    ListClientQueries,
    ListServerQueries,
    Load,
    LostEverything,
    OpenClient,
    PeerLost,
    PeerReachable,
    PeersStopped,
    Ping,
    Reachable,
    Ready,
    Reconcile,
    ReconcileAsk,
    ReconcileRetry,
    RegisterServer,
    Release,
    ResponseUpdated,
    Revoke,
    RunOnActor,
    Save,
    SendStatus,
    SetStatusCallback,
    SettleInDoubt,
    Snapshot,
    StatusBatch,
    StatusNotice,
    Stop,
    TextFields,
    Unload,
    UnregisterServer,
    UpdateResponse,
    YieldName,
    text_fields,
)
from rr_actors._registrar.provider import Lives, Provider, Servers, Teardown, Unloading
from rr_actors._registrar.state import NO_REPLY, POINTS, OpenReply, new_life
from rr_actors._registrar.status import DESK, StatusRelay, StatusTargets, Unacknowledged
from rr_actors._store import Saver, open_catalog
from rr_actors._types import Query
from rr_actors.config import RegistrarConfig
from rr_actors.errors import ConfigError, RegistrarUnavailableError, RrError
from rr_actors.events import Event

logger = logging.getLogger("rr_actors")


DRAIN = 64
"""Messages a durable registrar takes into one turn at most (`Actor.drain`)."""

DRAIN_SECONDS = 0.02
"""Seconds after a turn's first message past which no more are taken into that turn."""


Handler = Callable[[Any, Reply], None]
"""`handle(message, reply)`, run on the actor's thread: `reply` is the message's own (held
open for a message from the handle, `asked`), or `NO_REPLY`."""

Binder = Callable[[RegistrarRecord], Handler]
"""What makes a `Handler` of one actor from its record (run once, when it is built): a
part's `on_<step>`."""


def asked(bind: Binder) -> Binder:
    """A clause for a message from the handle, with an open reply (a death fails it); an
    `RrError` the handler raises is its caller's answer."""

    def bound(record: RegistrarRecord) -> Handler:
        handle = bind(record)
        open_requests, shared = record.open_requests, record

        def handle_asked(message: Any, reply: Reply) -> None:
            opened = OpenReply(reply, open_requests, shared)
            try:
                handle(message, opened)
            except RrError as exc:
                opened.set_error(exc)

        return handle_asked

    return bound


def _answering(tokens: Tokens) -> Handler:
    return lambda m, _reply: tokens.answer(m.token, m.value, m.error)


def _taken(_message: TakeOutcomes, _reply: Reply) -> None:
    """The outcomes waiting were taken before this message (`RegistrarActor.on_receive`)."""


def _answer_now(_message: Ping, reply: Reply) -> None:
    reply.set_result(None)


def _run_on_actor(record: RegistrarRecord) -> Handler:
    return lambda message, reply: message.op(record.actor, reply)


DISPATCH: dict[type, tuple[str, Binder]] = {
    # message: (step name, its handler). The step names are `rr_actors.testing.STEPS`.
    # A subclass of a message here is handled by its clause (`DurableLoaded`).
    # -- between registrars (the wire protocol) --
    Load: ("load", lambda a: a.provider.on_load),  # at the provider
    Unload: ("unload", lambda a: a.unloading.on_unload),  # at the provider
    Abandon: ("abandon", lambda a: a.unloading.on_abandon),  # at the provider
    Fetch: ("fetch", lambda a: a.registry.on_fetch),  # at the provider
    ConsumerDown: ("consumer_down", lambda a: a.presence.on_consumer_down),  # death watch
    Reconcile: ("reconcile", lambda a: a.unloading.on_reconcile),  # a consumer lists its ids
    ReconcileAsk: ("reconcile_ask", lambda a: a.presence.on_reconcile_ask),  # provider restarted
    LostEverything: ("lost_everything", lambda a: a.reconciling.on_lost_everything),  # no backup
    # -- from a carrier's presence callbacks (`Served`) --
    PeerLost: ("peer_lost", lambda a: a.presence.on_peer_lost),  # gone, nobody restarts it
    PeersStopped: ("peers_stopped", lambda a: a.presence.on_peers_stopped),  # the tree's stop
    PeerReachable: ("peer_reachable", lambda a: a.presence.on_peer_reachable),  # link healed
    ReconcileRetry: ("reconcile_retry", lambda a: a.presence.on_reconcile_retry),  # its timer
    KeptUnclaimed: ("kept_unclaimed", lambda a: a.reconciling.on_kept_unclaimed),  # its timer
    YieldName: ("yield_name", lambda a: a.lifecycle.on_yield_name),  # rule 22: another kept
    KeepName: ("keep_name", lambda a: a.lifecycle.on_keep_name),  # the kept one went meanwhile
    StatusBatch: ("status_batch", lambda a: a.status.on_status_batch),  # at a relay
    StatusNotice: ("status_notice", lambda a: a.status.on_status_notice),  # at a consumer
    Revoke: ("revoke", lambda a: a.holdings.on_revoke),  # at a consumer
    ResponseUpdated: ("response_updated", lambda a: a.holdings.on_response_updated),
    # -- from this registrar's callers' threads and its own helpers --
    ClientLoaded: ("client_loaded", lambda a: a.answers.on_client_loaded),  # an answer to record
    CallFailed: ("call_failed", lambda a: a.answers.on_call_failed),  # failed or withdrawn
    TakeOutcomes: ("take_outcomes", lambda _a: _taken),  # (taken before each message)
    Answer: ("answer", lambda a: _answering(a.tokens)),  # to one of its own questions
    Flush: ("flush", lambda a: a.lifecycle.on_flush),  # the save-interval timer fired
    Crash: ("crash", lambda a: a.lifecycle.on_crash),  # `rr_actors.testing.crash`
    # -- from the handle (`handle.py`), each answered through its reply --
    RegisterServer: ("register_server", asked(lambda a: a.registry.on_register_server)),
    UnregisterServer: ("unregister_server", asked(lambda a: a.registry.on_unregister_server)),
    Release: ("release", asked(lambda a: a.releases.on_release)),
    SendStatus: ("send_status", asked(lambda a: a.status.on_send_status)),
    ListServerQueries: ("server_queries", asked(lambda a: a.registry.on_list_server_queries)),
    ListClientQueries: ("client_queries", asked(lambda a: a.holdings.on_list_client_queries)),
    SetStatusCallback: ("set_status_callback", asked(lambda a: a.holdings.on_set_status_callback)),
    UpdateResponse: ("update_response", asked(lambda a: a.registry.on_update_response)),
    Save: ("save", asked(lambda a: a.lifecycle.on_save)),
    Stop: ("stop", asked(lambda a: a.lifecycle.on_stop)),
    Ready: ("ready", asked(lambda a: a.lifecycle.on_ready)),  # setup is done
    SettleInDoubt: ("settle_in_doubt", asked(lambda a: a.restoring.on_settle_in_doubt)),
    Reachable: ("reachable", asked(lambda a: a.lifecycle.on_reachable)),  # a carrier
    Snapshot: ("snapshot", asked(lambda a: a.lifecycle.on_snapshot)),
    Ping: ("ping", asked(lambda _a: _answer_now)),  # a manager process's heartbeat
    OpenClient: ("open_client", asked(lambda a: a.holdings.on_open_client)),
    RunOnActor: ("run_on_actor", asked(_run_on_actor)),  # test only
}
"""The one dispatch table: which part handles each message, under which step name."""

TEXT_FIELDS: dict[type, TextFields] = {kind: text_fields(kind) for kind in DISPATCH}
"""Each message's text fields, made at import: in a forkserver's preload once, not at
each manager process's start (42 dataclass walks a registrar)."""


def _misfit(message: object, names: TextFields) -> ConfigError | None:
    """A `ConfigError` naming a field of `names` not a str in `message` (refused, not fatal)."""
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


MESSAGE_STEPS: frozenset[str] = frozenset(step for step, _ in DISPATCH.values())
"""Steps that handle one message on the actor's thread (`before`/`after` it)."""

STEPS: frozenset[str] = MESSAGE_STEPS | POINTS
"""Every name `rr_actors.testing.intercept` accepts: the message steps and the points."""


class RegistrarActor(Actor):
    inline = frozenset({Load, Unload, Abandon, DurableLoaded})
    """What a carrier's receiving thread handles in the registrar's turn when it is idle
    (`_core.actor.deliver`): short steps that run user code only on workers."""

    shared: RegistrarRecord
    """The registrar's record: each part holds it, owns its own piece of it and reaches
    another part through it (as trio's `Runner` holds its collaborators)."""

    def __init__(
        self,
        config: RegistrarConfig,
        catalog: Catalog,
        saver: Saver,
        peer: LocalPeer,
        died: runtime.Event,
        due: DueAnswers,
        ended: OneShotFuture[None],
        published: Publisher[Event],
        clients: Clients,
        *,
        setting_up: bool = False,
        hold_in_doubt: bool = False,
        life: str = "",
        announced: bool = False,
    ) -> None:
        super().__init__()
        record = self.shared = RegistrarRecord(
            config, catalog, saver, peer, published, setting_up=setting_up, life=life
        )
        record.announced, record.actor, record.redeliver = announced, self, self.dispatch
        record.open_requests, record.lives = {}, Lives()
        record.died, record.ended, record.due, record.clients = died, ended, due, clients
        targets = StatusTargets(config.name, published, due)  # what the status desk reads
        DESK.serve(peer, targets)
        record.targets = targets.entries
        record.texts = ClientTexts(record)  # made by the answers, read by a snapshot
        record.unacked = Unacknowledged()  # statuses on their way, an Unload's answer carries
        # each part built from the record alone; it calls the parts of its own module and
        # of the modules below (life.py -> provider.py -> status.py -> consumer.py)
        record.flights, record.holdings = Flights(record), Holdings(record)
        record.answers, record.releases = Answers(record), Releases(record)
        record.reconciling, record.status = Reconciling(record), StatusRelay(record)
        record.teardown, record.provider = Teardown(record), Provider(record)
        record.unloading, record.registry = Unloading(record), Servers(record)
        record.presence = Presence(record)
        record.restoring = Restoring(record, hold_in_doubt=hold_in_doubt)
        record.lifecycle = Lifecycle(record)
        if saver.durable:  # the messages waiting commit together (`Shared.end_turn`)
            self.drain, self.drain_seconds, self.ends_turns = DRAIN, DRAIN_SECONDS, True
        self.handlers: dict[type, tuple[str, Handler, TextFields]] = {
            kind: (step, bind(self.shared), TEXT_FIELDS[kind])
            for kind, (step, bind) in DISPATCH.items()
        }

    @functools.cached_property  # (built at the first: a start needs none)
    def unknown(self) -> LogThrottle:  # the lines of messages a buggy peer sends
        return LogThrottle(logger)

    @property
    def name(self) -> str:
        return self.shared.name

    def on_start(self) -> None:
        self.shared.ref = self.shared.peer.ref = self.actor_ref
        self.shared.lifecycle.on_start()
        # every step from now on runs in a turn whose end commits it (`on_turn_end`)
        self.shared.in_turn = self.ends_turns

    def on_receive(self, message: Any) -> None:
        if not self.shared.due.outcomes.empty():  # call outcomes handed over before
            self.shared.flights.take_outcomes()  # this message: recorded first (`calls.py`)
        self.dispatch(message)

    def dispatch(self, message: Any) -> None:
        entry = self.handlers.get(type(message)) or self.inherited(type(message))
        if entry is None:  # (shown without running its __repr__: a peer's object)
            text = plain_text(message) or f"<a {type(message).__qualname__[:80]} object>"
            self.unknown.warning("registrar %s ignored an unknown message %s", self.name, text)
            return
        step, handle, texts = entry
        if (to := getattr(message, "reply", None)) is None:  # where its answer goes
            to = NO_REPLY
        # e.g. `unload(["id"])`: refused, not fatal (a message with no text field: no check)
        if texts and (wrong := _misfit(message, texts)) is not None:
            if to is NO_REPLY:
                self.unknown.warning("registrar %s ignored a message: %s", self.name, wrong)
            else:
                to.set_error(wrong)
            return
        probes = self.shared.probes
        try:
            if probes is None:
                handle(message, to)
            else:
                probes.around(step, message, lambda m: handle(m, to))
        except RrError as exc:  # e.g. a restored value that cannot be decoded any more
            if to is not NO_REPLY:
                to.set_error(exc)  # that request fails; the registrar keeps serving
            else:
                logger.exception("registrar %s: %s failed", self.name, type(message).__name__)
        except BaseException as exc:  # (not only Exception: see `ContainedError`)
            if to is not NO_REPLY:  # a bug: the actor dies, but its caller hears of it now
                to.set_error(
                    RegistrarUnavailableError(
                        f"registrar {self.name!r} died in its {step} step: {exc!r}"
                    )
                )
            raise

    def inherited(self, kind: type) -> tuple[str, Handler, TextFields] | None:
        """The clause of a subclass of a message in `DISPATCH` (`DurableLoaded`), kept for its
        next one; `None` for an unknown message."""
        for base in kind.__mro__[1:-1]:  # (not the class itself, nor `object`)
            entry = self.handlers.get(base)
            if entry is not None:
                step, handle, _ = entry
                entry = self.handlers[kind] = (step, handle, text_fields(kind))
                return entry
        return None

    def on_turn_end(self) -> None:
        shared = self.shared
        if shared.dirty or shared.staged:
            shared.end_turn()

    def on_failure(self, *_: object) -> None:
        self.shared.in_turn = False  # (nothing is staged any more: what is, is refused)
        self.shared.lifecycle.die()

    def on_ended(self) -> None:
        error = DIRECTORY.gone_error(self.name)  # outcomes left, or handed over later:
        self.shared.due.outcomes.close(lambda m: self.shared.lifecycle.refuse_message(m, error))
        self.shared.ended.set(None)

    def on_late(self, envelope: Any) -> None:
        self.shared.lifecycle.refuse(envelope, DIRECTORY.gone_error(self.name))


# -- starting --------------------------------------------------------------------------


EVENT_LOG = logging.getLogger("rr_actors.events")
"""Where registrars log their events at INFO (one line per event; off by default)."""


@dataclass(frozen=True, slots=True)
class Launched:
    config: RegistrarConfig
    ref: pykka.ActorRef[RegistrarActor]
    restored: bool
    in_doubt: tuple[Query, ...]
    """Resources the restore found neither loaded nor unloaded (thesis 4.3.3)."""
    due: DueAnswers
    died: runtime.Event
    ended: OneShotFuture[None]
    """Settled when the actor handed on its last message (an event loop awaits it)."""
    published: Publisher[events.Event]
    clients: Clients
    in_doubt_texts: tuple[tuple[str, str | None], ...] = ()
    life: str = ""
    """Its run (`Shared.life`): each `Load` its calls send carries it."""
    """Each in-doubt resource's id and its stored request display text (`display.py`)."""


def launch(
    config: RegistrarConfig | str,
    *,
    setting_up: bool,
    upstream: Publisher[events.Event] | None,
    hold_in_doubt: bool = False,
    announced: bool = False,
) -> Launched:
    """Restore the catalog and start the actor (on the calling thread).

    `setting_up`: a `setup` runs before it serves others; `upstream`: a publisher its
    events are relayed to as well; `hold_in_doubt`: keep in-doubt entries in the backup
    until the manager settles them; `announced`: its supervisor tells the system of its
    (re)starts (`Shared.announced`).

    Raises:
        DuplicateNameError: a registrar with this name is already running here.
        CatalogCorruptError: the backup exists but cannot be read (it is left as is).
        ConfigError: the configuration or its backup path is invalid; or this process
            was forked from one whose state a child cannot use.
    """
    if isinstance(config, str):
        config = RegistrarConfig(name=config)
    elif not isinstance(config, RegistrarConfig):
        raise ConfigError(f"config must be a RegistrarConfig or a name, got {config!r}")
    forkserver.check_usable(f"registrar {config.name!r}")
    durable = config.save_on_modify and config.backup_path is not None
    peer = LocalPeer(config.name, None, durable=durable)
    DIRECTORY.register(peer)
    saver: Saver | None = None
    try:
        saver, catalog, restored = open_catalog(config)
        catalog.shares = config.steps.shares  # (the catalog's step: `Catalog.shares`)
        doubtful = cut_short(catalog, config.steps)
        in_doubt = tuple(
            Query(r.id, r.server, config.name, config.name, r.request, r.response) for r in doubtful
        )
        in_doubt_texts = tuple((r.id, r.request_text) for r in doubtful)
        ended: OneShotFuture[None] = OneShotFuture()
        died, due, clients = runtime.Event(), DueAnswers(), Clients()
        life = new_life()  # this run: the actor's, and its handle's calls carry it
        published = events.publisher(EVENT_LOG)
        published.relay_to(upstream)
        ref = RegistrarActor.start(
            config,
            catalog,
            saver,
            peer,
            died,
            due,
            ended,
            published,
            clients,
            setting_up=setting_up,
            hold_in_doubt=hold_in_doubt,
            life=life,
            announced=announced,
        )
    except BaseException:
        if saver is not None:
            saver.close(erase=False, flush=False)
        DIRECTORY.unregister(peer, "stopped")
        raise
    return Launched(
        config, ref, restored, in_doubt, due, died, ended, published, clients, in_doubt_texts, life
    )
