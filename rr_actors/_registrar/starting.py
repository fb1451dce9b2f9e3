"""Starting a registrar: its catalog restored, its actor started (before any handle).

`launch` is the start protocol up to a running actor: the name is claimed in this
process's directory, the catalog is opened (restored from its backup if there is one),
what the restore left in doubt is listed, and the actor is started with the shared
signals its handle waits on. If anything fails, the name and the backup are let go.
`ResourceRegistrar.start` (in `handle.py`) wraps what it returns in a handle and runs the
manager's `setup`. `Served` is how a carrier sees a started registrar.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import pykka

from rr_actors import events
from rr_actors._catalog import ResourceState
from rr_actors._core.actor import OneShotFuture
from rr_actors._core.bus import Publisher
from rr_actors._core.directory import DIRECTORY, LocalPeer
from rr_actors._core.replies import FutureReply
from rr_actors._platform import fork
from rr_actors._registrar.actor import RegistrarActor
from rr_actors._registrar.calls import DueAnswers
from rr_actors._registrar.endpoints import Clients
from rr_actors._registrar.messages import PeerLost, PeerReachable, Reachable, YieldName
from rr_actors._store import Saver, open_catalog
from rr_actors._types import Query
from rr_actors.config import RegistrarConfig
from rr_actors.errors import ConfigError, RegistrarStoppedError

__all__ = [
    "EVENT_LOG",
    "Launched",
    "Network",
    "Servable",
    "Served",
    "check_network",
    "launch",
    "serve_on",
]

EVENT_LOG = logging.getLogger("rr_actors.events")
"""Where registrars log their events at INFO (one line per event; off by default)."""


@dataclass(frozen=True, slots=True)
class Launched:
    """A registrar actor just started, and what its handle shares with it."""

    config: RegistrarConfig
    ref: pykka.ActorRef[RegistrarActor]
    restored: bool
    """Whether its catalog was restored from a backup."""
    in_doubt: tuple[Query, ...]
    """Resources the restore found neither loaded nor unloaded (thesis 4.3.3)."""
    due: DueAnswers
    died: threading.Event
    """Set when a crash of the actor was fully handled."""
    ended: OneShotFuture[None]
    """Settled when the actor handed on its last message (an event loop awaits it)."""
    published: Publisher[events.Event]
    clients: Clients
    """Its client actors: the actor starts them, the handle looks them up."""
    in_doubt_texts: tuple[tuple[str, str | None], ...] = ()
    """Each in-doubt resource's id and its stored request display text (`display.py`)."""


def launch(
    config: RegistrarConfig | str,
    *,
    setting_up: bool,
    upstream: Publisher[events.Event] | None,
    hold_in_doubt: bool = False,
) -> Launched:
    """Restore the catalog and start the actor (on the calling thread).

    Args:
        config: a `RegistrarConfig`, or just a name.
        setting_up: whether a `setup` runs before it serves others (loads wait for it).
        upstream: a publisher its events are relayed to as well (a supervisor's tree).
        hold_in_doubt: keep the in-doubt entries in the backup until the manager settles
            them (`ResourceRegistrar.settle_in_doubt`; a `setup` runs first).

    Raises:
        DuplicateNameError: a registrar with this name is already running here.
        CatalogCorruptError: the backup exists but cannot be read (it is left as is).
        ConfigError: the configuration, or its backup path, is invalid; or this process
            was forked from one whose state a child cannot use (`rr_actors._platform.fork`).
    """
    if isinstance(config, str):
        config = RegistrarConfig(name=config)
    elif not isinstance(config, RegistrarConfig):
        raise ConfigError(f"config must be a RegistrarConfig or a name, got {config!r}")
    fork.check_usable(f"registrar {config.name!r}")
    durable = config.save_on_modify and config.backup_path is not None
    peer = LocalPeer(config.name, None, durable=durable)
    DIRECTORY.register(peer)
    saver: Saver | None = None
    try:
        saver, catalog, restored = open_catalog(config)
        doubtful = [r for r in catalog.resources.values() if r.state is not ResourceState.LOADED]
        in_doubt = tuple(
            Query(r.id, r.server, config.name, config.name, r.request, r.response) for r in doubtful
        )
        in_doubt_texts = tuple((r.id, r.request_text) for r in doubtful)
        ended: OneShotFuture[None] = OneShotFuture()
        died, due, clients = threading.Event(), DueAnswers(), Clients()
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
        )
    except BaseException:
        if saver is not None:
            saver.close(erase=False, flush=False)
        DIRECTORY.unregister(peer, "stopped")
        raise
    return Launched(
        config, ref, restored, in_doubt, due, died, ended, published, clients, in_doubt_texts
    )


class Network(Protocol):
    """What `ResourceRegistrar.start(network=)` needs of a carrier: to serve a registrar.

    Every carrier's `Transport` is one (`rr_actors._transport.base`; the registrar layer
    does not import the carriers). `serve` returns once the other processes of the
    system can reach the registrar, and the carrier stops serving it by itself when the
    registrar stops or dies.
    """

    def serve(self, endpoint: Served) -> None:
        """Make the registrar reachable from the other processes (and hosts) of the system.

        Raises:
            DuplicateNameError: another process of the system serves that name.
            ConfigError: the carrier cannot serve it.
            RegistrarStoppedError: this process left the system.
        """
        ...


class ActorHere(Protocol):
    """How `Served` reaches a started registrar's actor (`handle.Here` is one)."""

    def tell(self, message: Any) -> bool:
        """Send the actor `message` without waiting; whether the actor was running."""
        ...

    def wait_stopped(self, timeout: float | None = None) -> bool:
        """Block until the actor's thread ended (stopped or died); whether it did."""
        ...


class Servable(Protocol):
    """What a carrier's `Served` uses of a started registrar (`handle.ResourceRegistrar`
    is one; this module comes before the handle, so it names it by this only)."""

    @property
    def name(self) -> str:
        """The registrar's name."""
        ...

    @property
    def config(self) -> RegistrarConfig:
        """The configuration it was started with."""
        ...

    def is_alive(self) -> bool:
        """Whether the registrar actor is running."""
        ...

    def stop(self, *, timeout: float | None = None) -> None:
        """Stop the registrar (rule 12)."""
        ...

    @property
    def _actor(self) -> ActorHere:
        """Its actor, in this process."""
        ...


def check_network(network: object) -> None:
    """Raise `ConfigError` naming `network` unless it is `None` or has a `serve` method."""
    if network is not None and not callable(getattr(network, "serve", None)):
        raise ConfigError(
            f"network must be a carrier's Transport (an AF_UNIX System, a ZenohNetwork) "
            f"or None, got {network!r}"
        )


def serve_on(network: Network, registrar: Servable) -> None:
    """Serve `registrar` on `network`; if that fails, stop it and raise what failed."""
    try:
        network.serve(Served(registrar))
    except BaseException:
        registrar.stop()
        raise


class Served:
    """A registrar of this process as a carrier serves it (`rr_actors._transport.base.Endpoint`).

    Args:
        registrar: the registrar to make reachable from the other processes of a system.
    """

    __slots__ = ("registrar",)

    def __init__(self, registrar: Servable) -> None:
        self.registrar = registrar

    @property
    def name(self) -> str:
        """The registrar's name."""
        return self.registrar.name

    @property
    def max_message_bytes(self) -> int:
        """Its config's `max_message_bytes`: the carrier bounds its connections by it."""
        return self.registrar.config.max_message_bytes

    def run(self, fn: Callable[[Any], Any]) -> Any:
        """Run `fn(registrar)` on the calling thread."""
        return fn(self.registrar)

    def wait_ended(self, timeout: float | None = None) -> bool:
        """Block until the registrar actor ended (stopped or died); whether it did."""
        return self.registrar._actor.wait_stopped(timeout)

    def stopped_cleanly(self) -> bool:
        """Whether it ended because its owner stopped it (not a crash, not still running)."""
        if self.registrar.is_alive():
            return False
        return isinstance(DIRECTORY.gone_error(self.registrar.name), RegistrarStoppedError)

    def listening(self) -> None:
        """The other processes of the system can reach it now: it reconciles with its peers
        again (those in other processes could not answer it before)."""
        self.registrar._actor.tell(Reachable(FutureReply()))  # (nobody waits: `serve` must not)

    def peer_lost(self, name: str) -> None:
        """Registrar `name` of another process is gone for good (rule 19): `presence.py`."""
        self.registrar._actor.tell(PeerLost(name))

    def peer_reachable(self, name: str) -> None:
        """Registrar `name` of another process answers again (a healed link): `presence.py`."""
        self.registrar._actor.tell(PeerReachable(name))

    def yield_name(self, reason: str) -> None:
        """Another process's registrar of this name is kept (rule 22): this one unloads
        what it serves and stops (`lifecycle.py`)."""
        self.registrar._actor.tell(YieldName(reason))
