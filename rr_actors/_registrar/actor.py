"""The registrar actor: the only writer of its catalog, split into roles.

```
              ┌──────────────────── RegistrarActor (one mailbox, one thread) ───────────────┐
 message ───► │ handlers: type -> (step name, role method)                                   │
              │   Provider   Load                        (provider.py, matching.py)          │
              │   Unloading  Unload Abandon ConsumerDown Reconcile       (unloading.py)      │
              │   Servers    Fetch; register, unregister, update         (servers.py)        │
              │   Consumer   Pending ClientLoaded CallFailed Revoke ResponseUpdated          │
              │              ReconcileAsk                                 (consumer.py)      │
              │   StatusRelay StatusNotice                               (status.py)         │
              │   Lifecycle  Request Flush Crash; start, stop, death     (lifecycle.py)      │
              │ Shared: config, catalog, saver, servers, phase, workers  (state.py)          │
              └──────────────────────────────────────────────────────────────────────────────┘
```

It never blocks: what it needs from another actor arrives later as a message that
resumes the work (`Shared.send`, `Join`). User callbacks run on worker threads, so a
slow or hung callback never blocks the mailbox.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

from rr_actors._catalog import Catalog
from rr_actors._core.actor import Actor
from rr_actors._core.bus import Publisher
from rr_actors._core.directory import DIRECTORY, LocalPeer
from rr_actors._core.replies import Answer
from rr_actors._registrar.calls import DueAnswers
from rr_actors._registrar.consumer import Consumer
from rr_actors._registrar.lifecycle import Lifecycle
from rr_actors._registrar.messages import (
    Abandon,
    CallFailed,
    ClientLoaded,
    ConsumerDown,
    Crash,
    Fetch,
    Flush,
    Load,
    Pending,
    Reconcile,
    ReconcileAsk,
    Request,
    ResponseUpdated,
    Revoke,
    StatusNotice,
    Unload,
)
from rr_actors._registrar.provider import Provider
from rr_actors._registrar.servers import Servers
from rr_actors._registrar.state import Shared
from rr_actors._registrar.status import StatusRelay
from rr_actors._registrar.unloading import Unloading
from rr_actors._store import Saver
from rr_actors.config import RegistrarConfig
from rr_actors.errors import RegistrarUnavailableError, RrError
from rr_actors.events import Event

__all__ = ["RegistrarActor"]

logger = logging.getLogger("rr_actors")


class RegistrarActor(Actor):
    """The registrar actor: dispatches each message to the role that owns it.

    Attributes:
        shared: the state every role uses.
        provider, unloading, servers, consumer, status, lifecycle: the roles.
    """

    def __init__(
        self,
        config: RegistrarConfig,
        catalog: Catalog,
        saver: Saver,
        peer: LocalPeer,
        died: threading.Event,
        due: DueAnswers,
        ended: threading.Event,
        published: Publisher[Event],
        *,
        setting_up: bool = False,
    ) -> None:
        super().__init__()
        self.shared = Shared(config, catalog, saver, peer, published, setting_up=setting_up)
        # Each role is built after the roles it calls, and calls only those (one way):
        # lifecycle -> servers -> status | unloading -> provider -> consumer.
        self.consumer = Consumer(self.shared, due, self.on_receive)
        self.provider = Provider(self.shared, self.consumer)
        self.unloading = Unloading(self.shared, self.provider)
        self.status = StatusRelay(self.shared, self.consumer)
        self.servers = Servers(self.shared, self.provider, self.status)
        self.lifecycle = Lifecycle(
            self.shared, self.provider, self.unloading, self.consumer, self, died, ended
        )
        tokens = self.shared.tokens
        self.handlers: dict[type, tuple[str, Callable[[Any], None]]] = {
            Answer: ("answer", lambda m: tokens.answer(m.token, m.value, m.error)),
            Load: ("load", self.provider.on_load),
            Unload: ("unload", self.unloading.on_unload),
            Abandon: ("abandon", self.unloading.on_abandon),
            Fetch: ("fetch", self.servers.on_fetch),
            ConsumerDown: ("consumer_down", self.unloading.on_consumer_down),
            Reconcile: ("reconcile", self.unloading.on_reconcile),
            ReconcileAsk: ("reconcile_ask", self.consumer.on_reconcile_ask),
            StatusNotice: ("status_notice", self.status.on_status_notice),
            Revoke: ("revoke", self.consumer.on_revoke),
            ResponseUpdated: ("response_updated", self.consumer.on_response_updated),
            Pending: ("pending", self.consumer.on_pending),
            ClientLoaded: ("client_loaded", self.consumer.on_client_loaded),
            CallFailed: ("call_failed", self.consumer.on_call_failed),
            Request: ("request", self.lifecycle.on_request),
            Flush: ("flush", self.lifecycle.on_flush),
            Crash: ("crash", self.lifecycle.on_crash),
        }

    @property
    def name(self) -> str:
        """The registrar's name."""
        return self.shared.name

    def on_start(self) -> None:
        self.shared.ref = self.actor_ref
        self.shared.peer.ref = self.actor_ref
        self.lifecycle.on_start()

    def on_receive(self, message: Any) -> None:
        entry = self.handlers.get(type(message))
        if entry is None:
            logger.warning("registrar %s ignored an unknown message %r", self.name, message)
            return
        step, handle = entry
        probes = self.shared.probes
        try:
            if probes is None:
                handle(message)
            else:
                probes.around(step, message, handle)
        except RrError as exc:  # e.g. a restored value that cannot be decoded any more
            reply = getattr(message, "reply", None)
            if reply is not None:
                reply.set_error(exc)  # that request fails; the registrar keeps serving
            else:
                logger.exception("registrar %s: %s failed", self.name, type(message).__name__)
        except BaseException as exc:  # (not only Exception: see `ContainedError`)
            reply = getattr(message, "reply", None)
            if reply is not None:  # a bug: the actor dies, but its caller hears of it now
                reply.set_error(
                    RegistrarUnavailableError(
                        f"registrar {self.name!r} died in its {step} step: {exc!r}"
                    )
                )
            raise

    def on_failure(self, *_: object) -> None:
        self.lifecycle.die()

    def on_ended(self) -> None:
        self.lifecycle.ended.set()

    def on_late(self, envelope: Any) -> None:
        """A message that arrived after this actor's loop ended (any thread)."""
        self.lifecycle.refuse(envelope, DIRECTORY.gone_error(self.name))
