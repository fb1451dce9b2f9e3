"""A run's numbers from its events (`rr_actors_lab.experiments.metrics`): down intervals,
unavailability, recovery per fault kind."""

from __future__ import annotations

from rr_actors import events
from rr_actors_lab.experiments import FaultRecord
from rr_actors_lab.experiments.metrics import (
    ClientRecovery,
    down_intervals,
    percentile,
    recovery_time,
    restarts,
    unavailable,
)

T0 = 1024.0  # times below are binary fractions: sums and differences stay exact


def exited(child: str, at: float, supervisor: str = "root") -> events.ChildExited:
    return events.ChildExited(supervisor, child, 1, "killed by SIGKILL", at=T0 + at)


def restarted(child: str, at: float, supervisor: str = "root") -> events.ChildRestarted:
    return events.ChildRestarted(supervisor, child, 2, 0.1, at=T0 + at)


def consumer(provider: str, of: str, at: float = 0.5) -> events.ConsumerAdded:
    return events.ConsumerAdded(provider, "r", "q", of, at=T0 + at)


def fault(kind: str, target: str, at: float) -> FaultRecord:
    return FaultRecord(0, 0, kind, target, at, at, "")


def test_a_manager_is_down_from_its_exit_to_its_restart() -> None:
    seen = [exited("a", 1.0), restarted("a", 1.25), exited("a", 2.0), restarted("a", 2.5)]

    down = down_intervals(seen, ["a", "b"], T0)

    assert {"a": [(1.0, 1.25), (2.0, 2.5)], "b": []} == down


def test_a_kill_opens_the_interval_at_the_injection_not_at_the_exit_seen() -> None:
    seen = [exited("a", 1.0078125), restarted("a", 1.125)]

    down = down_intervals(seen, ["a"], T0, [fault("kill_manager", "a", 1.0)])

    assert {"a": [(1.0, 1.125)]} == down


def test_a_hung_manager_resumed_before_anyone_killed_it_serves_again_from_then() -> None:
    down = down_intervals([], ["a"], T0, [fault("hang_manager", "a", 1.0)], [("a", 2.5)])

    assert {"a": [(1.0, 2.5)]} == down


def test_a_manager_still_down_at_the_end_has_an_open_interval() -> None:
    seen = [exited("a", 1.0), exited("a", 3.0)]  # the second: the run's own shutdown

    assert {"a": [(1.0, None)]} == down_intervals(seen, ["a"], T0, until=2.0)
    assert {"a": 2.0} == unavailable({"a": [(1.0, None)]}, end=3.0)


def test_unavailability_counts_only_the_run() -> None:
    assert {"a": 0.7} == unavailable({"a": [(-0.5, 0.2), (1.0, 1.5)]}, end=10.0)


def test_a_manager_kill_recovers_when_every_manager_it_took_down_serves_again() -> None:
    seen = [
        exited("a", 1.0),
        exited("b", 1.0078125),  # one_for_all: the sibling is restarted too
        restarted("a", 1.125),
        restarted("b", 1.25),
    ]
    kill = fault("kill_manager", "a", 1.0)
    down = down_intervals(seen, ["a", "b"], T0, [kill])

    assert 0.25 == recovery_time(kill, down, seen, T0, [])


def test_a_manager_that_never_came_back_did_not_recover() -> None:
    seen = [exited("a", 1.0)]
    kill = fault("kill_manager", "a", 1.0)

    assert recovery_time(kill, down_intervals(seen, ["a"], T0, [kill]), seen, T0, []) is None


def test_a_resource_kill_recovers_when_a_client_got_its_resource_back() -> None:
    kill = fault("kill_resource", "erm", 2.0)
    back = [ClientRecovery("erm", 0.75, 1.0), ClientRecovery("erm", 2.0, 2.25)]

    assert 0.25 == recovery_time(kill, {}, [], T0, [*back, ClientRecovery("erm", 2.5, 3.0)])


def test_an_outage_that_began_before_a_kill_is_not_part_of_its_recovery() -> None:
    seen = [exited("b", 0.5), exited("a", 1.0), restarted("a", 1.25), restarted("b", 3.0)]
    kill = fault("kill_manager", "a", 1.0)
    down = down_intervals(seen, ["a", "b"], T0, [kill])

    assert 0.25 == recovery_time(kill, down, seen, T0, [])


def test_an_outage_that_began_at_the_kill_is_part_of_its_recovery() -> None:
    seen = [exited("a", 1.0), exited("b", 1.0), restarted("a", 1.25), restarted("b", 1.5)]
    kill = fault("kill_manager", "a", 1.0)
    down = down_intervals(seen, ["a", "b"], T0, [kill])

    assert 0.5 == recovery_time(kill, down, seen, T0, [])


def test_a_resource_kill_is_not_recovered_by_a_client_of_an_unrelated_manager() -> None:
    kill = fault("kill_resource", "erm", 2.0)
    elsewhere = ClientRecovery("db", 2.0, 2.125)  # another manager's resource failed too

    assert recovery_time(kill, {}, [consumer("db", "client-0")], T0, [elsewhere]) is None


def test_a_resource_kill_recovers_through_a_manager_that_holds_resources_of_it() -> None:
    seen = [consumer("erm", "cm"), consumer("cm", "client-0")]  # cm loads from erm
    kill = fault("kill_resource", "erm", 2.0)
    recoveries = [ClientRecovery("db", 2.0, 2.125), ClientRecovery("cm", 2.0, 2.5)]

    assert 0.5 == recovery_time(kill, {}, seen, T0, recoveries)


def test_a_reload_after_a_failure_heard_before_the_kill_is_not_its_recovery() -> None:
    kill = fault("kill_resource", "erm", 2.0)
    earlier = ClientRecovery("erm", 1.875, 2.125)  # an earlier kill's reload, ending late

    assert recovery_time(kill, {}, [], T0, [earlier]) is None


def test_restarts_of_managers_and_of_nested_supervisors_are_counted_apart() -> None:
    seen = [
        exited("pool", 1.0),  # the nested supervisor, restarted by root with its workers
        restarted("pool", 1.25),
        restarted("w1", 1.25, supervisor="pool"),
        restarted("w2", 1.25, supervisor="pool"),
        exited("db", 2.0),
        restarted("db", 2.25),
    ]

    assert (3, 1) == restarts(seen, ["db", "w1", "w2"])


def test_a_kill_in_a_nested_one_for_all_recovers_when_its_siblings_serve_again() -> None:
    seen = [
        exited("w1", 1.0, supervisor="pool"),
        exited("w2", 1.0078125, supervisor="pool"),
        restarted("w1", 1.125, supervisor="pool"),
        restarted("w2", 1.5, supervisor="pool"),
        exited("db", 0.5),  # a manager of the top supervisor, down before and after
        restarted("db", 2.0),
    ]
    kill = fault("kill_manager", "w1", 1.0)
    down = down_intervals(seen, ["db", "w1", "w2"], T0, [kill])

    assert {"db": [(0.5, 2.0)], "w1": [(1.0, 1.125)], "w2": [(1.0078125, 1.5)]} == down
    assert 0.5 == recovery_time(kill, down, seen, T0, [])


def test_a_load_error_recovers_at_the_first_load_after_it_ended() -> None:
    seen = [
        events.ResourceLoaded("db", "resource", "r1", "q1", 0.0, at=T0 + 1.5),
        events.ResourceLoaded("db", "resource", "r2", "q2", 0.0, at=T0 + 2.5),
    ]
    error = fault("load_error", "db", 1.0)

    assert 1.5 == recovery_time(error, {}, seen, T0, [], load_error_until=2.0)
    assert recovery_time(error, {}, seen, T0, [], load_error_until=None) is None


def test_a_cut_recovers_when_the_manager_answers_a_call_again() -> None:
    seen = [
        events.ConsumerAdded("db", "r", "q0", "api", at=T0 + 0.5),
        events.ConsumerAdded("db", "r", "q1", "api", at=T0 + 1.125),
    ]

    assert 0.125 == recovery_time(fault("cut_connections", "db", 1.0), {}, seen, T0, [])


def test_percentiles_interpolate_between_values() -> None:
    assert 2.5 == percentile([4.0, 1.0, 2.0, 3.0], 50)
    assert 3.7 == round(percentile([1.0, 2.0, 3.0, 4.0], 90) or 0, 6)
    assert percentile([], 50) is None
