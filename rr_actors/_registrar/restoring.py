"""What a restored catalog needs once: in-doubt entries settled, unheld resources swept.

```
 lifecycle.py on_start ──► settle_in_doubt: each resource a crash cut short (rule 16)
                            ──► its dependencies released (releases.py), then forgotten
                               (teardown.py); held out of the backup while setup runs
                           ──► each call in flight (or dependency of a resource gone)
                               given back, forgotten with its QueryForgotten("in doubt")
                               (holdings.py)
                           ──► unload_unheld ──► sweep(0): one slice per turn of the
                               mailbox (`Catalog.sweep`): unheld resources unloaded
                               (teardown.py), the consumers holding ids noted
 SettleInDoubt (the manager) ──► on_settle_in_doubt: written off in the backup
 lifecycle.py reconcile ──► ask_consumers: ReconcileAsk to the consumers noted
                            (unloading.py), now or once the sweep is done
```

The in-doubt ids and the sweep's progress are this role's state; the phase, the stop
and the death are `lifecycle.py`'s.
"""

from __future__ import annotations

import functools
import logging

from rr_actors import events
from rr_actors._catalog import ResourceState
from rr_actors._core.directory import Reply
from rr_actors._registrar.holdings import Holdings
from rr_actors._registrar.messages import SettleInDoubt, give_back
from rr_actors._registrar.releases import Releases
from rr_actors._registrar.state import Phase, Shared
from rr_actors._registrar.teardown import Teardown
from rr_actors._registrar.unloading import Unloading
from rr_actors.errors import RrError, UnknownQueryError

__all__ = ["Restoring"]

logger = logging.getLogger("rr_actors")


class Restoring:
    """Settles what the last run left in doubt, and sweeps the restored catalog.

    Attributes:
        hold_in_doubt: keep the settling of in-doubt entries out of the backup until
            the manager settles them (a `setup` runs).
        in_doubt_ids: the ids of the resources found in doubt at the restore.
        sweeping: slices of the restored catalog are still to be swept.
        swept_origins: registrars holding ids in what was swept.
        reconcile_owed: `ask_consumers` came during the sweep.
    """

    def __init__(
        self,
        shared: Shared,
        unloading: Unloading,
        teardown: Teardown,
        releases: Releases,
        holdings: Holdings,
        *,
        hold_in_doubt: bool = False,
    ) -> None:
        self.registrar = shared
        self.unloading = unloading
        self.teardown = teardown
        self.releases = releases
        self.holdings = holdings
        self.hold_in_doubt = hold_in_doubt
        self.in_doubt_ids: frozenset[str] = frozenset()
        self.sweeping = False
        self.swept_origins: set[str] = set()
        self.reconcile_owed = False

    def settle_in_doubt(self) -> None:
        """Drop restored resources whose load or unload a crash cut short (rule 16).

        They were reported to the manager as `in_doubt`; what they held as dependencies
        is released, so nothing they started at other servers leaks. A top-level call that
        was in flight is given up at its provider (its caller died with the last run), and
        so is a dependency whose resource is gone (a sub-call that outlived its load).
        With `hold_in_doubt` (a `setup` runs), their rows stay in the backup as they were
        until the manager settles them (`on_settle_in_doubt`).
        """
        catalog = self.registrar.catalog
        doubtful = [r for r in catalog.resources.values() if r.state is not ResourceState.LOADED]
        self.in_doubt_ids = frozenset(r.id for r in doubtful)
        if self.hold_in_doubt:
            self.registrar.held_in_doubt.update(self.in_doubt_ids)
        for resource in doubtful:
            if self.registrar.events.active:
                self.registrar.events.publish(
                    events.InDoubt(
                        self.registrar.name,
                        resource.id,
                        resource.server,
                        "load" if resource.state is ResourceState.LOADING else "unload",
                    )
                )
            catalog.begin_unload(resource.id)
            self.releases.release_dependencies(
                resource.id, functools.partial(self.teardown.remove_resource, resource)
            )
        for record in list(catalog.clients.values()):
            orphan = record.parent is not None and record.parent not in catalog.resources
            if orphan or (record.parent is None and not record.loaded):
                query = record.query
                give_back(query.serving_rr, query.id, self.registrar.name)
                self.holdings.forget(query.id, commit=False, reason="in doubt")
        self.registrar.commit()

    def unload_unheld(self) -> None:
        """Unload restored resources that no consumer holds (rule 7).

        Their last consumer left (or every caller of their load gave up) and that was
        written, but a crash came before their unload began (it is written apart): no
        one holds an id to release them, so without this they would stay loaded, and
        hold their dependencies at other registrars, for good. Their unload runs once
        setup registered their server (or they are dropped if it does not).
        """
        for resource in self.registrar.catalog.unheld():
            self.teardown.unload_resource(resource, None)
        self.sweep(0)

    def sweep(self, after: int) -> None:
        """Sweep the restored resources still in the backup, one slice per turn.

        Each slice (`Catalog.sweep`: `SWEEP_ROWS` resources, a few ms) unloads those no
        consumer holds (as `unload_unheld`) and notes the registrars holding ids in it
        (whom `ask_consumers` asks); the next slice is a message to itself, behind what
        arrived meanwhile, so calls are served between slices. A restart reads these
        rows after it serves, not before: a catalog of one slice is swept at once.
        """
        if self.registrar.phase in (Phase.STOPPING, Phase.ENDED):
            return
        try:
            unheld, origins, next_slice = self.registrar.catalog.sweep(after)
            self.swept_origins |= origins
            for resource in unheld:
                self.teardown.unload_resource(resource, None)
            if next_slice is not None:
                self.sweeping = True
                self.registrar.come_back(lambda _v, _e: self.sweep(next_slice)).set_result(None)
                return
        except RrError as exc:  # a damaged row: a lookup that needs it fails then
            logger.error(  # noqa: TRY400 - the cause says it all
                "registrar %s: the sweep of its restored catalog stopped: %s",
                self.registrar.name,
                exc,
            )
        self.sweeping = False
        if self.reconcile_owed:
            self.reconcile_owed = False
            self.unloading.ask_to_reconcile(self.swept_origins)

    def ask_consumers(self) -> None:
        """It serves: ask every consumer holding ids here for the ids it holds
        (`ReconcileAsk`); while the sweep is under way, once it is done (the sweep
        names the consumers to ask)."""
        if self.sweeping:
            self.reconcile_owed = True
        else:
            self.unloading.ask_to_reconcile(self.swept_origins)

    def on_settle_in_doubt(self, message: SettleInDoubt, reply: Reply) -> None:
        """The manager handled in-doubt entry `query_id` (`None`: every one): write it off.

        Its row leaves the backup now (or as it was left: its dependencies may still be
        being released); a later restore no longer offers it. Settling one twice is a
        no-op. A write that fails is the caller's error (`CatalogWriteError`): the entry
        stays settled in memory, and the next write that succeeds takes it out.
        """
        query_id = message.query_id
        if query_id is None:
            rids = set(self.in_doubt_ids)
        elif query_id in self.in_doubt_ids:
            rids = {query_id}
        else:
            reply.set_error(
                UnknownQueryError(
                    f"{query_id!r} is not in doubt at registrar {self.registrar.name!r}"
                )
            )
            return
        failed = self.registrar.settle_held(rids)  # (a failed write stays pending: the
        if failed is not None:  # next commit writes it; until then a restart offers it again)
            reply.set_error(failed)
            return
        reply.set_result(None)
