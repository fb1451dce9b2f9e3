"""The experiment's figures (`rr_actors_lab.experiments.plot`): recovery.png and timeline.png across
hosts: per-host recovery, each fault's host, the time to fail and to heal of faults between
hosts, the verdict in the titles. Drawn from results built by hand (no run, no namespaces) and
read back from the figures."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("matplotlib")

from matplotlib.figure import Figure

from rr_actors_lab.experiments import parse_plan
from rr_actors_lab.experiments.plot import plot_recovery, plot_timeline
from rr_actors_lab.experiments.results import CallRecord, FaultRecord, Results, RunResult

SERVICE = "rr_actors_lab.experiments.services:service"

TREE = f"""\
[tree]
[[tree.children]]
name = "db"
setup = "{SERVICE}"
{{db_host}}

[[tree.children]]
name = "api"
setup = "{SERVICE}"
"""

HOSTS = (
    """\
name = "across"
duration = 6.0

[hosts]
names = ["a", "b"]

"""
    + TREE.format(db_host='host = "b"')
    + """
[[faults]]
kind = "kill_manager"             # managers of the run's own host only
target = "api"
at = [1.0]

[[faults]]
kind = "cut"
link = ["a", "b"]
at = [2.0]
for = 1.5

[[faults]]
kind = "freeze"
target = "b"
at = [4.5]
for = 0.5

[compare]
setting = "hosts.lease"
values = [0.5, 2.0]
"""
)

ONE_HOST = (
    """\
name = "alone"
duration = 6.0

"""
    + TREE.format(db_host="")
    + """
[[faults]]
kind = "kill_manager"
target = ["db", "api"]
at = [0.5, 1.0]
"""
)


def run_result(value: Any, faults: tuple[FaultRecord, ...], *, hosts: bool) -> RunResult:
    return RunResult(
        plan="p",
        setting="hosts.lease" if hosts else "",
        value=value,
        run=1,
        repeat=1,
        seed=0,
        version="0",
        started_at=0.0,
        duration_s=6.0,
        calls_ok=50,
        calls_failed=3,
        calls_retried=4,
        unavailable_s={"db": 0.2, "api": 0.1},
        restarts=2,
        gave_up=False,
        recovery_median_s=0.1,
        recovery_p90_s=0.2,
        unrecovered=0,
        leaked_processes=0,
        catalog_entries_left=0,
        events=100,
        events_dropped=0,
        faults=faults,
        calls=(
            CallRecord(0, "db", "resource", 0.1, 0.2, ok=True, retried=False),
            CallRecord(0, "db", "resource", 2.0, 2.6, ok=False, retried=True, error="E"),
        ),
        down={"db": ((0.5, 0.6),), "api": ((1.0, 1.1),)},
        restart_times={"db": (0.6,), "api": (1.1,)},
        verdict="held",
        hosts=("a", "b") if hosts else (),
    )


def kill_api() -> FaultRecord:
    return FaultRecord(0, 0, "kill_manager", "api", 1.0, 1.0, "SIGKILL", recovery_s=0.12)


def kills() -> tuple[FaultRecord, ...]:
    return (
        FaultRecord(0, 0, "kill_manager", "db", 0.5, 0.5, "SIGKILL", recovery_s=0.1),
        kill_api(),
    )


def across(lease: float, *, cut_failed: bool) -> RunResult:
    """A run with a kill of api (on a), a cut of a-b (a call failed if `cut_failed`) and a
    freeze of b shorter than the lease (no call failed)."""
    cut = FaultRecord(
        1,
        0,
        "cut",
        "a-b",
        2.0,
        2.0,
        "link a-b down for 1.5 s",
        recovery_s=1.9,
        fail_s=lease if cut_failed else None,
        heal_s=0.4,
    )
    freeze = FaultRecord(2, 0, "freeze", "b", 4.5, 4.5, "SIGSTOP", recovery_s=0.6, heal_s=0.1)
    return run_result(lease, (kill_api(), cut, freeze), hosts=True)


def legend_labels(figure: Figure) -> list[str]:
    legends = [*figure.legends, *(ax.get_legend() for ax in figure.axes)]
    return [t.get_text() for legend in legends if legend is not None for t in legend.get_texts()]


def texts(figure: Figure) -> list[str]:
    found = [t.get_text() for t in figure.texts]
    for ax in figure.axes:
        found += [t.get_text() for t in ax.texts] + [ax.get_title(loc="left"), ax.get_title()]
        found += [t.get_text() for t in ax.get_yticklabels()]
    return found


def with_hosts() -> Results:
    plan = parse_plan(HOSTS)
    runs = (across(0.5, cut_failed=True), across(2.0, cut_failed=False))
    return Results(plan=plan, runs=runs)


def test_recovery_names_the_hosts_the_faults_hit_and_plots_time_to_fail_and_heal(
    tmp_path: Path, drawn: list[Figure]
) -> None:
    plot_recovery(with_hosts(), tmp_path / "recovery.png")
    (figure,) = drawn
    labels = legend_labels(figure)
    shown = texts(figure)

    assert {"host a", "host b", "cut", "freeze"} <= set(labels)
    assert any(title.startswith("time to fail") for title in shown)
    assert any(title.startswith("time to heal") for title in shown)
    assert any("2 faults\n1: no call failed" in text for text in shown)  # the freeze at 0.5
    assert any("verdicts: 2 held" in text for text in shown)
    assert (tmp_path / "recovery.png").read_bytes().startswith(b"\x89PNG")


def test_the_timeline_marks_the_host_each_fault_hit(tmp_path: Path, drawn: list[Figure]) -> None:
    plot_timeline(with_hosts(), tmp_path / "timeline.png")
    (figure,) = drawn
    shown = texts(figure)

    assert {"fault on host a", "fault on host b"} <= set(legend_labels(figure))
    assert {"db @b", "api @a", "kill api @a", "cut a-b", "freeze b"} <= set(shown)
    assert any("held (0 violations, 0 unverifiable)" in text for text in shown)


def test_without_hosts_the_plots_name_no_host(tmp_path: Path, drawn: list[Figure]) -> None:
    results = Results(plan=parse_plan(ONE_HOST), runs=(run_result(None, kills(), hosts=False),))

    plot_recovery(results, tmp_path / "recovery.png")
    plot_timeline(results, tmp_path / "timeline.png")
    recovery, timeline = drawn

    assert 3 == len(recovery.axes)
    assert [] == [label for label in legend_labels(recovery) if "host" in label]
    assert "fault" in legend_labels(timeline)
    assert {"db", "api", "kill db", "kill api"} <= set(texts(timeline))
