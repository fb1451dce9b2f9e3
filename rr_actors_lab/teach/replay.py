"""A simulated seed replayed step by step in the browser (`rr-actors teach replay`).

```
 a seed of a plan (an exercise's folder, the student's step in place; or a plan file)
   simulate.run_seed ─► history ─► story.story: the steps (events, faults, violations)
   Replay: each step's event folded into a state (the tree, each registrar's catalog);
           a checkpoint every CHECKPOINT steps (JSON text): state_at(n) folds at most
           CHECKPOINT - 1 steps after the checkpoint before n
   judge(plan, run) ─► the check's Verdict: passed, or the rule broken, in words, and the
           step of its first violating event (default: the checker's rules alone)
   show(n) ─► the observer's hub: "tree", "catalog/<name>", "graph" (shown by the
           observer's own page), "replay" (the step, the story around it, what is in flight,
           the verdict)
 the page (the observer's, mode "replay"): first, back, play/pause, step, a slider, a
   click on a story line ── POST /api/control {"step": n} ─► show(n) ─► the stream
 live (`rerun`): a manager's kill or cut ── {"fault", "target"} ─► branch: the plan and
   one more fault `after` the shown step's event, run again (`rerun`), shown at the fault
```

Each step shows what the events say, never the registrars read: the children's states,
each registrar's rows (from the catalog events), and in flight the calls begun and not
yet answered and the statuses whose last delivery comes later.
"""

from __future__ import annotations

import dataclasses
import json
import re
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rr_actors import events
from rr_actors.errors import ConfigError
from rr_actors_lab.experiments import check, simulate, story
from rr_actors_lab.experiments.plan import FaultKind, FaultPlan, Plan, SupervisorPlan, Trigger
from rr_actors_lab.observe._hub import Hub
from rr_actors_lab.observe._observer import Observer, require_extra
from rr_actors_lab.observe._sources import event_dict
from rr_actors_lab.observe._view import dependency_graph, summarise_catalog
from rr_actors_lab.teach import grade

__all__ = [
    "BRANCHES",
    "CHECKPOINT",
    "WINDOW",
    "Replay",
    "Verdict",
    "checker_verdict",
    "exercise_verdict",
    "open_replay",
]

CHECKPOINT = 32
"""Steps between two kept states: a step is at most this many folds away from one."""

BRANCHES: dict[str, FaultKind] = {"kill": "kill_manager", "cut": "cut_connections"}
"""The faults a live replay's page adds (`Replay.branch`): the plan's fault kinds."""

WINDOW = (12, 6)
"""Story lines the page shows before the step and after it."""


@dataclasses.dataclass(frozen=True)
class Verdict:
    """What a check says of a replayed run (the page shows it above the story).

    Attributes:
        passed: it held every rule.
        rule: the first rule it broke, e.g. `"dependency"` (`""`: passed).
        words: that rule in words (an exercise's rule; `""`: none to tell).
        message: what broke it, in this run.
        line: the history's line of its first violating event (`None`: passed, or no
            event shows it: a setup that raised, a plan refused before any run).
        checker: the checker's own verdict of the run (`"held"`, `"violated"`, ...), which
            knows the semantic rules only, not an exercise's own.
    """

    passed: bool
    rule: str = ""
    words: str = ""
    message: str = ""
    line: int | None = None
    checker: str = "held"


def checker_verdict(plan: Plan, run: simulate.SimulatedRun) -> Verdict:
    """The verdict of the semantic rules' checker on `run` (a replay without an exercise):
    its first violation (by its last event), or the crash; an unverifiable run passes,
    as it does a check."""
    words = "the semantic rules alone (no exercise's folder: its own rules are not checked)"
    if run.verdict == "crashed":
        said = run.findings[0] if run.findings else "the system raised"
        return Verdict(False, "crashed", words, said, None, run.verdict)
    if run.verdict != "violated":
        return Verdict(True, words=words, checker=run.verdict)
    numbered = check.read_runs(run.history.splitlines()).get(simulate.RUN, [])
    resolve = plan.hosts.resolve if plan.hosts is not None else "first_served"
    found = [f for f in check.check(numbered, resolve).findings if f.kind == "violation"]
    if not found:
        return Verdict(True, words=words, checker=run.verdict)
    first = min(found, key=lambda f: max(f.lines, default=0))
    line = max(first.lines) if first.lines else None
    return Verdict(False, first.rule, words, first.message, line, run.verdict)


def exercise_verdict(folder: Path) -> Callable[[Plan, simulate.SimulatedRun], Verdict]:
    """The verdict of `folder`'s check on a run of a plan (`grade.judge`: the exercise's
    rules besides the checker's), for `Replay`'s `judge`."""

    def judge(plan: Plan, run: simulate.SimulatedRun) -> Verdict:
        failure = grade.judge(folder, plan, run)
        if failure is None:
            return Verdict(True, checker=run.verdict)
        at = re.match(r"#(\d+):", failure.first_event or "")  # (`Failure.first_event`'s form)
        line = int(at.group(1)) if at is not None else None
        return Verdict(False, failure.rule, failure.words, failure.message, line, run.verdict)

    return judge


@dataclasses.dataclass(frozen=True)
class _Step:
    line: story.StoryLine
    at: float  # virtual seconds, the run's clock (an event's `at`)
    event: events.Event | None  # a fault's or a violation's step: None


class Replay:
    """The steps of one simulated run and the state at each (`state_at`, `sections`).

    Args:
        plan: the plan the run ran (its tree: the names, strategies and kinds).
        run: the run (its history).
        hub: where `show` puts the sections (`None`: a hub of its own).
        rerun: runs the seed of a plan again (`branch`; `None`: the page cannot).
        judge: the check's verdict of a run of a plan (`None`: `checker_verdict`), asked
            for this run and each rerun, on the thread that makes it.
    """

    def __init__(
        self,
        plan: Plan,
        run: simulate.SimulatedRun,
        hub: Hub | None = None,
        rerun: Callable[[Plan], simulate.SimulatedRun] | None = None,
        judge: Callable[[Plan, simulate.SimulatedRun], Verdict] | None = None,
    ) -> None:
        self.hub = hub if hub is not None else Hub(convert=event_dict)
        self.shown = 0
        self.rerun = rerun
        self.judge = judge if judge is not None else checker_verdict
        # the page's requests run on a server's threads: one at a time (a kill's rerun
        # replaces the steps while a scrub would read them; a double click reruns once)
        self._lock = threading.RLock()
        self._load(plan, run)

    def _load(self, plan: Plan, run: simulate.SimulatedRun) -> None:
        self.plan = plan
        self.run = run
        texts = run.history.splitlines()
        numbered = dict(check.read_runs(texts).get(simulate.RUN, []))
        lines = story.story(run.history)
        ats = [e.at for e in numbered.values()]
        start = min(ats, default=0.0)
        self.steps = [_Step(line, start + line.at_s, numbered.get(line.line)) for line in lines]
        self.verdict = self.judge(plan, run)
        self.violating = self._violating(self.verdict)
        self._managers = {m.name: m for m in plan.managers()}
        self._in_flight = self._flights()
        self._checkpoints: list[str] = []
        state = self._empty()
        for index, step in enumerate(self.steps):
            if index % CHECKPOINT == 0:
                self._checkpoints.append(json.dumps(state))
            _fold(state, step.event)

    def _violating(self, verdict: Verdict) -> int | None:
        """The step (1..len) of `verdict`'s first violating event, or of the run's crash;
        `None`: none."""
        for index, step in enumerate(self.steps, 1):
            if verdict.line is not None and step.line.line == verdict.line:
                return index
            if verdict.rule == "crashed" and step.line.who == "crashed":
                return index
        return None

    # -- the state at a step ------------------------------------------------------------

    def __len__(self) -> int:
        return len(self.steps)

    def state_at(self, n: int) -> dict[str, Any]:
        """The state once steps 1..`n` happened (`n` in 1..len; 0: before the first)."""
        n = max(0, min(n, len(self.steps)))
        base = min((n // CHECKPOINT), len(self._checkpoints) - 1) if self._checkpoints else 0
        state: dict[str, Any] = (
            json.loads(self._checkpoints[base]) if self._checkpoints else self._empty()
        )
        for step in self.steps[base * CHECKPOINT : n]:
            _fold(state, step.event)
        return state

    def sections(self, n: int) -> dict[str, Any]:
        """What the page shows at step `n` (1..len): its sections, by key."""
        n = max(1, min(n, len(self.steps))) if self.steps else 0
        state = self.state_at(n)
        at = self.steps[n - 1].at if n else 0.0
        tree = {**self._supervisor(self.plan.tree, state), "server_time": at}
        gave_up = state["gave_up"].get(self.plan.tree.name)
        tree["state"] = "gave up" if gave_up is not None else "running"
        tree["gave_up"] = gave_up
        catalogs: dict[str, dict[str, Any]] = {}
        for name, rows in state["catalogs"].items():
            child = state["children"].get(name)
            manager = self._managers.get(name)
            kind = f"{manager.isolation} manager" if manager is not None else "consumer"
            up = child["state"] if child is not None else ("running" if manager is None else "")
            catalogs[name] = {
                "registrar": name,
                "kind": kind,
                "state": up or "starting",
                "available": up == "running",
                "catalog": _summary(name, rows),
                "error": None,
            }
        states = {name: c["state"] for name, c in catalogs.items()}
        graph = dependency_graph({n: c["catalog"] for n, c in catalogs.items()}, states)
        sections: dict[str, Any] = {"tree": tree, "graph": graph}
        sections.update({f"catalog/{name}": c for name, c in catalogs.items()})
        sections["replay"] = self._replay(n, at)
        return sections

    def show(self, n: int) -> int:
        """Put step `n`'s sections into the hub (clamped to 1..len); the step shown."""
        with self._lock:
            n = max(1, min(int(n), len(self.steps))) if self.steps else 0
            sections = self.sections(n)
            for key in self.hub.keys("catalog/"):
                if key not in sections:
                    self.hub.remove(key)
            for key, value in sections.items():
                self.hub.put(key, value)
            self.shown = n
            return n

    def control(self, data: dict[str, Any]) -> dict[str, Any]:
        """The page's request: `{"step": n}` shows step `n`; `{"fault": "kill" | "cut",
        "target": manager}` runs the seed again with that fault right after the step
        shown (`branch`). The answer (JSON). One request at a time (any thread)."""
        with self._lock:
            return self._control(data)

    def _control(self, data: dict[str, Any]) -> dict[str, Any]:
        if "fault" in data:
            kind, target = data.get("fault"), data.get("target")
            if kind not in BRANCHES or not isinstance(target, str):
                raise ConfigError(f"a fault is kill or cut of a manager, got {kind!r} {target!r}")
            message = self.branch(kind, target)
            return {"ok": True, "message": message, "step": self.shown, "steps": len(self)}
        step = data.get("step")
        if isinstance(step, bool) or not isinstance(step, int):
            raise ConfigError(f"a step is a whole number, got {step!r}")
        return {"ok": True, "step": self.show(step), "steps": len(self.steps)}

    def branch(self, kind: str, target: str) -> str:
        """Run the seed again with one more fault, `kind` (`BRANCHES`) of manager `target`, right
        after the shown step's event; show the same step of the new run. What happened, in words.

        Raises:
            ConfigError: a replay without `rerun`; `target` is not a process manager of the
                plan; nothing happened yet to trigger it on.
        """
        if self.rerun is None:
            raise ConfigError("this replay shows a recorded run: it cannot run it again")
        manager = self._managers.get(target)
        if manager is None or manager.isolation != "process":
            raise ConfigError(f"{target!r} is not a process manager of plan {self.plan.name}")
        n = self.shown
        at = next((m for m in range(n, 0, -1) if self.steps[m - 1].event is not None), 0)
        if at == 0:
            raise ConfigError("no event yet to put the fault after: step on first")
        event = self.steps[at - 1].event
        nth = sum(1 for s in self.steps[:at] if type(s.event) is type(event))
        fault = FaultPlan(
            kind=BRANCHES[kind],
            targets=(target,),
            after=Trigger(event=type(event).__name__, nth=nth),
        )
        before = [s.line.plain() for s in self.steps[:n]]
        plan = dataclasses.replace(self.plan, faults=(*self.plan.faults, fault))
        self._load(plan, self.rerun(plan))
        landed = next(
            (i for i, s in enumerate(self.steps, 1)
             if i >= at and s.line.who == "fault" and s.line.plain() not in before
             and s.line.text.startswith(f"{BRANCHES[kind]} {target}")),
            None,
        )  # fmt: skip
        kept = min(n, landed - 1 if landed is not None else n)
        same = [s.line.plain() for s in self.steps[:kept]] == before[:kept]
        self.show(landed if landed is not None else n)  # (the fault's own step: next, its effect)
        where = f"at step {landed}" if landed is not None else "nowhere (it did not fire)"
        told = "the steps before it are the same" if same else "the steps before it changed"
        return (
            f"{BRANCHES[kind]} {target} after step {at}: run again ({len(self)} steps), "
            f"the fault {where}; {told}"
        )

    # -- the observer's source protocol ---------------------------------------------------

    def start(self) -> None:
        """Show the first step."""
        self.show(1)

    def close(self, timeout: float = 5.0) -> None:
        """Nothing runs: nothing to stop."""

    # -- parts ----------------------------------------------------------------------------

    def _empty(self) -> dict[str, Any]:
        children = {
            m.name: {"state": "starting", "pid": None, "restarts": 0, "last_exit": None}
            for m in self.plan.managers()
        }
        for sup in self.plan.tree.supervisors()[1:]:
            children[sup.name] = {
                "state": "starting",
                "pid": None,
                "restarts": 0,
                "last_exit": None,
            }
        return {"children": children, "gave_up": {}, "catalogs": {}}

    def _supervisor(self, sup: SupervisorPlan, state: dict[str, Any]) -> dict[str, Any]:
        children = []
        for child in sup.children:
            now = state["children"][child.name]
            entry: dict[str, Any] = {"name": child.name, **now, "restart_due": None}
            if isinstance(child, SupervisorPlan):
                entry.update(self._supervisor(child, state), kind="supervisor")
                entry["restart"] = child.restart
                entry["isolation"] = None
                if child.name in state["gave_up"]:
                    entry["state"] = "gave up"
            else:
                entry.update(
                    kind="manager", isolation=child.isolation, restart=child.restart,
                    hang_after=None,
                )  # fmt: skip
            children.append(entry)
        return {
            "name": sup.name,
            "kind": "supervisor",
            "strategy": sup.strategy,
            "max_restarts": sup.max_restarts,
            "period": sup.period,
            "children": children,
        }

    def _flights(self) -> list[tuple[float, int, int, dict[str, Any]]]:
        """Each call and status of the run: (begun at, begun at step, ended at step, row)."""
        flights: list[tuple[float, int, int, dict[str, Any]]] = []
        sent: dict[str, tuple[int, dict[str, Any]]] = {}
        last: dict[str, int] = {}
        for index, step in enumerate(self.steps, 1):
            e = step.event
            if isinstance(e, events.CallAnswered | events.CallFailed | events.CallWithdrawn):
                if e.started > 0:
                    outcome = {
                        events.CallAnswered: "answered",
                        events.CallFailed: "failed",
                        events.CallWithdrawn: "withdrawn",
                    }[type(e)]
                    row = {
                        "kind": "call",
                        "id": e.query_id,
                        "from": e.registrar,
                        "to": f"{e.serving_rr}/{e.server}",
                        "then": f"{outcome} at step {index}",
                    }
                    flights.append((e.started, 0, index, row))
            elif isinstance(e, events.StatusSent):
                row = {
                    "kind": "status",
                    "id": e.status_id or e.query_id,
                    "from": e.registrar,
                    "to": f"the consumers of {e.query_id[:8]}",
                    "then": "",
                }
                sent[e.status_id] = (index, row)
            elif isinstance(e, events.StatusDelivered) and e.status_id in sent:
                last[e.status_id] = index
        for status_id, (index, row) in sent.items():
            end = last.get(status_id, index)
            row["then"] = f"last delivered at step {end}"
            flights.append((float("-inf"), index, end, row))
        return flights

    def _replay(self, n: int, at: float) -> dict[str, Any]:
        before, after = WINDOW
        rows = []
        for index in range(max(1, n - before), min(len(self.steps), n + after) + 1):
            line = self.steps[index - 1].line
            rows.append(
                {
                    "step": index,
                    "line": line.line,
                    "at_s": round(line.at_s, 6),
                    "who": line.who,
                    "pid": line.pid,
                    "text": line.text,
                    "marked": line.marked,
                    "violating": index == self.violating,
                }
            )
        flying = [
            row
            for begun, begun_step, ended, row in self._in_flight
            if ended > n and (begun <= at if begun_step == 0 else begun_step <= n)
        ]
        current = self.steps[n - 1].line if n else None
        verdict = self.verdict
        return {
            "plan": self.plan.name,
            "seed": self.run.seed,
            "verdict": self.run.verdict,
            "check": {
                "outcome": "passed" if verdict.passed else "FAILED",
                "rule": verdict.rule,
                "words": verdict.words,
                "message": verdict.message,
                "step": self.violating,
                "checker": verdict.checker,
            },
            "step": n,
            "steps": len(self.steps),
            "at_s": round(current.at_s, 6) if current is not None else 0.0,
            "story": rows,
            "in_flight": flying,
        }


def _summary(name: str, rows: dict[str, Any]) -> dict[str, Any]:
    """A registrar's rows as the observer's catalog summary (`summarise_catalog`'s shape)."""
    summary = summarise_catalog(name, [], [])
    servers: list[str] = []
    resources = []
    for rid, r in rows["resources"].items():
        if r["server"] not in servers:
            servers.append(r["server"])
        label = r["label"] or rid[:8]
        resources.append(
            {
                "id": rid,
                "server": r["server"],
                "state": r["state"],
                "in_doubt": r["state"] != "loaded",
                "request": label,
                "response": "",
                "label": label,
                "consumers": [{"query_id": q, "origin": o} for q, o in r["consumers"].items()],
            }
        )
    clients = [
        {
            "query_id": qid,
            "serving_rr": c["serving_rr"],
            "server": c["server"],
            "request": "",
            "parent": c["parent"],
            "loaded": c["loaded"],
        }
        for qid, c in rows["clients"].items()
    ]
    in_doubt = [{"id": rid, "request": cut} for rid, cut in rows["in_doubt"].items()]
    summary.update(servers=servers, resources=resources, clients=clients, in_doubt=in_doubt)
    return summary


def _rows(state: dict[str, Any], registrar: str) -> dict[str, Any]:
    catalogs: dict[str, Any] = state["catalogs"]
    rows: dict[str, Any] = catalogs.setdefault(
        registrar, {"resources": {}, "clients": {}, "in_doubt": {}}
    )
    return rows


def _fold(state: dict[str, Any], e: events.Event | None) -> None:  # noqa: PLR0912
    """Change `state` by what event `e` says happened (`None`: a fault or a violation)."""
    children = state["children"]
    if isinstance(e, events.ChildStarted | events.ChildRestarted):
        child = children.setdefault(e.child, {"restarts": 0, "last_exit": None})
        child.update(state="running", pid=e.pid)
        if isinstance(e, events.ChildRestarted):
            child["restarts"] += 1
    elif isinstance(e, events.ChildExited):
        child = children.setdefault(e.child, {"restarts": 0, "pid": None})
        ends = e.restart == "temporary" or (e.restart == "transient" and e.normal)
        child.update(state="stopped" if ends or e.stopped else "restarting", last_exit=e.reason)
    elif isinstance(e, events.SupervisorGaveUp):
        state["gave_up"][e.supervisor] = e.reason
    elif isinstance(e, events.CatalogRestored):
        rows = _rows(state, e.registrar)
        if e.complete:  # (a label: the one its load said, if this replay saw it)
            labels = {rid: r["label"] for rid, r in rows["resources"].items()}
            rows["resources"] = {
                r[0]: {"server": r[1], "state": r[2], "label": labels.get(r[0]), "consumers": {}}
                for r in e.resources
            }
            for qid, rid, consumer in e.consumers:
                if rid in rows["resources"]:
                    rows["resources"][rid]["consumers"][qid] = consumer
            rows["clients"] = {
                c[0]: {"serving_rr": c[1], "server": c[2], "parent": c[3] or None, "loaded": True}
                for c in e.clients
            }
            rows["in_doubt"] = {}
    elif isinstance(e, events.ResourceLoaded):
        _rows(state, e.registrar)["resources"][e.resource_id] = {
            "server": e.server, "state": "loaded", "label": e.label, "consumers": {},
        }  # fmt: skip
    elif isinstance(e, events.ResourceUnloaded):
        _rows(state, e.registrar)["resources"].pop(e.resource_id, None)
    elif isinstance(e, events.ConsumerAdded):
        resource = _rows(state, e.registrar)["resources"].get(e.resource_id)
        if resource is not None:
            resource["consumers"][e.query_id] = e.consumer
    elif isinstance(e, events.ConsumerReleased):
        resource = _rows(state, e.registrar)["resources"].get(e.resource_id)
        if resource is not None:
            resource["consumers"].pop(e.query_id, None)
    elif isinstance(e, events.CallAnswered):
        _rows(state, e.registrar)["clients"][e.query_id] = {
            "serving_rr": e.serving_rr, "server": e.server, "parent": e.parent, "loaded": True,
        }  # fmt: skip
    elif isinstance(e, events.CallFailed):
        clients = _rows(state, e.registrar)["clients"]
        if e.may_have_executed:
            clients[e.query_id] = {
                "serving_rr": e.serving_rr, "server": e.server, "parent": None, "loaded": False,
            }  # fmt: skip
        else:
            clients.pop(e.query_id, None)
    elif isinstance(e, events.QueryForgotten):
        _rows(state, e.registrar)["clients"].pop(e.query_id, None)
    elif isinstance(e, events.InDoubt):
        _rows(state, e.registrar)["in_doubt"][e.query_id] = f"{e.server} {e.cut}".strip()
    elif e is not None and hasattr(e, "registrar"):
        _rows(state, str(e.registrar))  # (a registrar named: its card shows)


def open_replay(
    plan: Plan,
    run: simulate.SimulatedRun,
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    rerun: Callable[[Plan], simulate.SimulatedRun] | None = None,
    judge: Callable[[Plan, simulate.SimulatedRun], Verdict] | None = None,
) -> tuple[Observer, Replay]:
    """Open the observer's page on a replay of `run` (of `plan`), at its first step;
    with `rerun` (a plan's run of the same seed), the page's kill and cut buttons run it
    again with that fault (`Replay.branch`). `judge` gives the check's verdict the page
    shows (default: `checker_verdict`).

    Returns:
        The open observer (its `url`; `close()` it) and the replay it shows.

    Raises:
        ConfigError: the `observe` extra is missing; the port is in use.
    """
    require_extra()
    replay = Replay(plan, run, rerun=rerun, judge=judge)
    hello = {
        "mode": "replay",
        "title": f"replay of {plan.name}, seed {run.seed}",
        "pid": 0,
        "opened": time.time(),
        "branches": rerun is not None,
    }
    observer = Observer(
        replay,
        replay.hub,
        host=host,
        port=port,
        allow_remote=False,
        hello=hello,
        faults=None,
        control=replay.control,
    )
    return observer, replay
