"""Presence: what a registrar does when a carrier says a peer is lost for good, or back.

A carrier (the AF_UNIX one on one machine, Zenoh across hosts) watches the other
processes of the system and calls its endpoints' presence callbacks
(`rr_actors._transport.base.Endpoint`); this role is the one place that decides what
they mean for the catalog:

```
 carrier ── Endpoint.peer_lost(name) ──► PeerLost ──► on_peer_lost        (DESIGN rule 19)
     as a provider: every id `name` held here is released (each `unload` runs once),
                    as the death watch's `ConsumerDown` does
     as a consumer: the ids held at `name` get `FATAL` (and up their dependents), then
                    they are forgotten
 carrier ── Endpoint.peer_reachable(name) ──► PeerReachable ──► on_peer_reachable
     as a consumer: `Reconcile` with `name` (what either side released or lost meanwhile)
     as a provider: `ReconcileAsk` to `name` when it holds ids here
```

A provider that its supervisor restarts is not lost (rule 15): its restored catalog
keeps its consumers' ids, and it reconciles itself when it serves again (`lifecycle.py`).
"""

from __future__ import annotations

import logging

from rr_actors._core.directory import DIRECTORY
from rr_actors._registrar.consumer import Consumer
from rr_actors._registrar.messages import PeerLost, PeerReachable, ReconcileAsk
from rr_actors._registrar.state import Shared
from rr_actors._registrar.unloading import Unloading
from rr_actors.errors import RrError

__all__ = ["Presence"]

logger = logging.getLogger("rr_actors")


class Presence:
    """The registrar's answers to a carrier's presence callbacks (runs on the actor thread).

    Args:
        registrar: the state every role shares.
        unloading: releases the ids a lost consumer held here.
        consumer: reports and forgets the ids held at a lost provider; reconciles.
    """

    def __init__(self, registrar: Shared, unloading: Unloading, consumer: Consumer) -> None:
        self.registrar = registrar
        self.unloading = unloading
        self.consumer = consumer

    def on_peer_lost(self, message: PeerLost) -> None:
        if message.name == self.registrar.name:
            return
        self.unloading.release_all_of(message.name)
        self.consumer.lose_provider(message.name)

    def on_peer_reachable(self, message: PeerReachable) -> None:
        name = message.name
        if name == self.registrar.name:
            return
        if self.consumer.holds_at(name):
            self.consumer.reconcile(name)
        if self.registrar.catalog.consumers_from(name):
            try:
                DIRECTORY.lookup(name).tell(ReconcileAsk(self.registrar.name))
            except RrError as exc:
                logger.debug(
                    "registrar %s: %s not reachable yet: %s", self.registrar.name, name, exc
                )
