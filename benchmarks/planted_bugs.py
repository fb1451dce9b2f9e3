"""Planted bugs found by the simulation: seeds to find each one, its CPU, its shrunk run.

Issue 42 section 3, "Power". Each row of `PLANTS` is one bug, a small edit of the source
(a file, its exact old text, the new text, a line saying what the bug is). For each:

    copy rr_actors/ to a temporary folder ─► apply the edit there (the old text must be
      found exactly once: the script stops, naming the plant, when the code moved)
    a child process with PYTHONPATH at the copy (and PYTHONHASHSEED=0, as a sweep has):
      seeds 1, 2, ... of the plant's shipped plan on the simulation
      (`rr_actors_lab.experiments.simulate.run_seed`) until the first seed with a violation
      of the plant's rule (the kind of finding the bug must cause), or `--seeds` seeds
    the same seed on an unedited copy: that finding must not be there (else the row
      says "also unplanted": the plant did not cause it)
    `--shrink`: the found seed shrunk (`rr_actors_lab.experiments.shrink`, at most `--budget`
      runs) to a small plan whose run still violates the plant's rule, its events counted;
      the shrunk plan at its seed on the unedited copy (it must not violate that rule)

The worktree itself is never edited. Rows: the bug, the plan, the first seed whose run
violated the rule, the seeds run, the violation's text, the CPU seconds of the search
(the child's, `time.process_time`), the events of that seed's history (and after
shrinking, with `--shrink`). A plant never found within `--seeds` is a row saying so (a
finding, not something to hide). Figures are recorded in docs/performance.md
("Planted bugs"). CPU seconds are the steadier figure on a shared machine; pin it for
the docs' figures:

    taskset -c 0 python benchmarks/planted_bugs.py --shrink           # every plant
    python benchmarks/planted_bugs.py --only dedup,retry-fatal --seeds 200  # a quick look
    python benchmarks/planted_bugs.py --check                         # edits apply?
    python benchmarks/planted_bugs.py --only dedup --shrink --keep    # into shrunk/dedup.toml
    python benchmarks/planted_bugs.py --only unload-held --first 17 --shrink --keep  # its seed
    python benchmarks/planted_bugs.py --only unload-held --shrink --keep --from-kept  # again
    python benchmarks/planted_bugs.py --baseline --seeds 100          # unplanted code

`--baseline` runs the plans on the unedited copy instead and prints every violated rule
it met (what the search finds in today's code).

The plans a plant names are shipped ones (`simchain`, `simretry`, `simheal`, `simshare`,
`simrest`, `simprogram`, ... were added for plants no other plan reached); why each plant
and plan was chosen, and those tried and dropped, is in git (`git log -- benchmarks/`).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "rr_actors"
LAB = ROOT / "rr_actors_lab"
PLANS = ROOT / "rr_actors_lab" / "experiments" / "plans"


@dataclasses.dataclass(frozen=True)
class Plant:
    """One planted bug: an edit of one file of the package, and what must find it."""

    name: str
    bug: str  # what the bug is, in a line
    file: str  # relative to rr_actors/
    old: str  # found exactly once in the file
    new: str
    plan: str  # a plan of rr_actors_lab/experiments/plans/ (its stem)
    rule: str  # the checker's rule whose violation the bug causes


PLANTS = (
    Plant(
        "dedup",
        "an equal request loaded twice: a loaded resource is not shared (rule 1)",
        "_registrar/provider.py",
        "        if resource is not None and resource.state is ResourceState.LOADED:"
        "  # the hot path\n"
        "            self.share(resource, message)\n"
        "            return\n",
        "        if resource is not None and resource.state is ResourceState.LOADED:"
        "  # the hot path\n"
        "            resource = None  # PLANTED: no dedup hit, loaded again\n",
        "simchain",
        "dedup",
    ),
    Plant(
        "unload-held",
        "an unload run while held: any release of a loaded resource unloads it (rule 7); "
        "the catalog refuses to remove a resource with consumers (an assertion), so the "
        "actor dies after the unload began: its restart finds it in doubt, still held",
        "_registrar/provider.py",
        "        if last and resource.state is ResourceState.LOADED:  # one commit with its"
        " unload mark\n",
        "        if resource.state is ResourceState.LOADED:  # PLANTED: consumers left\n",
        "simchain",
        "in-doubt",
    ),
    Plant(
        "status-path",
        "a status not sent up one dependency path: one that climbs (hop 2 and up) skips "
        "consumers in other processes (rule 9)",
        "_registrar/status.py",
        "        for relay, parts, batched in self.routes.plan(elsewhere):\n",
        "        for relay, parts, batched in self.routes.plan(elsewhere if hop == 1 else []):"
        "  # PLANTED\n",
        "simchain",
        "status-reached",
    ),
    Plant(
        "retry-fatal",
        "a retry answered and then reported FATAL: a Reconcile's 'unknown' settles a "
        "record answered after its list left (the reverse of 786b5f8, issue 29)",
        "_registrar/consumer.py",
        "            since = query_id in listing.due or not"
        " self.registrar.holdings.answered_before(\n"
        "                query_id, listing.epoch\n"
        "            )\n",
        "            since = query_id in listing.due\n",
        "simretry",
        "reported-lost",
    ),
    Plant(
        "consumer-restart",
        "an id never released after a restart: a Reconcile releases none of the ids its "
        "consumer no longer holds (rule 20; sent by a consumer after its own restart, "
        "and after its provider's)",
        "_registrar/provider.py",
        "        stale = sorted(mine - held)\n",
        "        stale: list[str] = []  # PLANTED: sorted(mine - held)\n",
        "simchain",
        "end",
    ),
    Plant(
        "restore-unread",
        "a restore that serves before the catalog is read: a lookup by request does not "
        "read the restored rows still in the backup first (rule 1 after a restart)",
        "_catalog/catalog.py",
        "        if found is None and self._unread is not None:\n            if digest",
        "        if found is None and self._unread is not None and False:  # PLANTED\n"
        "            if digest",
        "simchain",
        "dedup",
    ),
    Plant(
        "heal-no-yield",
        "two servers of one name after a healed cut: the one served later never gives way "
        "(rule 22; the reverse of the merge fa1549b, in the decision every carrier runs)",
        "_transport/messenger.py",
        "        if self.resolution.kept(name, [local, rival]) is local:\n"
        "            self._claim(name, local, rival)\n"
        "            return\n",
        "        if True:  # PLANTED: self.resolution.kept(name, [local, rival]) is local\n"
        "            return\n",
        "simheal",
        "one-name",
    ),
    Plant(
        "rows-left",
        "rows left after every manager reconciled: a Reconcile finds the ids its consumer "
        "gave back while this registrar was down but releases none of them, so their "
        "resources stay (issue 51, `catalog_entries_left`; `end` sees the ids too)",
        "_registrar/provider.py",
        "            if catalog.has_consumer(query_id):  # (still: a release above may have "
        "cascaded)\n",
        "            if False:  # PLANTED: catalog.has_consumer(query_id)\n",
        "simchain",
        "left",
    ),
    Plant(
        "withdrawn",
        "a withdrawn call's id kept after its provider's restart: the failure of a call its "
        "caller withdrew is held for a retry, so the next Reconcile lists it and the "
        "restarted provider keeps it (the reverse of 01defa0, issue 51 finding 1)",
        "_registrar/consumer.py",
        "            gone = message.withdrawn or message.attempt.state is AttemptState.WITHDRAWN\n",
        "            gone = False  # PLANTED: a withdrawn call's failure held for a retry too\n",
        "simcancel",
        "withdrawn",
    ),
    Plant(
        "retry-released",
        "an id kept for a retry released by the second reconcile of the provider's life "
        "that kept it (a life asks as it starts and once served): the retry loads afresh "
        "(the reverse of bf53b40, issue 51: a full CI run's failure)",
        "_registrar/consumer.py",
        "        held |= self.registrar.flights.kept_at(serving_rr, life)\n",
        "        # PLANTED: kept for a retry, listed in its first Reconcile only\n",
        "simretry",
        "retry-kept",
    ),
    Plant(
        "intensity",
        "a supervisor that gives up one restart early: at `max_restarts` restarts within "
        "`period`, not past them (OTP's intensity, issue 51)",
        "_supervision/policy.py",
        "        return len(self._times) <= self.max_restarts\n",
        "        return len(self._times) < self.max_restarts  # PLANTED: one restart early\n",
        "crashloop",
        "intensity",
    ),
    Plant(
        "intensity-rest",
        "the plant `intensity` (one restart early) under rest_for_one: `simrest` gave "
        "`max_restarts` 1000 until issue 68 item 7, so it never reached the bug",
        "_supervision/policy.py",
        "        return len(self._times) <= self.max_restarts\n",
        "        return len(self._times) < self.max_restarts  # PLANTED: one restart early\n",
        "simrest",
        "intensity",
    ),
    Plant(
        "dedup-order",
        "an equal request loaded before its unloading resource is gone: a load that comes "
        "while its resource unloads starts at once, not after the unload (rule 1's order; "
        "issue 68 item 7: `simretry` missed it in 100 seeds)",
        "_registrar/provider.py",
        "        if resource is None:\n"
        "            self.start_load(self.registrar.servers[message.server], message, waiter,"
        " key)\n"
        "        elif resource.state is ResourceState.UNLOADING:  # load it afresh once it is"
        " gone\n",
        "        if resource is None or resource.state is ResourceState.UNLOADING:  # PLANTED\n"
        "            self.start_load(self.registrar.servers[message.server], message, waiter,"
        " key)\n"
        "        elif False:  # PLANTED: loaded afresh once it is gone\n",
        "simretry",
        "dedup",
    ),
    Plant(
        "doubt-unloading-unseen",
        "an unload a kill cut short dropped unseen at the restart: the row goes without its "
        "unload, and neither the manager nor the events are told it was in doubt (rule 16; "
        "issue 68 item 7: `left` and `no-leak` excuse a row restored unloading)",
        "_registrar/life.py",
        "        self.in_doubt_ids = frozenset(r.id for r in doubtful)\n"
        "        if self.hold_in_doubt:\n"
        "            self.registrar.held_in_doubt.update(self.in_doubt_ids)\n"
        "        for resource in doubtful:\n"
        "            if self.registrar.events.active:\n",
        "        self.in_doubt_ids = frozenset(  # PLANTED: the unloads cut short left out\n"
        "            r.id for r in doubtful if r.state is ResourceState.LOADING\n"
        "        )\n"
        "        if self.hold_in_doubt:\n"
        "            self.registrar.held_in_doubt.update(self.in_doubt_ids)\n"
        "        for resource in doubtful:\n"
        "            if self.registrar.events.active and resource.id in self.in_doubt_ids:\n",
        "simdoubt",
        "doubt-reported",
    ),
    Plant(
        "reconcile-due",
        "a due call's id left out of its consumer's Reconcile: the provider releases an id "
        "whose answer is on its way, and the consumer then records it (issue 68 item 7: "
        "every verdict said `held`)",
        "_registrar/consumer.py",
        "        held |= due\n        held -= withdrawn\n",
        "        held -= withdrawn  # PLANTED: held |= due\n",
        "simretry",
        "answer-released",
    ),
    Plant(
        "record-lost",
        "a consumer's record write lost: a new client row's INSERT is dropped, so the "
        "restore after a kill lacks an id its consumer had recorded, and it is handed "
        "back quietly (its provider releases it at the reconcile; issue 68 item 7)",
        "_store/schema.py",
        '        ops.append(\n            (\n                "INSERT INTO clients',
        "        [].append(  # PLANTED: ops.append\n            (\n"
        '                "INSERT INTO clients',
        "simchain",
        "record-kept",
    ),
    Plant(
        "shed-ms",
        "a load's run time learned in milliseconds: its server's pace is a thousand times "
        "what its loads take, so loads that had time to start are shed as they come "
        "(`DeadlineExceededError`; issue 68 item 7: no rule judged a refusal needed)",
        "_registrar/provider.py",
        "        pace.load_s += _LOAD_S_WEIGHT * (took - pace.load_s)\n",
        "        pace.load_s += _LOAD_S_WEIGHT * (took * 1000 - pace.load_s)  # PLANTED: ms\n",
        "simdoubt",
        "shed-needed",
    ),
    # -- issue 51 section 2: a reviewer's plants, one or more per area ---------------
    Plant(
        "status-seen-server",
        "a status climbing two resources of one server reaches one: the relay's "
        "already-seen key is the status and the server, not the resource (rule 9)",
        "_registrar/status.py",
        "        key = (event, resource.id)\n",
        "        key = (event, resource.server)  # PLANTED: resource.id\n",
        "simshare",
        "status-reached",
    ),
    Plant(
        "status-hop",
        "a status climbing to a dependent resource keeps its hop count: its consumers are "
        "told it at the hop of the dependency (rule 9's path)",
        "_registrar/status.py",
        "                    hop=message.hop + 1,\n",
        "                    hop=message.hop,  # PLANTED: message.hop + 1\n",
        "simdoubt",
        "status-path",
    ),
    Plant(
        "reconcile-unread-ids",
        "a Reconcile after a restore sees only the consumer ids already read from the "
        "backup: it names the others unknown and never releases the stale ones among them",
        "_catalog/catalog.py",
        "            ids.update(self._unread.consumer_ids_from(origin_rr))\n",
        "            pass  # PLANTED: ids.update(self._unread.consumer_ids_from(origin_rr))\n",
        "simchain",
        "reported-lost",
    ),
    Plant(
        "restore-no-parents",
        "a restore reads no resource that owns a dependency at once: its dependencies' "
        "records look orphaned and are given back while it still holds them",
        "_store/restore.py",
        '    "WHERE state != 1 OR digest IS NULL "  # == _UNSETTLED: the partial index serves it\n'
        '    f"UNION SELECT {RESOURCE_COLUMNS} FROM resources "\n'
        '    "WHERE id IN (SELECT parent FROM clients WHERE parent IS NOT NULL) ORDER BY seq"\n',
        '    "WHERE state != 1 OR digest IS NULL ORDER BY seq"  # PLANTED: no UNION of parents\n',
        "simchain",
        "dependency-held",
    ),
    Plant(
        "doubt-loads-only",
        "an unload a kill cut short is not in doubt at the restart: only loads are "
        "(rule 16), so the resource stays as unloading, never unloaded",
        "_registrar/life.py",
        "    return [r for r in catalog.resources.values() if r.state is not "
        "ResourceState.LOADED]\n",
        "    return [r for r in catalog.resources.values() if r.state is ResourceState.LOADING]"
        "  # PLANTED\n",
        "simdoubt",
        "left",
    ),
    Plant(
        "doubt-unread-unloading",
        "a restore reads only the loads cut short at once, not the unloads: an unload a "
        "kill cut short is never reported in doubt (rule 16) nor finished",
        "_store/restore.py",
        '    "WHERE state != 1 OR digest IS NULL "  # == _UNSETTLED',
        '    "WHERE state = 0 OR digest IS NULL "  # PLANTED: state != 1 (== _UNSETTLED)',
        "simdoubt",
        "left",
    ),
    Plant(
        "intensity-swapped",
        "a supervisor's intensity built with its two numbers swapped: `period` restarts "
        "within `max_restarts` seconds (a positional mix-up)",
        "_supervision/policy.py",
        "            spec.max_restarts, spec.period, record.tree.clock, "
        "recent=record.tree.steps.recent\n",
        "            spec.period, spec.max_restarts, record.tree.clock, "
        "recent=record.tree.steps.recent  # PLANTED\n",
        "crashloop",
        "intensity",
    ),
    Plant(
        "forget-before-carried",
        "an unload's answer handled before the statuses it carried: the id is forgotten "
        "first, so a status its provider sent on to it just before the release, which "
        "the answer carried, finds no record (rule 9 across a release)",
        "_registrar/consumer.py",
        "            self.deliver_on_its_way(query_id, on_its_way, join)\n"
        "            self.registrar.holdings.forget(query_id, began=began)\n",
        "            self.registrar.holdings.forget(query_id, began=began)  # PLANTED:"
        " before the statuses\n"
        "            self.deliver_on_its_way(query_id, on_its_way, join)\n",
        "simshare",
        "status-reached",
    ),
    Plant(
        "fetch-unread",
        "after a restore, a fetch lists only the resources already read from the backup "
        "(rule 10: exact)",
        "_catalog/catalog.py",
        '        """Every consumer query of every loaded resource of `server`."""\n'
        "        if self._unread is not None:\n"
        "            self._read_in(self._unread.of_server(server))\n",
        '        """Every consumer query of every loaded resource of `server`."""\n'
        "        # PLANTED: the unread rows of `server` are not read in\n",
        "simdoubt",
        "fetch",
    ),
    Plant(
        "unload-before-deps",
        "a resource unloaded before its dependencies are released: its unload runs at "
        "once, its dependencies released beside it (rule 7's order)",
        "_registrar/provider.py",
        "            self.registrar.releases.release_dependencies(resource.id,"
        " run_unload, trace=trace)\n",
        "            run_unload()  # PLANTED: release_dependencies(resource.id, run_unload)\n"
        "            self.registrar.releases.release_dependencies(resource.id, lambda:"
        " None, trace=trace)\n",
        "simdoubt",
        "unload-order",
    ),
    Plant(
        "intensity-stale-exit",
        "a sibling stopped for a group restart counted as a crash: the exit of an "
        "incarnation stopped on purpose is not recognised as stale (OTP's intensity)",
        "_supervision/policy.py",
        "        if child is None or child.incarnation != event.incarnation or "
        "self.restarts.gave_up:\n",
        "        if child is None or self.restarts.gave_up:  # PLANTED: incarnation\n",
        "crashloop",
        "restore-first",
    ),
    Plant(
        "restart-reversed",
        "a group restarted in the order it was stopped in: one_for_all's siblings come "
        "back in reverse start order (OTP starts them in start order; issue 51)",
        "_supervision/policy.py",
        "        for child in map(record.by_name.__getitem__, event.names):  # (in start order)\n"
        '            if child.state != "restarting" or self._due.get(child.name) is not event:\n',
        "        for child in reversed([*map(record.by_name.get, event.names)]):  # PLANTED\n"
        '            if child.state != "restarting" or self._due.get(child.name) is not event:\n',
        "crashloop",
        "strategy",
    ),
    Plant(
        "sibling-left-running",
        "one_for_all's siblings restarted without being stopped: a crash takes down only "
        "the crashed child, and its siblings are started again beside themselves",
        "_supervision/policy.py",
        "            if other.running is not None:\n"
        "                self.stopping.stop_child(other, final=not comes_back, "
        "restarting=comes_back)\n",
        "            if other.running is not None:  # PLANTED: not stopped\n"
        "                other.running = None\n",
        "crashloop",
        "strategy",
    ),
    Plant(
        "rest-for-one-before",
        "rest_for_one takes down the children started before the crashed one (itself "
        "included), not those after it: the ones that depend on it run on",
        "_supervision/children.py",
        "    return tuple(names[names.index(crashed) :])\n",
        "    return tuple(names[: names.index(crashed) + 1])  # PLANTED: names[index:]\n",
        "simrest",
        "strategy",
    ),
    Plant(
        "give-up-unescalated",
        "a nested supervisor that gives up never tells its parent: the parent keeps it as "
        "running, its managers down for good (OTP escalates: the parent sees it exit)",
        "_supervision/policy.py",
        "        if self.on_gave_up is not None:\n            self.on_gave_up(error)\n",
        "        # PLANTED: self.on_gave_up(error) not called\n",
        "crashloop",
        "escalation",
    ),
    Plant(
        "lost-unreported",
        "an id a restart without a backup lost, never reported FATAL: a Reconcile's "
        "'unknown' is taken for a release on its way, for every id (rule 20); its consumer "
        "forgets it later, on its release, which left after that reconcile (issue 51's "
        "state = false: a release that crossed the restart is no such loss)",
        "_registrar/consumer.py",
        "            elif query_id not in self.registrar.releases.releasing:  # (its release: no"
        " FATAL)\n",
        "            elif False:  # PLANTED: query_id not in self.registrar.releases.releasing\n",
        "simnostate",
        "kept",
    ),
    Plant(
        "retry-doubt-dropped",
        "a failed retry of a held id its provider's restart (no backup) knew not is kept, "
        "never reported FATAL: the retry was due at the restart's reconcile (doubted), and "
        "its failure ends the flight without its provider, which drops the doubt (issue 51); "
        "nor is its failure, a new load there, taken for the loss (issue 68)",
        "_registrar/consumer.py",
        "            flights.answered(qid, message.attempt, message.provider)\n"
        "        record = self.registrar.catalog.client(qid)",
        "            flights.answered(qid, message.attempt)  # PLANTED\n"
        "        record = None  # PLANTED: self.registrar.catalog.client(qid)",
        "simnostate",
        "kept",
    ),
    Plant(
        "program-restart",
        "a program killed and started again on its state_dir: its consumers (registrars of "
        "Supervisor.registrar, no backup) are not told they lost everything, so the ids "
        "their last run held stay in the managers' restored catalogs for nobody (the "
        "reverse of b52ff0e6, issue 51 finding 2)",
        "_supervision/supervisor.py",
        "        if ran_before(state_dir, registrar.name):\n",
        "        if ran_before(state_dir, registrar.name) and False:  # PLANTED: not told\n",
        "simprogram",
        "left",
    ),
    Plant(
        "status-lanes",
        "an id's next status run beside its hung callback: the status watchdog that gives "
        "up a callback opens its id's lane (the reverse of 5884c558, issue 51 finding 6)",
        "_registrar/status.py",
        "                        drainer.abandoned = True\n"
        "                        self._drainers -= 1\n"
        "                        self._inside.discard(drainer)\n",
        "                        drainer.abandoned = True\n"
        "                        self._drainers -= 1\n"
        "                        self._inside.discard(drainer)\n"
        "                        self._let_go(drainer, drainer.call)  # PLANTED: lane opened\n",
        "simslow",
        "status-order",
    ),
    Plant(
        "status-ways",
        "a consumer's status overtaken on the way to its process's relay: the provider "
        "switches a consumer registrar to the relay while statuses sent on its own "
        "connection are unanswered (the reverse of issue 68 item 1)",
        "_registrar/status.py",
        "                if way or home is None:\n",
        "                if home is None:  # PLANTED: no way kept\n",
        "simways",
        "status-order",
    ),
)
"""The planted bugs, one at a time (docs/performance.md lists them)."""


# -- the parent: scratch copies, one child per plant ------------------------------------


def plant_text(plant: Plant, text: str) -> str:
    """`text` (the file's) with `plant`'s edit; SystemExit if its old text is not found
    exactly once (the code moved: the plant must be written again)."""
    count = text.count(plant.old)
    if count != 1:
        raise SystemExit(
            f"plant {plant.name!r}: its old text is found {count} times in "
            f"rr_actors/{plant.file} (must be once): write the plant again\n{plant.old}"
        )
    return text.replace(plant.old, plant.new)


def scratch(folder: Path, plant: Plant | None) -> Path:
    """A copy of the package under `folder` (`plant` applied), and of the lab beside it (this
    checkout's plans and workload, not an installed one's); the PYTHONPATH to use."""
    target = folder / "rr_actors"
    shutil.copytree(PACKAGE, target, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(LAB, folder / "rr_actors_lab", ignore=shutil.ignore_patterns("__pycache__"))
    if plant is not None:
        path = target / plant.file
        path.write_text(plant_text(plant, path.read_text()))
    return folder


def child(path: Path, *arguments: str) -> dict[str, Any]:
    """Run this script's child part on the package at `path`; its JSON answer."""
    env = {**os.environ, "PYTHONPATH": str(path), "PYTHONHASHSEED": "0"}
    done = subprocess.run(
        [sys.executable, __file__, "--child", str(path), *arguments],
        env=env,
        check=False,
        stdout=subprocess.PIPE,
        text=True,
    )
    if done.returncode != 0 or not done.stdout.strip():
        raise SystemExit(f"the child failed ({done.returncode}): {' '.join(arguments)}")
    answer: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return answer


def search(
    plant: Plant, seeds: int, budget: int, first: int = 1, *, kept: bool = False
) -> dict[str, Any]:
    """`plant`'s row: the first seed from `first` on violating its rule, then that seed
    unplanted; `kept`: its kept shrunk plan at its seed instead (shrunk again)."""
    with tempfile.TemporaryDirectory(prefix=f"rr-planted-{plant.name}-") as folder:
        planted = scratch(Path(folder) / "planted", plant)
        if kept:
            path = str(KEPT / f"{plant.name}.toml")
            row = child(planted, "kept", plant.plan, path, plant.rule, str(budget))
        else:
            arguments = (plant.plan, plant.rule, str(seeds), str(budget), str(first))
            row = child(planted, "search", *arguments)
        row["also_unplanted"] = None
        if row["seed"] is not None and not kept:
            clean = scratch(Path(folder) / "clean", None)
            seed = str(row["seed"])
            again = child(clean, "search", plant.plan, plant.rule, seed, "0", seed)
            row["also_unplanted"] = again["seed"] is not None
            if (small := row.get("shrunk")) and small.get("text"):  # (a shrunk plan: the same)
                text = Path(folder) / "shrunk.toml"
                text.write_text(small["text"], encoding="utf-8")
                arguments = (plant.plan, str(text), str(small["seed"]), plant.rule)
                small["unplanted"] = child(clean, "shrunk", *arguments)["violations"]
        if kept and (small := row.get("shrunk")) and small.get("text"):
            clean = scratch(Path(folder) / "clean", None)
            text = Path(folder) / "shrunk.toml"
            text.write_text(small["text"], encoding="utf-8")
            arguments = (plant.plan, str(text), str(small["seed"]), plant.rule)
            small["unplanted"] = child(clean, "shrunk", *arguments)["violations"]
    return row


KEPT = ROOT / "benchmarks" / "shrunk"
"""Each plant's shrunk plan (`--keep`): `PLANT.toml`, its top-level `seed` the seed it
violates with (tests/test_benchmarks.py runs each on its plant)."""


def kept_text(
    plant: Plant,
    text: str,
    seed: int,
    events: int,
    runs: int,
    story: int | None = None,
    again: str = "",
) -> str:
    """A shrunk plan's text as `--keep` writes it: a header, then its seed, then the plan."""
    told = (
        f"# Its story is its first {story} events: the checker finds the same violation "
        f"without the {events - story} after its finding.\n"
        if story is not None and story < events
        else ""
    )
    header = (
        f"# The plant {plant.name!r} (benchmarks/planted_bugs.py) shrunk: seed {seed} of this "
        f"plan violates [{plant.rule}]\n# in {events} events on the planted code "
        f"({runs} simulated runs of the shrink{again}; `--shrink --keep` writes it again).\n"
        f"{told}"
    )
    return f"{header}seed = {seed}\n{text}"


def run_kept(plant: Plant, path: Path) -> dict[str, Any]:
    """The kept shrunk plan at `path` run at its seed on a copy with `plant` applied: its
    verdict, its violations of the plant's rule, its events and its story's
    (`rr_actors_lab.experiments.shrink.story_events`)."""
    seed = tomllib.loads(path.read_text(encoding="utf-8"))["seed"]
    with tempfile.TemporaryDirectory(prefix=f"rr-planted-{plant.name}-") as folder:
        planted = scratch(Path(folder), plant)
        return child(planted, "shrunk", plant.plan, str(path), str(seed), plant.rule)


def baseline(plans: list[str], seeds: int) -> list[dict[str, Any]]:
    """Each plan's seeds on an unedited copy: the rules violated, and on which seeds."""
    with tempfile.TemporaryDirectory(prefix="rr-planted-baseline-") as folder:
        clean = scratch(Path(folder), None)
        return [child(clean, "baseline", plan, str(seeds)) for plan in plans]


# -- the child: seeds on the copy PYTHONPATH names ----------------------------------------


def violated(findings: tuple[str, ...], rule: str | None) -> list[str]:
    """The violation lines of `findings` (of `rule` only, unless it is None)."""
    lines = [line.strip() for line in findings if line.lstrip().startswith("violation")]
    return [line for line in lines if rule is None or f"[{rule}]" in line]


def progress(plan: str, seed: int, run: Any, found: str | None) -> None:
    """A line on stderr per seed run (the table is on stdout)."""
    rules = sorted(
        {line.split("[", 1)[1].split("]", 1)[0] for line in violated(run.findings, None)}
    )
    mark = f"  <- [{found}]" if found else ""
    print(
        f"  {plan} seed {seed}: {run.verdict} {' '.join(rules)} ({run.events} events, "
        f"{run.cpu_s:.2f} CPU s){mark}",
        file=sys.stderr,
        flush=True,
    )


def child_main(path: str, command: str, arguments: list[str]) -> None:
    """The child: checks it runs the copy at `path`, then `command`; one JSON line out."""
    import logging  # noqa: PLC0415

    import rr_actors  # noqa: PLC0415 - the copy's, from PYTHONPATH
    from rr_actors_lab.experiments import load_plan, simulate  # noqa: PLC0415

    for module in (rr_actors, simulate):
        here = Path(module.__file__ or "").resolve()
        if not here.is_relative_to(Path(path).resolve()):
            raise SystemExit(f"the child imported {here}, not the copy at {path}")
    logging.getLogger("rr_actors").setLevel(logging.ERROR)  # (a WARNING per kill)
    plan = load_plan(str(PLANS / f"{arguments[0]}.toml"))
    started = time.process_time()
    if command == "shrunk":  # (the shrunk plan's text in a file, its seed, the rule)
        from rr_actors_lab.experiments import shrink  # noqa: PLC0415
        from rr_actors_lab.experiments.reading import parse_plan  # noqa: PLC0415

        text = Path(arguments[1]).read_text(encoding="utf-8")
        run = simulate.run_seed(parse_plan(text, source=plan.source), int(arguments[2]))
        found = violated(run.findings, arguments[3])
        judge = functools.partial(rule_first, rule=arguments[3])
        kinds = shrink.violation_kinds(run, judge)
        story = shrink.story_events(run, kinds[0], judge) if found else run.events
        answer = {"verdict": run.verdict, "violations": found, "events": run.events}
        print(json.dumps(answer | {"story": story}))
        return
    if command == "kept":  # (the kept shrunk plan's file, the rule, the budget)
        print(json.dumps(kept_row(plan, arguments[1], arguments[2], int(arguments[3]))))
        return
    if command == "baseline":
        rules: dict[str, list[int]] = {}
        seeds = int(arguments[1])
        for seed in range(1, seeds + 1):
            run = simulate.run_seed(plan, seed)
            progress(plan.name, seed, run, None)
            for line in violated(run.findings, None):
                rule = line.split("[", 1)[1].split("]", 1)[0]
                if seed not in rules.setdefault(rule, []):
                    rules[rule].append(seed)
        answer: dict[str, Any] = {
            "plan": plan.name,
            "seeds": seeds,
            "rules": rules,
            "cpu_s": time.process_time() - started,
        }
        print(json.dumps(answer))
        return
    rule, last, budget = arguments[1], int(arguments[2]), int(arguments[3])
    first = int(arguments[4]) if len(arguments) > 4 else 1
    answer = {"plan": plan.name, "rule": rule, "seed": None, "seeds": 0, "violation": None}
    for seed in range(first, last + 1):
        run = simulate.run_seed(plan, seed)
        answer["seeds"] += 1
        found = violated(run.findings, rule)
        progress(plan.name, seed, run, rule if found else None)
        if found:
            answer.update(seed=seed, violation=found[0], events=run.events)
            break
    answer["cpu_s"] = time.process_time() - started
    answer["shrunk"] = (
        shrunk(plan, answer["seed"], rule, budget) if budget and answer["seed"] else None
    )
    print(json.dumps(answer))


def kept_row(plan: Any, path: str, rule: str, budget: int) -> dict[str, Any]:
    """The child's row of a kept shrunk plan (at `path`): its seed's run, then that seed
    shrunk again (`budget` runs), its text the start."""
    from rr_actors_lab.experiments import simulate  # noqa: PLC0415 - the copy's
    from rr_actors_lab.experiments.reading import parse_plan  # noqa: PLC0415

    started = time.process_time()
    text = Path(path).read_text(encoding="utf-8")
    kept, seed = parse_plan(text, source=plan.source), tomllib.loads(text)["seed"]
    run = simulate.run_seed(kept, seed)
    found = violated(run.findings, rule)
    row: dict[str, Any] = {"plan": plan.name, "rule": rule, "seeds": 1}
    row |= {"seed": seed if found else None, "violation": found[0] if found else None}
    row |= {"events": run.events, "cpu_s": time.process_time() - started}
    small = shrunk(kept, seed, rule, budget, text) if found and budget else None
    return row | {"shrunk": small}


def say(line: str) -> None:
    """A shrink's step on stderr (the answer is on stdout)."""
    print(f"  shrink: {line}", file=sys.stderr, flush=True)


def rule_first(run: Any, rule: str) -> list[Any]:
    """The checker's violations of `run`, those of `rule` first (the shrinker keeps a run's
    first kind)."""
    from rr_actors_lab.experiments import shrink  # noqa: PLC0415 - the copy's

    return sorted(shrink.violations(run), key=lambda finding: finding.rule != rule)


def shrunk(plan: Any, seed: int, rule: str, budget: int, text: str | None = None) -> dict[str, Any]:
    """`seed`'s run shrunk (`rr_actors_lab.experiments.shrink`) keeping a violation of `rule`:
    the events of the shrunk run, the violation kind it kept, the runs it made and their
    CPU seconds."""
    from rr_actors.errors import ConfigError  # noqa: PLC0415 - the copy's
    from rr_actors_lab.experiments import shrink  # noqa: PLC0415

    judge = functools.partial(rule_first, rule=rule)
    started = time.process_time()
    try:
        result = shrink.shrink(plan, seed, budget=budget, on_step=say, judge=judge, text=text)
    except ConfigError as exc:  # (its run again did not violate: not replayed)
        return {"events": None, "kind": f"not shrunk: {exc}", "runs": 1, "cpu_s": 0.0}
    if out := os.environ.get("RR_PLANTED_OUT"):  # (`--out`: the shrunk run to read)
        from rr_actors_lab.experiments.sweep import seed_line  # noqa: PLC0415

        shrink.write(result, Path(out), seed_line(result.run, result.plan))
    return {
        "events": result.run.events,
        "kind": result.kind,
        "runs": result.runs,
        "cpu_s": time.process_time() - started,
        "text": result.text,
        "seed": result.seed,
        "story": result.story,
    }


# -- the table ------------------------------------------------------------------------


def table(rows: list[tuple[Plant, dict[str, Any]]], seeds: int, shrink: bool) -> None:
    """Print the rows (and each plant's violation on its own line below)."""
    head = ("bug", "plan", "rule", "found at seed", "seeds run", "CPU s", "events")
    if shrink:
        head += ("shrunk",)
    lines = [head]
    for plant, row in rows:
        seed = row["seed"]
        found = "not found" if seed is None else str(seed)
        if row.get("also_unplanted"):
            found += " (also unplanted)"
        cells = (
            plant.name,
            row["plan"],
            plant.rule,
            found,
            str(row["seeds"]),
            f"{row['cpu_s']:.1f}",
            "-" if seed is None else str(row["events"]),
        )
        if shrink:
            small = row.get("shrunk")
            events = "-" if small is None or small["events"] is None else str(small["events"])
            if small is not None and small.get("story") not in (None, small["events"]):
                events += f" (story {small['story']})"
            spent = "" if small is None else f" ({small['runs']} runs, {small['cpu_s']:.0f} CPU s)"
            if small is not None and small.get("unplanted"):
                spent += " (also unplanted)"
            cells += (events + spent,)
        lines.append(cells)
    widths = [max(len(line[i]) for line in lines) for i in range(len(head))]
    for line in lines:
        print("  ".join(cell.ljust(width) for cell, width in zip(line, widths, strict=True)))
    print()
    for plant, row in rows:
        print(f"{plant.name}: {plant.bug}")
        print(f"    {row['violation'] or f'no [{plant.rule}] violation in {seeds} seeds'}")
        if row.get("shrunk") is not None:
            print(f"    shrunk, keeping: {row['shrunk']['kind']}")
            if "unplanted" in row["shrunk"]:  # (its seed on the unedited code)
                held = not row["shrunk"]["unplanted"]
                print(
                    f"    shrunk plan, seed {row['shrunk']['seed']}, unplanted: "
                    f"{'no [' + plant.rule + '] violation' if held else 'ALSO VIOLATED'}"
                )


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if args[:1] == ["--child"]:
        child_main(args[1], args[2], args[3:])
        return 0
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--seeds", type=int, default=10_000, help="most seeds per plant")
    parser.add_argument("--only", help="plants to run, by name, comma-separated")
    parser.add_argument(
        "--first", type=int, default=1, help="the first seed searched (a seed known to violate)"
    )
    parser.add_argument("--shrink", action="store_true", help="shrink each found seed")
    parser.add_argument("--budget", type=int, default=2500, help="most runs of one shrink")
    parser.add_argument("--check", action="store_true", help="only check the edits apply and parse")
    parser.add_argument(
        "--out", type=Path, help="write each shrunk run to OUT/PLANT (`rr-actors replay`)"
    )
    parser.add_argument("--baseline", action="store_true", help="run the unedited code")
    parser.add_argument(
        "--from-kept",
        action="store_true",
        help="with --shrink: shrink each plant's kept plan again, not a seed of its plan",
    )
    parser.add_argument(
        "--keep", action="store_true", help="with --shrink: write each shrunk plan to shrunk/"
    )
    options = parser.parse_args(args)
    chosen = [p for p in PLANTS if options.only is None or p.name in options.only.split(",")]
    if not chosen:
        parser.error(f"--only: none of {', '.join(p.name for p in PLANTS)}")
    for plant in chosen:
        try:  # (an edit that no longer parses: indented as the code was before it moved)
            compile(plant_text(plant, (PACKAGE / plant.file).read_text()), plant.file, "exec")
        except SyntaxError as exc:
            raise SystemExit(f"plant {plant.name!r}: the edit does not parse: {exc}") from None
    if options.check:
        print(f"{len(chosen)} plants apply")
        return 0
    if options.baseline:
        plans = sorted({p.plan for p in chosen})
        for answer in baseline(plans, options.seeds):
            rules = ", ".join(
                f"{rule} ({len(s)} seeds, first {s[0]})" for rule, s in answer["rules"].items()
            )
            print(
                f"{answer['plan']}: {answer['seeds']} seeds, {answer['cpu_s']:.1f} CPU s: "
                f"{rules or 'every seed held'}"
            )
        return 0
    budget = options.budget if options.shrink else 0
    rows = []
    for plant in chosen:
        if options.out is not None:
            os.environ["RR_PLANTED_OUT"] = str((options.out / plant.name).resolve())
        found = search(plant, options.seeds, budget, options.first, kept=options.from_kept)
        rows.append((plant, found))
        small = rows[-1][1].get("shrunk")
        if options.keep and small and small.get("text"):
            KEPT.mkdir(exist_ok=True)
            again = f", from the kept plan's {found['events']} events" if options.from_kept else ""
            text = kept_text(
                plant,
                small["text"],
                small["seed"],
                small["events"],
                small["runs"],
                small["story"],
                again,
            )
            (KEPT / f"{plant.name}.toml").write_text(text, encoding="utf-8")
    table(rows, options.seeds, options.shrink)
    return 0


if __name__ == "__main__":
    sys.exit(main())
