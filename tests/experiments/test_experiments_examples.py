"""Every shipped plan (rr_actors/experiments/plans/, and examples/experiments/) runs
(shortened: one repeat, a shorter duration) and shows what its docs page says it shows.

The full runs (`--repeat 3`, under a minute each) made the figures of docs/experiments/.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from rr_actors.experiments import Results, RunResult, load_plan, plans, run

EXAMPLES = Path(__file__).resolve().parents[2] / "examples" / "experiments"

SHIPPED = {"strategies", "crashloop", "hang", "resource", "first", "killheavy", "leases"}
"""Every plan shipped in the package; the tutorial's `first` runs in the docs test."""


def shortened(name: str, duration: float) -> Results:
    path = EXAMPLES / "workload.toml" if name == "workload" else plans.find(name)
    return run(load_plan(path), repeat=1, duration=duration)


def by_value(results: Results) -> dict[object, RunResult]:
    return {value: runs[0] for value, runs in results.by_value()}


def test_this_test_knows_every_shipped_plan() -> None:
    assert SHIPPED == set(plans.shipped())
    assert {"workload"} == {p.stem for p in EXAMPLES.glob("*.toml")}


def restarted_after_first_kill(result: RunResult) -> set[str]:
    """Managers that served again after the run's first kill, before its second one."""
    kills = [f for f in result.faults if f.injected_s is not None]
    start = kills[0].injected_s
    assert start is not None
    end = kills[1].injected_s if len(kills) > 1 else float("inf")
    assert end is not None
    return {
        name for name, times in result.restart_times.items() if any(start < t < end for t in times)
    }


def test_strategies_restart_one_all_or_the_rest_after_a_kill() -> None:
    runs = by_value(shortened("strategies", 2.0))

    for strategy, result in runs.items():
        first = next(f for f in result.faults if f.injected_s is not None)
        restarted = restarted_after_first_kill(result)
        order = ["erm", "cm", "rm"]
        expected = {
            "one_for_one": {first.target},
            "one_for_all": set(order),
            "rest_for_one": set(order[order.index(str(first.target)) :]),
        }[str(strategy)]
        assert expected == restarted, (strategy, first)
        assert 0 == result.leaked_processes


def tripped(result: RunResult) -> bool:
    """Whether the pool's intensity was exceeded: 3 kills of its worker within its 2 s
    period (its `max_restarts` is 2). A kill is skipped while the worker is down, so how
    many land depends on how fast it restarts, which a loaded machine slows."""
    kills = sorted(
        f.injected_s for f in result.faults if f.injected_s is not None and not f.skipped
    )
    # (2.5 s, not 2: the period counts restarts, which follow their kills by how long each
    # exit took to be seen and handled)
    return any(last - first <= 2.5 for first, last in zip(kills, kills[2:], strict=False))


def test_the_crash_loop_escalates_and_only_a_tolerant_top_survives_it() -> None:
    runs = by_value(shortened("crashloop", 3.0))

    for result in runs.values():  # the pool gives up only when kills came fast enough
        assert tripped(result) or "pool" not in {sup for sup, _ in result.give_ups}
    # (whether they did depends on restart speed, which load slows: a loaded machine may
    # see no escalation at all; the top that tolerates none gives up with its pool)
    pool_gave_up = "pool" in {sup for sup, _ in runs[0].give_ups}
    assert runs[0].gave_up == pool_gave_up
    assert not runs[5].gave_up
    # The tolerant top keeps serving: it fails no more calls than the top that gave up (a
    # call may still time out on a loaded machine while its worker is being restarted).
    assert runs[5].calls_ok > 0
    assert runs[5].calls_failed <= runs[0].calls_failed


def test_the_kill_heavy_plan_breaks_no_rule_and_leaves_nothing() -> None:
    (result,) = shortened("killheavy", 3.0).runs

    assert result.restarts >= 3  # (a kill every 0.15-0.4 s, of edge, api or db)
    assert [] == list(result.findings)
    # (a consumer killed after a release failed, its provider being down, reconciles
    # with every registrar when it is restored: the provider releases the id)
    assert 0 == result.catalog_entries_left, result.findings
    assert 0 == result.leaked_processes


def test_the_heartbeat_finds_a_hang_and_without_it_the_hang_lasts() -> None:
    runs = by_value(shortened("hang", 2.0))

    off, fast = runs[False], runs[0.1]
    assert 0 == off.restarts
    assert 1.2 == pytest.approx(off.unavailable_s["planner"], abs=0.1)
    assert 1 == fast.restarts
    (hang,) = fast.faults
    assert hang.recovery_s is not None  # the heartbeat's restart served again (how soon is
    # a figure of docs/experiments/hang.md, measured on a quiet machine, not a test's bound)


def test_a_killed_resource_process_is_heard_and_loaded_again() -> None:
    results = shortened("resource", 2.5)

    killed = [f for _, f in results.faults() if f.injected_s is not None]
    assert killed
    assert all("a process of erm" in f.detail for f in killed)
    assert any(f.recovery_s is not None for f in killed)
    assert [0, 0] == [r.leaked_processes for r in results.runs]


def test_the_workload_plan_calls_through_its_factory_in_lidars_py() -> None:
    # workload.toml names `factory = "lidars:lidar"`: examples/experiments/lidars.py
    (result,) = shortened("workload", 2.0).runs

    assert result.calls_ok > 0
    assert {"cm"} == {c.manager for c in result.calls}
    (kill,) = result.faults
    assert kill.recovery_s is not None


def test_the_leases_plan_compares_three_leases_under_a_cut_and_a_freeze() -> None:
    """(Its runs need root and take minutes: tests/experiments/test_experiments_hosts.py
    runs a small plan of the same shape for real.)"""
    plan = load_plan(plans.find("leases"))
    assert [0.5, 1.0, 2.0] == [value for value, _ in plan.variants]
    assert [0.5, 1.0, 2.0] == [p.hosts.lease for _, p in plan.variants if p.hosts is not None]
    assert ["cut", "freeze"] == [fault.kind for fault in plan.faults]
