"""What an experiment gives back: one `RunResult` per run, its faults and calls, and `Results`.

All times of a run are seconds from the start of its workload (`t = 0`), except the
wall-clock `started_at` (`time.time()`), which places the run in `events.jsonl` (whose
events carry wall-clock `at`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from rr_actors_lab.experiments.plan import Plan

__all__ = ["CallRecord", "FaultRecord", "Results", "RunResult", "show_value"]


@dataclasses.dataclass(frozen=True)
class FaultRecord:
    """One scheduled fault of one run: when it was meant to fire, when it did, what it did.

    Attributes:
        fault: index of the fault in the plan's `[[faults]]`.
        n: which injection of that fault (0, 1, ...).
        kind: the fault kind.
        target: the manager it hit (for `kill_resource`, the manager of the process).
        scheduled_s: when it was meant to fire (triggered: the trigger's time plus delay).
        injected_s: when it fired, or `None` if it was skipped.
        detail: what it did, for people (`"SIGKILL pid 4242"`), or why it was skipped.
        skipped: whether it did nothing (no manager or process, the run ended first).
        fail_s: a fault between hosts: seconds from the injection to the first failed
            call to an affected host's manager (`None`: none failed).
        heal_s: a fault between hosts: seconds from its end to the first call answered again.
        recovery_s: seconds from the injection until the system served again
            (docs/reference/plan.md, "Recovery"), or `None` if not within the run.
    """

    fault: int
    n: int
    kind: str
    target: str | None
    scheduled_s: float | None
    injected_s: float | None
    detail: str
    skipped: bool = False
    recovery_s: float | None = None
    fail_s: float | None = None
    heal_s: float | None = None

    @property
    def late_s(self) -> float | None:
        """Seconds from the scheduled time to the injection (the injector's error)."""
        if self.injected_s is None or self.scheduled_s is None:
            return None
        return self.injected_s - self.scheduled_s


@dataclasses.dataclass(frozen=True)
class CallRecord:
    """One call the workload made (a first call, or a reload after a `FATAL`).

    Attributes:
        client: the client's index.
        manager: the provider called.
        server: its server.
        start_s: when the call started.
        end_s: when it returned or failed.
        ok: whether it returned a response.
        retried: whether it needed more than one attempt (the provider died, was being
            restarted, or a connection was cut).
        error: the error's type name if it failed.
    """

    client: int
    manager: str
    server: str
    start_s: float
    end_s: float
    ok: bool
    retried: bool
    error: str | None = None


@dataclasses.dataclass(frozen=True)
class RunResult:
    """One run: its row of `runs.csv` and what the plots need.

    Attributes:
        plan: the plan's name.
        setting: the compared setting (`""` without `compare`).
        value: the compared value for this run (`None` without `compare`).
        run: the run's number in the experiment (1, 2, ...).
        repeat: its number among the runs of its value (1, 2, ...).
        seed: the run's seed (the same seed gives the same fault schedule).
        version: the rr_actors version that ran it.
        started_at: wall-clock start of the workload (`time.time()` seconds).
        duration_s: seconds of workload and faults.
        calls_ok: calls that returned a response.
        calls_failed: calls that failed (after retries, or at once).
        calls_retried: calls that needed more than one attempt (ok or not).
        unavailable_s: per manager, seconds it did not serve (from a kill, hang or exit).
        restarts: restarts of managers in the whole tree (nested ones included).
        gave_up: whether the top supervisor gave up (restart intensity exceeded).
        recovery_median_s: median recovery time of the faults (`None`: none recovered).
        recovery_p90_s: 90th percentile of the same.
        unrecovered: faults injected that did not recover within the run.
        leaked_processes: processes the run started that were still alive after it.
        catalog_entries_left: rows left in the readable catalogs after the clients unloaded.
        events: events recorded.
        events_dropped: events lost to a full queue (then the metrics are incomplete).
        faults: every scheduled fault of the run.
        calls: every call of the run.
        down: per manager, the `(start, end)` intervals it did not serve (`end` `None`:
            still down at the end).
        restart_times: per manager, when it served again after each exit.
        give_ups: `(supervisor, time)` of each supervisor that gave up.
        supervisor_restarts: restarts of nested supervisors.
        catalogs_unread: managers whose catalog could not be read at the end (not in
            `catalog_entries_left`).
        verdict: the verdict from its events (`check`): `"held"`, `"violated"`,
            `"unverifiable"` (`""`: not checked).
        violations: findings that are violations.
        unverifiable: findings that could not be checked (events were lost).
        findings: each finding with its window of events, as `rr-actors check` prints them.
        check_s: seconds the check took.
        hosts: the plan's hosts (empty without `[hosts]`: then the row has the medians of
            `fail_s`, `heal_s` and a `recovery_s_<host>` per host).
    """

    plan: str
    setting: str
    value: Any
    run: int
    repeat: int
    seed: int
    version: str
    started_at: float
    duration_s: float
    calls_ok: int
    calls_failed: int
    calls_retried: int
    unavailable_s: dict[str, float]
    restarts: int
    gave_up: bool
    recovery_median_s: float | None
    recovery_p90_s: float | None
    unrecovered: int
    leaked_processes: int
    catalog_entries_left: int
    events: int
    events_dropped: int
    faults: tuple[FaultRecord, ...] = ()
    calls: tuple[CallRecord, ...] = dataclasses.field(default=(), repr=False)
    down: dict[str, tuple[tuple[float, float | None], ...]] = dataclasses.field(
        default_factory=dict, repr=False
    )
    restart_times: dict[str, tuple[float, ...]] = dataclasses.field(
        default_factory=dict, repr=False
    )
    give_ups: tuple[tuple[str, float], ...] = ()
    supervisor_restarts: int = 0
    catalogs_unread: int = 0
    verdict: str = ""
    violations: int = 0
    unverifiable: int = 0
    findings: tuple[str, ...] = dataclasses.field(default=(), repr=False)
    check_s: float = 0.0
    hosts: tuple[str, ...] = ()

    def row(self) -> dict[str, Any]:
        """This run as one row of `runs.csv` (`unavailable_s_<manager>` per manager)."""
        row: dict[str, Any] = {
            "plan": self.plan,
            "setting": self.setting,
            "value": "" if self.value is None else show_value(self.value),
            "run": self.run,
            "repeat": self.repeat,
            "seed": self.seed,
            "version": self.version,
            "duration_s": round(self.duration_s, 3),
            "calls_ok": self.calls_ok,
            "calls_failed": self.calls_failed,
            "calls_retried": self.calls_retried,
        }
        for name, seconds in self.unavailable_s.items():
            row[f"unavailable_s_{name}"] = round(seconds, 4)
        row.update(
            {
                "restarts": self.restarts,
                "supervisor_restarts": self.supervisor_restarts,
                "gave_up": self.gave_up,
                "faults": sum(1 for f in self.faults if not f.skipped),
                "faults_skipped": sum(1 for f in self.faults if f.skipped),
                "recovery_median_s": _rounded(self.recovery_median_s),
                "recovery_p90_s": _rounded(self.recovery_p90_s),
                "unrecovered": self.unrecovered,
                "leaked_processes": self.leaked_processes,
                "catalog_entries_left": self.catalog_entries_left,
                "catalogs_unread": self.catalogs_unread,
                "events": self.events,
                "events_dropped": self.events_dropped,
                "verdict": self.verdict,
                "violations": self.violations,
                "unverifiable": self.unverifiable,
                "check_s": round(self.check_s, 4),
            }
        )
        if self.hosts:
            between = [f for f in self.faults if f.fail_s is not None or f.heal_s is not None]
            fails = [f.fail_s for f in between if f.fail_s is not None]
            heals = [f.heal_s for f in between if f.heal_s is not None]
            row["fail_median_s"] = _rounded(_median(fails))
            row["heal_median_s"] = _rounded(_median(heals))
            for host in self.hosts[1:]:
                times = [
                    f.recovery_s
                    for f in self.faults
                    if f.recovery_s is not None and host in _hosts_of(f)
                ]
                row[f"recovery_s_{host}"] = _rounded(_median(times))
        return row

    def verdict_counts(self) -> str:
        """The verdict with its counts, as the summary and the plots' titles show it."""
        if not self.verdict:
            return "not checked"
        return f"{self.verdict} ({self.violations} violations, {self.unverifiable} unverifiable)"

    def recoveries(self) -> list[float]:
        """The recovery times of the run's faults that recovered, in seconds."""
        return [f.recovery_s for f in self.faults if f.recovery_s is not None]


def show_value(value: Any) -> str:
    """A compared value as the plan writes it (`false`, not `False`)."""
    if isinstance(value, bool):
        return str(value).lower()
    return str(value)


def _median(values: list[float]) -> float | None:
    ordered = sorted(values)
    if not ordered:
        return None
    middle = len(ordered) // 2
    return ordered[middle] if len(ordered) % 2 else (ordered[middle - 1] + ordered[middle]) / 2


def _hosts_of(fault: FaultRecord) -> set[str]:
    """The hosts a fault between hosts names in its target (`a-b`, `b+c`, `b`)."""
    return set((fault.target or "").replace("+", "-").split("-"))


def _rounded(value: float | None) -> float | str:
    return "" if value is None else round(value, 4)


@dataclasses.dataclass(frozen=True)
class Results:
    """Everything an experiment produced.

    Attributes:
        plan: the plan that ran (with the overrides of `run`).
        runs: the finished runs, in the order they ran.
        out: the output directory, or `None` if nothing was written.
        interrupted: whether it was stopped (Ctrl-C) before every run finished.
    """

    plan: Plan
    runs: tuple[RunResult, ...]
    out: Path | None = None
    interrupted: bool = False

    def rows(self) -> list[dict[str, Any]]:
        """Every run as a row of `runs.csv`."""
        return [run.row() for run in self.runs]

    def by_value(self) -> list[tuple[Any, list[RunResult]]]:
        """The runs grouped by compared value, in the plan's order of values."""
        grouped: list[tuple[Any, list[RunResult]]] = [(v, []) for v, _ in self.plan.variants]
        for run in self.runs:
            for value, runs in grouped:
                if type(value) is type(run.value) and value == run.value:  # False is not 0
                    runs.append(run)
                    break
        return grouped

    def faults(self) -> Iterator[tuple[RunResult, FaultRecord]]:
        """Every fault of every run, with its run."""
        for run in self.runs:
            for fault in run.faults:
                yield run, fault
