"""The provider's side of a run: one pass over each provider's catalog as its events tell it
(`kept`, `unload-once`, `no-leak`, `one-resource`, `release-match`, `in-doubt`, `dedup`,
`restore-first`), `unload-order`, `dependency-held`, `doubt-reported`, `shed-needed`,
`overload-paced`, `share-needed` and `share-kept`.

```
 steps (_history.walk) ──► Providers.run: per registrar a Catalog, a handler per event kind
                              ├─► findings
                              ├─► holdings: (provider, query id) -> when each life held it
                              └─► expected: who a status should reach (`status-reached`)
 steps ──► unload_order: each resource's dependencies forgotten before its ResourceUnloaded
 steps ──► dependency_held: those dependencies kept while their resource has a consumer
 steps ──► doubt_reported: each row restored loading or unloading reported or unloaded
 history ──► shed_needed: each load shed with nothing ahead against its server's load times
 steps ──► overload_paced: each server's ServerOverloaded at its bound, a second apart a life
 steps ──► share_needed: each ShareRefused past the consumer's share, or behind others waiting
 steps ──► share_kept: each ShareAdmitted under the consumer's share, a slot left for those ahead
 history ──► undigested: each load of a run of plain requests carries its digest (`dedup`)
```

Every lookup is a dict's: a run of a million events is checked in one linear pass.
Each rule's windows and what it excuses: docs/how-to/check-a-run.md.
"""

from __future__ import annotations

import dataclasses
import operator
import re
from collections import defaultdict
from collections.abc import Callable, Sequence
from typing import Any

from rr_actors import events
from rr_actors._types import Status
from rr_actors_lab.experiments._history import Facts, Finding, Life, Line, Step

__all__ = [
    "PROVIDER_ENDED",
    "Expected",
    "Holding",
    "Providers",
    "dependency_held",
    "doubt_reported",
    "overload_paced",
    "share_kept",
    "share_needed",
    "shed_needed",
    "unload_order",
]


@dataclasses.dataclass(slots=True)
class _Held:
    resource_id: str
    consumer: str
    line: int
    stamp: int  # (of its ConsumerAdded, or of the restore that listed it first)


@dataclasses.dataclass(slots=True)
class Holding:
    """One life of a provider holding a query id (for `reported-lost` and `fetch`).

    Attributes:
        life: the provider's life.
        since: the stamp it began holding it (its `ConsumerAdded`, or the restore).
        line: that event's line.
        until: the stamp it let it go (released, in doubt, or its catalog taken again
            at the next life), `None` if it held it to the end of the run.
        server: the provider's server that held it (`""`: not known).
    """

    life: int
    since: int
    line: int
    until: int | None = None
    server: str = ""


@dataclasses.dataclass(frozen=True, slots=True)
class Expected:
    """A holder a status should reach (for `status-reached`).

    Attributes:
        status_id: the status (its `StatusSent.status_id`).
        query_id: the holder's query id.
        holder: the consumer registrar that holds it.
        hop: the hop it should reach it at.
        sender: the registrar that sent it on to it (the provider, or the consumer of
            the dependency it climbed from).
        life: the sender's life then.
        since: the stamp of the send (`StatusSent`, or the delivery it climbs from).
        line: that event's line.
    """

    status_id: str
    query_id: str
    holder: str
    hop: int
    sender: str
    life: int
    since: int
    line: int


@dataclasses.dataclass(slots=True)
class _Catalog:
    """What the events say one provider registrar holds now."""

    pid: int | None = None
    life: int = -1
    held: dict[str, _Held] = dataclasses.field(default_factory=dict)  # query id -> ...
    holders: dict[str, dict[str, None]] = dataclasses.field(default_factory=dict)
    # resource id -> its held query ids
    live: dict[str, tuple[str, int | None, int]] = dataclasses.field(default_factory=dict)
    # resource id -> (server, digest, line): matched by equal requests
    digests: dict[tuple[str, int], dict[str, None]] = dataclasses.field(default_factory=dict)
    # (server, digest) -> its live resource ids
    unloaded: dict[str, int] = dataclasses.field(default_factory=dict)  # rid -> line
    pending: dict[str, tuple[int, bool]] = dataclasses.field(default_factory=dict)
    # resource id -> (line its last holder was released, whether a restore showed it)
    blind: bool = False  # the last restore listed no rows: who holds what is not known

    def forget_all(self) -> None:
        self.held.clear()
        self.holders.clear()
        self.live.clear()
        self.digests.clear()
        self.pending.clear()

    def make_live(self, rid: str, server: str, digest: int | None, line: int) -> None:
        self.live[rid] = (server, digest, line)
        if digest is not None:
            self.digests.setdefault((server, digest), {})[rid] = None

    def not_live(self, rid: str) -> None:
        found = self.live.pop(rid, None)
        if found is not None and found[1] is not None:
            self.digests.get((found[0], found[1]), {}).pop(rid, None)


class Providers:
    """The provider pass: feed it every step (`run`), then read its findings.

    Args:
        facts: what the whole run says (`_history.Facts`).
        lives: each registrar's lives (`_history.walk`).
        lost_backups: the lines of the restores of a backup a fault deleted or damaged
            (`_supervision_rules.damaged_backup`): an id they lost is kept if its consumer
            lets it go (`let_go_of`: told `FATAL` at its reconcile, its own release, or
            its call failed).
        heard_from_start: whether each registrar's first life was heard from its start
            (`check`'s).
    """

    def __init__(
        self,
        facts: Facts,
        lives: dict[tuple[str, int], Life] | None = None,
        lost_backups: set[int] | None = None,
        *,
        heard_from_start: bool = True,
    ) -> None:
        self.lost_backups = lost_backups or set()
        self.heard_from_start = heard_from_start  # (`False`: first lives' starts unheard)
        self.with_backup = facts.with_backup
        self.forgets = facts.forgets
        self.release_stamps = facts.released
        self.lives = lives or {}
        self.fatal_at = facts.fatal_at
        self.parent = facts.parent
        self.watch = facts.lost | facts.fetched
        self.outcomes = facts.outcomes
        self.held_on = facts.held_on
        self.releasing = facts.releasing
        self.catalogs: dict[str, _Catalog] = defaultdict(_Catalog)
        self._by_name: dict[str, list[Life]] | None = None  # each registrar's lives
        self.findings: list[Finding] = []
        self.holdings: dict[tuple[str, str], list[Holding]] = defaultdict(list)
        self.server_of: dict[tuple[str, str], str] = {}  # (provider, resource id) -> server
        self.expected: list[Expected] = []

    def found(self, rule: str, message: str, lines: tuple[int, ...], *names: str) -> None:
        self.findings.append(Finding(rule, "violation", message, lines, names))

    def run(self, steps: list[Step]) -> None:
        """Replay every step on its registrar's catalog."""
        handlers = _HANDLERS
        catalogs = self.catalogs
        for name, line, event, new, life in steps:
            catalog = catalogs[name]
            if new:
                self.begin(name, catalog, line, event, life)
            handler = handlers.get(type(event))
            if handler is not None:
                handler(self, name, catalog, line, event)

    # -- lives -------------------------------------------------------------------------------

    def begin(self, name: str, catalog: _Catalog, line: int, event: Any, life: int) -> None:
        """A new life of `name`: it restores first, or it lost what it held."""
        restoring = isinstance(event, events.CatalogRestored)
        if name in self.with_backup and not restoring and (life or self.heard_from_start):
            self.found(
                "restore-first",
                f"{name} (pid {event.pid}) published {type(event).__name__} before its "
                f"CatalogRestored",
                (line,),
                name,
            )
        if not restoring and catalog.pid is not None:
            ended = self.ended(name, catalog.life, event.hlc)
            unheld = {
                q
                for q, held in catalog.held.items()
                if self.failed(q, held.stamp, event.hlc)
                or self.crossed(name, q, ended)
                or self.added_again(name, q, life)
            }
            # (forgotten since the end of the life before, by no release that crossed the
            # restart: owed a FATAL; the restart's first event may come much later)
            self.lose(
                name, catalog, unheld, line, event.hlc, "in a restart without a backup", ended
            )
            self.let_go_all(name, catalog, event.hlc)
            catalog.forget_all()
            catalog.blind = False
        catalog.pid = event.pid
        catalog.life = life

    def failed(self, qid: str, since: int, stamp: int) -> bool:
        """Whether the call of `qid`, added at `since`, had failed for its caller at `stamp`, which
        so held no id (rule 17; a failed retry of an id it held leaves it held)."""
        outcomes = [(at, held) for at, held in self.outcomes.get(qid, ()) if at > since]
        before = [held for at, held in outcomes if at < stamp]
        if before:
            return not before[-1]
        return bool(outcomes) and not outcomes[0][1]

    def added_again(self, name: str, qid: str, life: int) -> bool:
        """Whether `name`'s restart, in its `life`, added `qid` again: its consumer's retry of
        the id it held (the same id) was answered there, so its reconcile found it known (a
        due id is reconciled again once its call ends, rule 20): no `FATAL` is owed."""
        record = self.lives.get((name, life))
        if record is None:
            return False
        end = record.last if record.end is None else record.end
        added = self.held_on.get(qid, ())
        return any(by == name and record.start <= at <= end for at, by, _rid, _line in added)

    def ended(self, name: str, life: int, restart: int) -> int:
        """The stamp before which no consumer can have reconciled with the restart after `life`: its
        end if its exit or stop shows it, else its last event."""
        record = self.lives.get((name, life))
        if record is None:
            return 0
        if record.end is not None and record.end < restart:
            return record.end
        return record.last

    def crossed(self, name: str, qid: str, ended: int) -> bool:
        """Whether the consumer forgot `qid` on the answer to a release sent before it reconciled
        with `name`'s restart after `ended`: it let it go, no `FATAL` is owed (rule 20)."""
        released = self.release_stamps.get((name, qid))
        return released is not None and released[1] < ended

    def died_before(self, consumer: str, stamp: int, since: int, qid: str = "") -> bool:
        """Whether `consumer`'s life that held an id since `since` ended (killed without a backup,
        as `kill_program` does, or a manager restarted empty) before `stamp`: its last releases'
        events may be lost, and no `FATAL` is owed (its next life holds nothing of it)."""
        if consumer in self.with_backup:
            return False
        begun = [life for life in self.lives_of(consumer) if life.start < stamp]
        if not begun:
            return False
        # (the life that held it: the first not ended when it was added)
        holding = [life for life in begun if life.end is None or life.end >= since]
        if not holding and any(held for at, held in self.outcomes.get(qid, ()) if at > since):
            return False  # (none: a dead life's call, unless a life shown later got its answer)
        start = operator.attrgetter("start")
        last = min(holding, key=start) if holding else max(begun, key=start)
        followed = any(life.start > last.start for life in self.lives_of(consumer))
        return followed and last.last < stamp and last.end is not None

    def released_before_kill(self, name: str, consumer: str, qid: str, stamp: int) -> bool:
        """Whether `consumer` had committed `qid`'s release before a kill: its restore lists it
        as a dependency of a resource it was unloading, its life before showed nothing after
        `stamp` (`name`'s restore), and it forgot `qid` after. Its `Unload` may have left
        before the kill and been committed by `name`, whose events of it died with it (a
        program killed with its managers, `kill_program`: `simprogram` seed 215); its restart
        finished the unload, which `name` no longer knew."""
        at = self.releasing.get((consumer, qid))
        if at is None or (name, qid) not in self.forgets:
            return False
        lives = self.lives_of(consumer)
        after = next((i for i, life in enumerate(lives) if life.start == at), 0)
        return after > 0 and lives[after - 1].last < stamp <= self.forgets[name, qid][0]

    def let_go_before(self, name: str, qid: str, stamp: int) -> bool:
        """Whether `qid`'s consumer forgot it at `name` before `stamp` and held it no more
        since: no call of that id was answered after (called again, it is held anew)."""
        last = max((at for at in self.forgets.get((name, qid), ()) if at < stamp), default=None)
        return last is not None and not any(
            held for at, held in self.outcomes.get(qid, ()) if last < at < stamp
        )

    def let_go_of(self, name: str, qid: str) -> bool:
        """Whether `qid`'s consumer let it go of its own: forgot it, or its last call of it
        failed (it never held it: a lost backup's id nobody must be told of)."""
        calls = self.outcomes.get(qid)
        return (name, qid) in self.forgets or (calls is not None and not max(calls)[1])

    def lives_of(self, name: str) -> list[Life]:
        """`name`'s lives, in order."""
        if self._by_name is None:
            self._by_name = defaultdict(list)
            for (each, _number), record in sorted(self.lives.items()):
                self._by_name[each].append(record)
        return self._by_name.get(name, [])

    def lose(
        self,
        name: str,
        catalog: _Catalog,
        spared: set[str],
        line: int,
        stamp: int,
        why: str,
        let_go_by: int | None = None,
    ) -> None:
        """`kept`: the ids a restart lost (all but `spared`) are violations, unless their consumer
        was told `FATAL` since, or forgot them before `let_go_by`."""
        let_go_by = stamp if let_go_by is None else let_go_by
        for qid, held in catalog.held.items():
            if qid in spared:
                continue
            # its consumer had let it go: the release was committed, and the kill came
            # before its `ConsumerReleased` was published (the restore shows the commit)
            if self.let_go_before(name, qid, let_go_by):
                continue
            # (its forget is shown, after: it lived to let it go, its events were not lost)
            shown = any(at >= let_go_by for at in self.forgets.get((name, qid), ()))
            if not shown and self.died_before(held.consumer, stamp, held.stamp, qid):
                continue
            if self.released_before_kill(name, held.consumer, qid, stamp):
                continue
            if not any(told >= held.stamp for told in self.fatal_at.get(qid, ())):
                self.found(
                    "kept",
                    f"{name}: query {qid[:8]} of {held.consumer} (resource "
                    f"{held.resource_id[:8]}) was lost {why}, neither released nor "
                    f"reported FATAL",
                    (held.line, line),
                    name,
                    held.consumer,
                )

    # -- who holds what ----------------------------------------------------------------------

    def hold(self, name: str, catalog: _Catalog, held: _Held, qid: str) -> None:
        """`qid` is held on `held.resource_id` (again, if it was held there: a retry; one
        held on another resource was let go first)."""
        again = qid in catalog.held
        catalog.held[qid] = held
        catalog.holders.setdefault(held.resource_id, {})[qid] = None
        catalog.pending.pop(held.resource_id, None)
        if not again and (name, qid) in self.watch:
            server = self.server_of.get((name, held.resource_id), "")
            self.holdings[name, qid].append(
                Holding(catalog.life, held.stamp, held.line, server=server)
            )

    def let_go(self, name: str, catalog: _Catalog, qid: str, stamp: int) -> _Held | None:
        held = catalog.held.pop(qid, None)
        if held is None:
            return None
        ids = catalog.holders.get(held.resource_id)
        if ids is not None:
            ids.pop(qid, None)
            if not ids:
                del catalog.holders[held.resource_id]
        if (name, qid) in self.watch:
            for holding in self.holdings[name, qid]:
                if holding.until is None:
                    holding.until = stamp
        return held

    def let_go_all(self, name: str, catalog: _Catalog, stamp: int) -> None:
        for qid in [q for q in catalog.held if (name, q) in self.watch]:
            self.let_go(name, catalog, qid, stamp)

    # -- one handler per event kind ----------------------------------------------------------

    def restored(self, name: str, catalog: _Catalog, line: int, event: Any) -> None:
        if not event.complete:
            self.findings.append(
                Finding(
                    "kept",
                    "unverifiable",
                    f"{name} restored more rows than are listed ({event.counts})",
                    (line,),
                    (name,),
                )
            )
            self.let_go_all(name, catalog, event.hlc)
            catalog.forget_all()
            catalog.blind = True
            return
        self.same_digests(name, catalog, line, event)
        kept = {row[0] for row in event.consumers}
        if line in self.lost_backups:  # (every id lost: each consumer forgets its own)
            kept |= {qid for qid in catalog.held if self.let_go_of(name, qid)}
        self.lose(name, catalog, kept, line, event.hlc, "in a restore")
        before = {qid: (held.line, held.stamp) for qid, held in catalog.held.items()}
        pending = dict(catalog.pending)
        self.let_go_all(name, catalog, event.hlc)
        catalog.forget_all()
        catalog.blind = False
        for row in event.resources:
            self.server_of[name, row[0]] = row[1]
        for qid, rid, consumer, *_ in event.consumers:
            was, at = before.get(qid, (line, event.hlc))
            self.hold(name, catalog, _Held(rid, consumer, was, at), qid)
        for row in event.resources:
            rid = row[0]
            if len(row) > 4 and row[4]:  # reported FATAL: matched no more
                continue
            catalog.make_live(rid, row[1], int(row[3]) if len(row) > 3 and row[3] else None, line)
        # what no consumer holds is unloaded once it serves (its sweep); what was being
        # unloaded is reported in doubt; what is not listed was unloaded (its event lost
        # to the kill)
        for row in event.resources:
            rid = row[0]
            if rid not in catalog.holders and row[2] == "loaded":
                catalog.pending[rid] = (pending[rid][0] if rid in pending else line, True)

    def same_digests(self, name: str, catalog: _Catalog, line: int, event: Any) -> None:
        """`kept`: a resource restored live has the digest it was loaded with (a backup of
        another digest scheme has its digests recomputed on open: else no equal request
        matches it again)."""
        for row in event.resources:
            was = catalog.live.get(row[0])
            if was is None or was[1] is None or len(row) < 4 or not row[3]:
                continue
            if int(row[3]) != was[1]:
                self.found(
                    "kept",
                    f"{name}: resource {row[0][:8]} ({row[1]}) restored with digest {row[3]}, "
                    f"loaded with {was[1]}: an equal request no longer matches it",
                    (was[2], line),
                    name,
                )

    def loaded(self, name: str, catalog: _Catalog, line: int, event: Any) -> None:
        if event.digest is not None:
            twins = catalog.digests.get((event.server, event.digest))
            if twins:
                rid = next(iter(twins))
                self.found(
                    "dedup",
                    f"{name}/{event.server}: equal requests loaded twice ({rid[:8]} still "
                    f"live when {event.resource_id[:8]} loaded)",
                    (catalog.live[rid][2], line),
                    name,
                )
        catalog.make_live(event.resource_id, event.server, event.digest, line)
        self.server_of[name, event.resource_id] = event.server

    def load_failed(self, name: str, catalog: _Catalog, line: int, event: Any) -> None:
        catalog.not_live(event.resource_id)
        catalog.pending.pop(event.resource_id, None)

    def status_sent(self, name: str, catalog: _Catalog, line: int, event: Any) -> None:
        about = catalog.held.get(event.query_id)
        if about is None:
            return
        if event.status is Status.FATAL:  # dead: an equal request loads a new one (rule 1)
            catalog.not_live(about.resource_id)
        if event.status_id:
            self.expect(name, catalog, about.resource_id, event, 1, line)

    def status_delivered(self, name: str, catalog: _Catalog, line: int, event: Any) -> None:
        """A delivery to a dependency climbs to the holders of the resource it is one of."""
        rid = self.parent.get((name, event.query_id))
        if rid is not None and event.status_id:
            self.expect(name, catalog, rid, event, event.hop + 1, line)

    def expect(
        self, name: str, catalog: _Catalog, rid: str, event: Any, hop: int, line: int
    ) -> None:
        for qid in catalog.holders.get(rid, ()):
            holder = catalog.held[qid].consumer
            self.expected.append(
                Expected(event.status_id, qid, holder, hop, name, catalog.life, event.hlc, line)
            )

    def in_doubt(self, name: str, catalog: _Catalog, line: int, event: Any) -> None:
        rid = event.query_id  # (the in-doubt resource's id)
        catalog.not_live(rid)
        catalog.pending.pop(rid, None)
        for qid in list(catalog.holders.get(rid, ())):
            held = catalog.held[qid]
            self.found(
                "in-doubt",
                f"{name}: {rid[:8]} reported in doubt ({event.cut or 'cut'} not committed) "
                f"while {held.consumer} held it (query {qid[:8]}, committed)",
                (held.line, line),
                name,
                held.consumer,
            )
            self.let_go(name, catalog, qid, event.hlc)

    def cut_short(self, name: str, catalog: _Catalog, line: int, event: Any) -> None:
        catalog.pending.pop(event.resource_id, None)  # in doubt at the next start

    def added(self, name: str, catalog: _Catalog, line: int, event: Any) -> None:
        rid, qid = event.resource_id, event.query_id
        if rid in catalog.unloaded:
            self.found(
                "unload-once",
                f"{name}: {event.consumer} consumes {rid[:8]} (query {qid[:8]}) after its unload",
                (catalog.unloaded[rid], line),
                name,
                event.consumer,
            )
        old = catalog.held.get(qid)
        if old is not None and old.resource_id != rid:
            self.found(
                "one-resource",
                f"{name}: query {qid[:8]} of {event.consumer} added to {rid[:8]} while it "
                f"held {old.resource_id[:8]} (a retry of an id loads nothing, rule 2)",
                (old.line, line),
                name,
                event.consumer,
            )
            self.let_go(name, catalog, qid, event.hlc)
        self.hold(name, catalog, _Held(rid, event.consumer, line, event.hlc), qid)

    def released(self, name: str, catalog: _Catalog, line: int, event: Any) -> None:
        qid = event.query_id
        held = self.let_go(name, catalog, qid, event.hlc)
        if held is None:
            if not catalog.blind:
                self.found(
                    "unload-once",
                    f"{name}: query {qid[:8]} of {event.consumer} released ({event.reason}) "
                    f"but not held",
                    (line,),
                    name,
                    event.consumer,
                )
            return
        if held.resource_id != event.resource_id:
            self.found(
                "release-match",
                f"{name}: query {qid[:8]} of {held.consumer} released from "
                f"{event.resource_id[:8]}, but it held {held.resource_id[:8]}",
                (held.line, line),
                name,
                held.consumer,
            )
        if held.resource_id not in catalog.holders and not catalog.blind:
            catalog.pending[held.resource_id] = (line, False)

    def unloaded(self, name: str, catalog: _Catalog, line: int, event: Any) -> None:
        rid = event.resource_id
        if rid in catalog.unloaded:
            self.found(
                "unload-once",
                f"{name}/{event.server}: {rid[:8]} unloaded twice",
                (catalog.unloaded[rid], line),
                name,
            )
        holders = catalog.holders.get(rid)
        if holders:
            qid = next(iter(holders))
            held = catalog.held[qid]
            self.found(
                "unload-once",
                f"{name}/{event.server}: {rid[:8]} unloaded while {held.consumer} still "
                f"held it (query {qid[:8]})",
                (held.line, line),
                name,
                held.consumer,
            )
        catalog.unloaded[rid] = line
        catalog.not_live(rid)
        catalog.pending.pop(rid, None)

    def stopped(self, name: str, catalog: _Catalog, line: int, event: Any) -> None:
        """A clean stop lists every id it holds (`kept`); a resource whose last holder was released
        is unloaded or kept as unloading (or loaded, for the next start's sweep: `no-leak`)."""
        if not event.complete:
            catalog.pending.clear()  # (what it keeps is not listed: nothing to compare)
            return
        if not catalog.blind:
            rows = {row[0] for row in event.consumers}
            for qid, held in catalog.held.items():
                if qid not in rows:
                    self.found(
                        "kept",
                        f"{name}: query {qid[:8]} of {held.consumer} (resource "
                        f"{held.resource_id[:8]}) is not listed at its stop, but was never "
                        f"released",
                        (held.line, line),
                        name,
                        held.consumer,
                    )
        listed = {row[0]: row[2] for row in event.resources}
        for rid, (since, restored) in catalog.pending.items():
            kept = listed.get(rid)
            if kept in ("loading", "unloading") or (restored and kept == "loaded"):
                continue
            self.found(
                "no-leak",
                f"{name}: {rid[:8]} was released by its last consumer but never unloaded "
                f"(nor reported in doubt) before {name} stopped",
                (since, line),
                name,
            )
        catalog.pending.clear()


_HANDLERS: dict[type, Callable[[Providers, str, _Catalog, int, Any], None]] = {
    events.CatalogRestored: Providers.restored,
    events.ResourceLoaded: Providers.loaded,
    events.LoadFailed: Providers.load_failed,
    events.StatusSent: Providers.status_sent,
    events.StatusDelivered: Providers.status_delivered,
    events.InDoubt: Providers.in_doubt,
    events.UnloadCutShort: Providers.cut_short,
    events.ConsumerAdded: Providers.added,
    events.ConsumerReleased: Providers.released,
    events.ResourceUnloaded: Providers.unloaded,
    events.RegistrarStopped: Providers.stopped,
}
"""`Providers.run`'s handler of each event kind (the class's functions: bound methods in
its instance would be a cycle, which only the garbage collector frees)."""


def unload_order(steps: list[Step]) -> list[Finding]:
    """`unload-order` (rule 7): a resource's dependencies (its `CallAnswered` `parent`s, restored
    client rows) are forgotten before its `ResourceUnloaded`, in its registrar's line order."""
    findings: list[Finding] = []
    deps: dict[str, dict[str, dict[str, int]]] = defaultdict(dict)  # name -> rid -> qid -> line
    parent_of: dict[str, dict[str, str]] = defaultdict(dict)  # name -> qid -> rid
    for name, line, event, new, _life in steps:
        if new:
            deps[name].clear()
            parent_of[name].clear()
        if isinstance(event, events.CatalogRestored):
            for qid, _serving, _server, parent, *_ in event.clients:
                if parent:
                    deps[name].setdefault(parent, {})[qid] = line
                    parent_of[name][qid] = parent
        elif isinstance(event, events.CallAnswered) and event.parent is not None:
            deps[name].setdefault(event.parent, {}).setdefault(event.query_id, line)
            parent_of[name][event.query_id] = event.parent
        elif isinstance(event, events.QueryForgotten):
            rid = parent_of[name].pop(event.query_id, None)
            if rid is not None:
                deps[name].get(rid, {}).pop(event.query_id, None)
        elif isinstance(event, events.ResourceUnloaded):
            held = deps[name].pop(event.resource_id, {})
            for qid, at in held.items():
                parent_of[name].pop(qid, None)
                findings.append(
                    Finding(
                        "unload-order",
                        "violation",
                        f"{name}: resource {event.resource_id[:8]} unloaded while it still "
                        f"held its dependency {qid[:8]} (rule 7: its dependencies first)",
                        (at, line),
                        (name,),
                    )
                )
    return findings


PROVIDER_ENDED = ("revoked", "provider lost", "unknown at reconcile")
"""`QueryForgotten` reasons of a query its provider ended (unregistered its server, or
lost it: `FATAL`), which its consumer forgets whatever holds it."""


def dependency_held(steps: list[Step]) -> list[Finding]:
    """`dependency-held` (rule 7): a registrar does not forget a dependency of one of its
    resources while that resource has a consumer id, unless its provider ended it.

    Consumer ids are the registrar's own lines (restored rows, `ConsumerAdded`,
    `ConsumerReleased`); a life whose `CatalogRestored` is not `complete` is not judged.
    """
    findings: list[Finding] = []
    holders: dict[str, dict[str, dict[str, int]]] = defaultdict(dict)  # name -> rid -> qid -> line
    parent_of: dict[str, dict[str, tuple[str, int]]] = defaultdict(
        dict
    )  # name -> qid -> (rid, line)
    unjudged: set[str] = set()
    for name, line, event, new, _life in steps:
        if new:
            holders[name].clear()
            parent_of[name].clear()
            unjudged.discard(name)
        if isinstance(event, events.CatalogRestored):
            if not event.complete:
                unjudged.add(name)
            for qid, rid, _origin in event.consumers:
                holders[name].setdefault(rid, {})[qid] = line
            for qid, _serving, _server, parent, *_ in event.clients:
                if parent:
                    parent_of[name][qid] = (parent, line)
        elif isinstance(event, events.ConsumerAdded):
            holders[name].setdefault(event.resource_id, {})[event.query_id] = line
        elif isinstance(event, events.ConsumerReleased):
            holders[name].get(event.resource_id, {}).pop(event.query_id, None)
        elif isinstance(event, events.CallAnswered) and event.parent is not None:
            parent_of[name].setdefault(event.query_id, (event.parent, line))
        elif isinstance(event, events.QueryForgotten):
            rid, since = parent_of[name].pop(event.query_id, ("", 0))
            held = holders[name].get(rid)
            if not held or name in unjudged or event.reason in PROVIDER_ENDED:
                continue
            holder, at = next(iter(held.items()))
            findings.append(
                Finding(
                    "dependency-held",
                    "violation",
                    f"{name}: dependency {event.query_id[:8]} of resource {rid[:8]} "
                    f"forgotten ({event.reason}) while {holder[:8]} still held that resource "
                    "(rule 7: dependencies belong to the resource)",
                    (since, at, line),
                    (name,),
                )
            )
    return findings


def doubt_reported(steps: list[Step]) -> list[Finding]:
    """`doubt-reported` (rule 16): a resource a restore lists as `loading` or `unloading` (a
    crash cut its load or its unload short) is, in the life that restored it, reported
    `InDoubt` or unloaded (`ResourceUnloaded`): never dropped unseen.

    Not judged: a life with no event after its `CatalogRestored` (killed before its start
    turn ended: its report may have died with it, and its next restore lists the row
    again), a restore that is not `complete` (its rows are not listed).
    """
    findings: list[Finding] = []
    owed: dict[str, dict[str, tuple[int, str]]] = {}  # name -> rid -> (restore's line, state)
    went_on: dict[str, bool] = {}  # name -> its life showed an event after its restore

    def judge(name: str) -> None:
        if not went_on.pop(name, False):
            owed.pop(name, None)
            return
        for rid, (at, state) in owed.pop(name, {}).items():
            findings.append(
                Finding(
                    "doubt-reported",
                    "violation",
                    f"{name}: {rid[:8]}, restored {state} (a crash cut it short), was neither "
                    f"reported in doubt nor unloaded by the life that restored it (rule 16)",
                    (at,),
                    (name,),
                )
            )

    for name, line, event, new, _life in steps:
        if new:
            judge(name)
        if isinstance(event, events.CatalogRestored):
            judge(name)
            if event.complete:
                owed[name] = {
                    row[0]: (line, row[2])
                    for row in event.resources
                    if row[2] in ("loading", "unloading")
                }
                went_on[name] = False
            continue
        if name in went_on:
            went_on[name] = True
        if isinstance(event, events.InDoubt):
            owed.get(name, {}).pop(event.query_id, None)
        elif isinstance(event, events.ResourceUnloaded):
            owed.get(name, {}).pop(event.resource_id, None)
    for name in list(owed):
        judge(name)
    return findings


SHED_HEADROOM = 1.5
"""A load with nothing queued ahead is shed only if its callers' time left is at most this
times what its server's loads take (the provider's `_SHED_HEADROOM`)."""

SHED_SLACK = (1.25, 0.005)
"""How far above `SHED_HEADROOM` times the longest load a shed's time left may be and not be
judged needless: a factor and seconds (two clocks read a moment apart)."""

_SHED = re.compile(r"was shed before it started: ([0-9.]+) s were left of its callers' timeout,")
"""A shed load's `LoadFailed` message with nothing queued ahead (no `after N rounds`)."""


def shed_needed(history: Sequence[Line]) -> list[Finding]:
    """`shed-needed`: a load refused under overload could not have started in time. A load
    shed as it would start with nothing queued ahead (`LoadFailed`, `DeadlineExceededError`,
    its message's time left) had at most `SHED_HEADROOM` times the longest load its server
    ran in that process before it (`ResourceLoaded.load_s`) left of its callers' timeout.
    Not judged: a shed before any load of its server there ended, or after one failed (its
    time is not in the events), a shed behind queued loads (its time left is net of them)."""
    longest: dict[tuple[str, str, int], float] = {}  # (registrar, server, pid) -> seconds
    unknown: set[tuple[str, str, int]] = set()  # a load failed there: its time not shown
    findings = []
    for line, event in history:
        if isinstance(event, events.ResourceLoaded):
            key = (event.registrar, event.server, event.pid)
            longest[key] = max(longest.get(key, 0.0), event.load_s)
        elif isinstance(event, events.LoadFailed):
            key = (event.registrar, event.server, event.pid)
            shed = _SHED.search(event.message)
            if event.error_type != "DeadlineExceededError" or shed is None:
                unknown.add(key)
                continue
            if key in unknown or key not in longest:
                continue
            left, most = float(shed.group(1)), longest[key]
            factor, seconds = SHED_SLACK
            if left > SHED_HEADROOM * most * factor + seconds:
                findings.append(
                    Finding(
                        "shed-needed",
                        "violation",
                        f"{event.registrar}/{event.server}: a load shed with {left:.3f} s left "
                        f"of its callers' timeout and nothing queued ahead, where its loads "
                        f"took at most {most:.3f} s: it could have started in time (query "
                        f"{event.query_id[:8]})",
                        (line,),
                        (event.registrar,),
                    )
                )
    return findings


OVERLOAD_EVERY_S = 1.0
"""The provider's least time between two `ServerOverloaded` of one server, in seconds (the
refusals between are counted in the next)."""

OVERLOAD_SLACK_S = 0.05
"""What `overload-paced` allows under `OVERLOAD_EVERY_S`: the provider paces by its monotonic
clock, the events carry the wall clock's `at`."""


def overload_paced(steps: list[Step]) -> list[Finding]:
    """`overload-paced`: a server tells its overload at its bound, at most once a second. Each
    `ServerOverloaded` counts at least its own refusal (`refused` >= 1) at the server's bound
    (`pending` >= `bound`), and comes at least `OVERLOAD_EVERY_S` (less `OVERLOAD_SLACK_S`)
    after the previous one of its server in that registrar's life (by `at`: a new life, as a
    new process, counts afresh); the first of its server in a life tells its first refusal
    at once (`refused` 1)."""
    findings: list[Finding] = []
    last: dict[tuple[str, str], tuple[float, int]] = {}  # (registrar, server) -> (at, line)
    for name, line, event, new, _life in steps:
        if new:
            for key in [k for k in last if k[0] == name]:
                del last[key]
        if not isinstance(event, events.ServerOverloaded):
            continue
        key = (name, event.server)
        if event.refused < 1 or event.pending < event.bound:
            findings.append(
                Finding(
                    "overload-paced",
                    "violation",
                    f"{name}/{event.server}: told overloaded with {event.pending} loads of its "
                    f"bound {event.bound} under way and {event.refused} refused: a server is "
                    f"overloaded at its bound, and tells it at a refusal",
                    (line,),
                    (name,),
                )
            )
        before = last.get(key)
        if before is None and event.refused > 1:  # (its first refusal in a life told at once)
            findings.append(
                Finding(
                    "overload-paced",
                    "violation",
                    f"{name}/{event.server}: first told overloaded in this life with "
                    f"{event.refused} refused: a server tells its first refusal at once "
                    f"(refused 1), and counts the next ones in the one a second later",
                    (line,),
                    (name,),
                )
            )
        if before is not None and event.at - before[0] < OVERLOAD_EVERY_S - OVERLOAD_SLACK_S:
            findings.append(
                Finding(
                    "overload-paced",
                    "violation",
                    f"{name}/{event.server}: told overloaded {event.at - before[0]:.3f} s after "
                    f"it was told before: at most once every {OVERLOAD_EVERY_S:g} s (the "
                    f"refusals between counted in the next)",
                    (before[1], line),
                    (name,),
                )
            )
        last[key] = (event.at, line)
    return findings


def share_needed(steps: list[Step]) -> list[Finding]:
    """`share-needed`: a server with room refuses a consumer's load only past its fair share,
    or to keep a slot for consumers waiting ahead of it (`Admission.refusal`). Each
    `ShareRefused` has room (`pending` < `bound`, `under_way` <= `pending`), counts that add up
    (the waiting's loads within `pending`, fewer waiting than `consumers`), the share the docs
    give (`bound // consumers`, at least 1), an `ahead` the check counts itself from those
    waiting (`waiting`, `firsts`: fewer loads under way, or as many and first refused before
    `since`; told since schema 9, an older line's `ahead` taken as told), and a cause: the
    consumer holds its share (`under_way` >= `share`) or the free slots are kept for those
    ahead (`pending + ahead` >= `bound`)."""
    findings: list[Finding] = []
    for name, line, event, _new, _life in steps:
        if not isinstance(event, events.ShareRefused):
            continue
        share = max(1, event.bound // max(1, event.consumers))
        me = (event.under_way, event.since)  # (fewer loads first, then the longest waiting)
        ahead = sum(other < me for other in zip(event.waiting, event.firsts, strict=False))
        if not (
            min((event.under_way, *event.waiting)) >= 0
            and event.under_way + sum(event.waiting) <= event.pending < event.bound
            and len(event.waiting) == len(event.firsts) < event.consumers
            and 0 <= event.ahead < event.consumers
        ):
            why = "its counts do not add up: a server with room, the consumer among its consumers"
        elif event.share != share:
            why = f"its share is {share} (its bound among its consumers, at least 1)"
        elif event.waiting and event.ahead != ahead:  # (none told: a line before schema 9)
            why = f"{ahead} of the {len(event.waiting)} waiting are ahead of it, not {event.ahead}"
        elif event.under_way < event.share and event.pending + event.ahead < event.bound:
            why = "it was under its share, with a free slot beyond those kept for the others"
        else:
            continue
        findings.append(
            Finding(
                "share-needed",
                "violation",
                f"{name}/{event.server} refused a load of {event.consumer} holding "
                f"{event.under_way} of its {event.pending} loads under way (bound {event.bound}, "
                f"share {event.share} among {event.consumers}, {event.ahead} ahead of "
                f"{len(event.waiting)} waiting holding {list(event.waiting)}): {why}",
                (line,),
                (name,),
            )
        )
    return findings


def share_kept(steps: list[Step]) -> list[Finding]:
    """`share-kept`: a server admits a load while other consumers wait there only under the
    consumer's fair share and with a free slot left for each waiting ahead of it, one with fewer
    loads under way or as many and waiting longer (`Admission.refusal`). Each `ShareAdmitted`
    has counts that add up (none below 0, the consumer's and the waiting's loads at most
    `pending`, fewer waiting than `consumers`), the share the docs give, `under_way` < `share`
    and `pending` + those ahead < `bound`."""
    findings: list[Finding] = []
    for name, line, event, _new, _life in steps:
        if not isinstance(event, events.ShareAdmitted):
            continue
        share = max(1, event.bound // max(1, event.consumers))
        me = (event.under_way, event.since)  # (fewer loads first, then the longest waiting)
        ahead = sum(other < me for other in zip(event.waiting, event.firsts, strict=False))
        if not (
            min((event.under_way, *event.waiting)) >= 0
            and event.under_way + sum(event.waiting) <= event.pending
            and len(event.waiting) == len(event.firsts)
            and 0 < len(event.waiting) < event.consumers
        ):
            why = "its counts do not add up: loads of its consumers within its own, those waiting"
        elif event.share != share:
            why = f"its share is {share} (its bound among its consumers, at least 1)"
        elif event.under_way >= event.share:
            why = "it held its share already"
        elif event.pending + ahead >= event.bound:
            why = f"it took the free slot kept for the {ahead} waiting ahead of it"
        else:
            continue
        findings.append(
            Finding(
                "share-kept",
                "violation",
                f"{name}/{event.server} admitted a load of {event.consumer} holding "
                f"{event.under_way} of its {event.pending} loads under way (bound {event.bound}, "
                f"share {event.share} among {event.consumers}, {len(event.waiting)} others "
                f"waiting holding {list(event.waiting)}): {why}",
                (line,),
                (name,),
            )
        )
    return findings


def undigested(history: Sequence[Line]) -> list[Finding]:
    """`dedup` (rule 1), in a run whose requests are all plain values: each load carries its
    request's digest (`ResourceLoaded.digest`, `None` only for a value that is not plain):
    without one, no equal request finds the stored resource by its digest."""
    return [
        Finding(
            "dedup",
            "violation",
            f"{e.registrar}/{e.server}: resource {e.resource_id[:8]} loaded without the "
            "digest of its request, a plain value (rule 1: an equal one finds it by digest)",
            (line,),
            (e.registrar,),
        )
        for line, e in history
        if isinstance(e, events.ResourceLoaded) and e.digest is None
    ]
