"""The kit's own rules (`rr_actors_lab.teach.rules`): `dependency`, `survives`, `alone`,
`back`, `once`, `warned`, `loaded`, `kept`, `holds` and `warns`, each on events built here, the
line numbers as a history's; and `faults`, on a history's fault lines."""

from __future__ import annotations

from rr_actors import Status, events
from rr_actors_lab.teach.rules import (
    MARGIN_S,
    ROUND_S,
    RULES,
    alone,
    back,
    dependency,
    faults,
    holds,
    kept,
    loaded,
    once,
    survives,
    warned,
    warns,
)


def test_a_managers_call_without_a_parent_breaks_dependency_at_its_line() -> None:
    history = [
        (1, events.CallAnswered("actions", "q-own", "camera", "resource")),
        (2, events.CallAnswered("actions", "q-dep", "camera", "resource", parent="r1")),
        (3, events.CallAnswered("client-0", "q-client", "actions", "look")),  # a client's
    ]

    found = dependency(history, {"camera", "actions"})

    assert [(f.rule, f.kind, f.lines) for f in found] == [("dependency", "violation", (1,))]
    assert "actions holds camera/resource query q-own as a call of its own" in found[0].message


def test_calls_made_while_loading_hold_dependency() -> None:
    history = [(1, events.CallAnswered("actions", "q", "camera", "resource", parent="r1"))]

    assert dependency(history, {"camera", "actions"}) == []


def test_a_give_up_breaks_survives_and_names_the_managers_for_the_story() -> None:
    gave_up = events.SupervisorGaveUp("root", "more than 2 restart(s) within 5 s", 2, 5.0)
    history = [(1, events.CallAnswered("client-0", "q", "lidar", "resource")), (7, gave_up)]

    found = survives(history, ["lidar", "planner"])

    assert [(f.rule, f.lines, f.registrars) for f in found] == [
        ("survives", (7,), ("root", "lidar", "planner"))
    ]
    assert survives(history[:1], ["lidar"]) == []


def test_a_give_up_is_told_at_the_crash_it_gave_up_at_not_at_the_stops_after_it() -> None:
    # The supervisor stops its children (their exits, their stops) before it publishes
    # the give-up: the finding points at the crash since its last restart, so that what
    # those stops break (a consumer stopped before its provider: `end`) comes after it.
    history = [
        (1, events.ChildExited("root", "erm", 8, "killed by SIGKILL")),
        (2, events.ChildRestarted("root", "erm", 11, 0.01)),
        (3, events.ChildExited("root", "rm", 10, "killed by SIGKILL")),  # the last crash
        (4, events.ChildExited("root", "cm", 9, "shutdown", normal=True, stopped=True)),
        (5, events.ChildExited("root", "erm", 11, "shutdown", normal=True, stopped=True)),
        (6, events.SupervisorGaveUp("root", "more than 1 restart(s) within 5 s", 1, 5.0)),
    ]

    found = survives(history, ["erm", "cm", "rm"])

    assert [(f.rule, f.lines) for f in found] == [("survives", (3,))]
    assert found[0].message.startswith("supervisor root gave up at this exit of rm: ")


def test_a_sibling_stopped_and_restarted_with_a_crash_breaks_alone() -> None:
    # erm's crash under one_for_all takes cm down and back up: a violation from the
    # crash to cm's stop. rm's crash restarts rm alone, and the stops of the give-up (no
    # restart after them) are not judged.
    killed = {"reason": "killed by SIGKILL", "strategy": "one_for_all"}
    history = [
        (1, events.ChildExited("root", "erm", 8, **killed)),
        (2, events.ChildExited("root", "cm", 9, "shutdown", normal=True, stopped=True)),
        (3, events.ChildRestarted("root", "erm", 11, 0.01)),
        (4, events.ChildRestarted("root", "cm", 12, 0.01)),
        (5, events.ChildExited("root", "rm", 10, **killed)),
        (6, events.ChildRestarted("root", "rm", 13, 0.01)),
        (7, events.ChildExited("root", "erm", 11, **killed)),
        (8, events.ChildExited("root", "cm", 12, "shutdown", normal=True, stopped=True)),
        (9, events.SupervisorGaveUp("root", "more than 2 restart(s) within 5 s", 2, 5.0)),
    ]

    found = alone(history, ["erm", "cm", "rm"])

    assert [(f.rule, f.lines, f.registrars[:3]) for f in found] == [
        ("alone", (1, 2), ("root", "erm", "cm"))
    ]
    assert "stopped cm to restart it with erm's crash (one_for_all)" in found[0].message
    assert alone(history[4:], ["erm", "cm", "rm"]) == []


def test_a_call_loaded_again_while_its_first_load_holds_it_breaks_once() -> None:
    history = [
        (1, events.ResourceLoaded("dispenser", "resource", "r1", "q1", 0.05)),
        (2, events.ResourceLoaded("dispenser", "resource", "r2", "q2", 0.05)),
        (3, events.ResourceLoaded("dispenser", "resource", "r3", "q1", 0.05)),  # a retry
        (4, events.ResourceLoaded("other", "resource", "r4", "q2", 0.05)),  # another's
    ]

    found = once(history, ["dispenser"])

    assert [(f.rule, f.lines, f.registrars) for f in found] == [("once", (1, 3), ("dispenser",))]
    assert "loaded query q1 a second time (resource r3)" in found[0].message


def test_a_second_load_after_a_release_or_in_doubt_holds_once() -> None:
    released = [
        (1, events.ResourceLoaded("dispenser", "resource", "r1", "q1", 0.05)),
        (2, events.ConsumerReleased("dispenser", "r1", "q1", "client-0", reason="reconcile")),
        (3, events.ResourceLoaded("dispenser", "resource", "r2", "q1", 0.05)),
    ]
    doubted = [
        (1, events.ResourceLoaded("dispenser", "resource", "r1", "q1", 0.05)),
        (2, events.InDoubt("dispenser", "r1", "resource", "load")),
        (3, events.ResourceLoaded("dispenser", "resource", "r2", "q1", 0.05)),
    ]

    assert once(released, ["dispenser"]) == []
    assert once(doubted, ["dispenser"]) == []


def _served(resource: str, query: str, at: float) -> list[events.Event]:
    return [
        events.ResourceLoaded("camera", "stream", resource, query, 0.0, at=at),
        events.ConsumerAdded("camera", resource, query, "client-0", at=at),
    ]


def _sent(query: str, at: float) -> events.StatusSent:
    return events.StatusSent("camera", query, Status.WARNING, "recalibrating", at=at)


def test_a_round_of_statuses_that_leaves_a_resource_in_use_out_breaks_warned() -> None:
    opened = [*_served("r1", "q1", 1.0), *_served("r2", "q2", 1.0)]
    round_ = [_sent("q1", 2.0), _sent("q2", 2.0 + ROUND_S / 2)]  # both: held
    late = [*_served("r3", "q3", 3.0 - MARGIN_S / 2), _sent("q1", 3.0), _sent("q2", 3.01)]
    alone = [_sent("q1", 4.0)]  # r2 and r3 left out (r3 was too new for the round before)
    history = list(enumerate([*opened, *round_, *late, *alone], start=1))

    found = warned(history, ["camera"])

    assert [(f.rule, f.lines, f.registrars) for f in found] == [("warned", (11,), ("camera",))]
    assert "about 1 resource(s) of 3 in use: the consumers of r2, r3 never heard" in (
        found[0].message
    )


def test_a_round_cut_by_its_providers_exit_or_a_release_is_not_owed_warned() -> None:
    opened = [*_served("r1", "q1", 1.0), *_served("r2", "q2", 1.0)]
    exited = events.ChildExited("root", "camera", 7, "killed by SIGKILL", at=2.01)
    cut = [_sent("q1", 2.0), exited]
    gone = events.ConsumerReleased("camera", "r2", "q2", "client-0", at=3.0 + ROUND_S / 2)
    released = [_sent("q1", 3.0), gone]  # r2 let go before its turn could come
    history = list(enumerate([*opened, *cut, *released], start=1))

    assert warned(history, ["camera"]) == []


def test_a_load_that_raised_breaks_loaded() -> None:
    failed = events.LoadFailed("camera", "stream", "r2", "q2", "RuntimeError", "camera busy")
    history = [(1, events.ResourceLoaded("camera", "stream", "r1", "q1", 0.0)), (2, failed)]

    found = loaded(history, ["camera"])

    assert [(f.rule, f.lines) for f in found] == [("loaded", (2,))]
    assert found[0].message == "camera/stream's load for query q2 raised RuntimeError: camera busy"


def test_the_rules_are_listed_by_name() -> None:
    assert RULES == {
        "dependency": dependency,
        "survives": survives,
        "alone": alone,
        "back": back,
        "once": once,
        "warned": warned,
        "loaded": loaded,
        "kept": kept,
        "holds": holds,
        "warns": warns,
    }


def a_heal(yields_on: str) -> list[tuple[int, events.Event]]:
    """db on host c (pid 5) and, during a cut, a second db on host a (pid 6) that the
    clients (host a) and api (host b) load through; at the heal the one on `yields_on`
    yields: its ids released ("name yielded"), its exit normal."""
    pid = {"a": 6, "c": 5}[yields_on]
    supervisor = {"a": "beyond-1", "c": "root-c"}[yields_on]
    return [
        (1, events.CatalogRestored("db", (), (), (), pid=5, host="c")),
        (2, events.ConsumerAdded("db", "r1", "q1", "api", pid=5, host="c")),
        (3, events.CallAnswered("api", "q1", "db", "resource", pid=3, host="b")),
        (4, events.CatalogRestored("db", (), (), (), pid=6, host="a")),  # (the cut)
        (5, events.ConsumerAdded("db", "r2", "q2", "client-0", pid=6, host="a")),
        (6, events.CallAnswered("client-0", "q2", "db", "resource", pid=1, host="a")),
        (7, events.ConsumerAdded("db", "r3", "q3", "api", pid=6, host="a")),
        (8, events.CallAnswered("api", "q3", "db", "resource", pid=3, host="b")),
        (9, events.ConsumerReleased("db", "r3", "q3", "api", "name yielded", pid=pid, host="a")),
        (10, events.ChildExited(supervisor, "db", pid, "normal", normal=True, host=yields_on)),
        (
            11,
            events.ChildExited("root-c", "db", 5, "shutdown", normal=True, stopped=True, host="c"),
        ),
    ]


def test_the_majoritys_registrar_yielding_at_a_heal_breaks_kept_at_its_first_release() -> None:
    found = kept(a_heal(yields_on="a"), {"db", "api"})

    assert [(f.rule, f.kind, f.lines, f.registrars) for f in found] == [
        ("kept", "violation", (9,), ("db",))
    ]
    assert found[0].message == (
        "at the heal, db of host a, which served hosts a, b during the cut (2 of 3: the "
        "majority, 2 load(s) acknowledged), yielded to db of host c, which served c: the "
        "minority's registrar was kept, and 1 load(s) the majority still held were undone "
        "(FATAL to their consumers)"
    )


def test_the_minoritys_registrar_yielding_or_a_stop_at_the_end_holds_kept() -> None:
    # the lone host's db yields (what it acknowledged before the cut is not the
    # majority's work during it, nor is an answer to api lost in the cut: api never
    # heard it); a run's end stops db with "shutdown": no yield
    lost = events.ConsumerAdded("db", "r9", "q9", "api", pid=5, host="c")
    minority = [(n, e) for n, e in a_heal(yields_on="c") if n != 9] + [(12, lost)]
    minority.sort(key=lambda line: 4.5 if line[0] == 12 else line[0])  # (after the cut)

    assert kept(minority, {"db", "api"}) == []
    assert kept([(n, e) for n, e in a_heal(yields_on="a") if n != 10], {"db", "api"}) == []


def test_a_manager_never_started_again_after_its_exit_breaks_back() -> None:
    # cm is temporary: its kill is its end; rm's kill is followed by its restart, and
    # erm's by the give-up (`survives` says that one); the stops of the end are not exits
    history = [
        (1, events.ChildExited("root", "cm", 9, "killed by SIGKILL", restart="temporary")),
        (2, events.ChildExited("root", "rm", 10, "killed by SIGKILL", restart="permanent")),
        (3, events.ChildRestarted("root", "rm", 12, 0.01)),
        (4, events.ChildExited("sub", "erm", 8, "killed by SIGKILL", restart="permanent")),
        (5, events.SupervisorGaveUp("sub", "more than 0 restart(s) within 5 s", 0, 5.0)),
        (6, events.ChildExited("root", "rm", 12, "shutdown", normal=True, stopped=True)),
    ]

    found = back(history, ["erm", "cm", "rm"])

    assert [(f.rule, f.lines, f.registrars[:2]) for f in found] == [("back", (1,), ("root", "cm"))]
    assert "its restart type is 'temporary'" in found[0].message
    assert back(history[1:], ["erm", "cm", "rm"]) == []


def test_a_resource_loaded_without_a_call_to_what_it_needs_breaks_holds() -> None:
    history = [
        (1, events.CallAnswered("actions", "q1", "camera", "resource", parent="r1")),
        (2, events.ResourceLoaded("actions", "look", "r1", "c1", 0.01)),  # it holds camera
        (3, events.CallAnswered("actions", "q2", "lidar", "resource", parent="r2")),
        (4, events.ResourceLoaded("actions", "follow", "r2", "c2", 0.01)),  # not the camera
        (5, events.ResourceLoaded("camera", "resource", "r3", "q1", 0.01)),  # not judged
    ]

    found = holds(history, {"actions", "camera"}, actions="camera")

    assert [(f.rule, f.lines) for f in found] == [("holds", (4,))]
    assert "actions/follow loaded resource r2 without holding anything of camera" in (
        found[0].message
    )


def test_a_load_of_the_warning_server_with_streams_in_use_and_no_status_breaks_warns() -> None:
    t = 100.0
    history = [
        (1, events.ResourceLoaded("camera", "stream", "s1", "q1", 0.0, at=t)),
        (2, events.ConsumerAdded("camera", "s1", "q1", "client-0", at=t)),
        (3, events.StatusSent("camera", "q1", Status.WARNING, "recalibrating", at=t + 0.5)),
        (4, events.ResourceLoaded("camera", "recalibrate", "c1", "q2", 0.0, at=t + 0.51)),
        (5, events.ResourceLoaded("camera", "recalibrate", "c2", "q3", 0.0, at=t + 0.9)),
    ]

    found = warns(history, {"camera"}, camera="recalibrate")

    assert [(f.rule, f.lines) for f in found] == [("warns", (5,))]
    assert warns(history[:2] + history[4:], {"camera"}, camera="other") == []


def test_a_fault_table_that_never_fired_breaks_faults() -> None:
    lines = [
        '{"type": "ResourceLoaded"}',
        '{"type": "FaultInjected", "fault": 0, "kind": "kill_manager"}',
        '{"type": "FaultSkipped", "fault": 1, "kind": "kill_manager", "detail": "lidar was '
        'not running (stopped)"}',
    ]

    found = faults(lines, 2)

    assert [(f.rule, f.lines) for f in found] == [("faults", ())]
    assert found[0].message.startswith(
        "the plan's fault #2 never happened in this run (skipped, kill_manager: lidar was not "
        "running (stopped))"
    )
    assert faults(lines[:2], 1) == []
