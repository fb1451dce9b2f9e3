"""rr_actors_lab.experiments.check: a clean history holds; one seeded violation of each rule is
found, with the lines that show it; mutations of a real history are found too."""

from __future__ import annotations

import dataclasses
import datetime
import importlib
import inspect
import json
import textwrap
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors import events
from rr_actors._core import hlc
from rr_actors_lab.__main__ import main
from rr_actors_lab.experiments import (
    PlanError,
    _supervision_rules,
    check,
    load_plan,
    plans,
    run,
    simulate,
)

P = 100  # the provider's process
C = 200  # the consumer's process
RID, RID2 = "r1111111-0000", "r2222222-0000"
Q1, Q2 = "q1111111-0000", "q2222222-0000"


def clean() -> list[events.Event]:
    """A provider with a backup loads a resource for two queries, sends a status, both
    release it, it unloads; the consumer stops, then the provider."""
    return [
        events.CatalogRestored("erm", (), (), (), pid=P, seq=1),
        events.ResourceLoaded("erm", "cam", RID, Q1, 0.01, 42, "cam 0", pid=P, seq=2),
        events.ConsumerAdded("erm", RID, Q1, "cm", pid=P, seq=3),
        events.ConsumerAdded("erm", RID, Q2, "cm", pid=P, seq=4),
        events.StatusSent("erm", Q1, rr.Status.WARNING, "hot", "s1", pid=P, seq=5),
        events.StatusDelivered("cm", Q1, rr.Status.WARNING, 1, 0.001, "s1", pid=C),
        events.StatusDelivered("cm", Q2, rr.Status.WARNING, 1, 0.001, "s1", pid=C),
        events.ConsumerReleased("erm", RID, Q1, "cm", pid=P, seq=6),
        events.ConsumerReleased("erm", RID, Q2, "cm", pid=P, seq=7),
        events.ResourceUnloaded("erm", "cam", RID, pid=P, seq=8),
        events.ResourceLoaded("erm", "cam", RID2, Q1, 0.01, 42, "cam 0", pid=P, seq=9),
        events.ConsumerAdded("erm", RID2, Q1, "cm", pid=P, seq=10),
        events.ConsumerReleased("erm", RID2, Q1, "cm", pid=P, seq=11),
        events.ResourceUnloaded("erm", "cam", RID2, pid=P, seq=12),
        events.RegistrarStopped("cm", (), (), (), pid=C),
        events.RegistrarStopped("erm", (), (), (), pid=P, seq=13),
    ]


def numbered(history: list[events.Event]) -> list[check.Line]:
    return list(enumerate(history, start=1))


def test_a_clean_history_holds() -> None:
    verdict = check.check(numbered(clean()))
    assert ("held", 0, 0, len(clean())) == (
        verdict.verdict,
        verdict.violations,
        verdict.unverifiable,
        verdict.events,
    )


def _without(history: list[events.Event], *indexes: int) -> list[events.Event]:
    return [e for i, e in enumerate(history) if i not in indexes]


def _seeded() -> dict[str, tuple[list[events.Event], set[int]]]:
    """Per rule: a clean history with one violation of it, and the lines that show it."""
    h = clean()
    restarted = [
        *h[:4],  # restored, loaded, Q1 and Q2 added; then a restart that lost Q2
        events.CatalogRestored(
            "erm", ((RID, "cam", "loaded", "42"),), ((Q1, RID, "cm"),), (), (1, 1, 0), pid=P + 1
        ),
        events.ConsumerReleased("erm", RID, Q1, "cm", pid=P + 1, seq=1),
        events.ResourceUnloaded("erm", "cam", RID, pid=P + 1, seq=2),
    ]
    return {
        "kept": (restarted, {4, 5}),
        "unload-once": ([*h[:10], h[9]], {10, 11}),  # unloaded twice
        "dedup": (  # the second load while the first is live
            [*h[:3], events.ResourceLoaded("erm", "cam", RID2, Q2, 0.01, 42, pid=P, seq=4)],
            {2, 4},
        ),
        "restore-first": (  # a restart of a registrar with a backup serves before restoring
            [*h, events.ResourceLoaded("erm", "cam", RID2, Q2, 0.01, 7, pid=P + 1, seq=1)],
            {len(h) + 1},
        ),
        "status-once": ([*h[:7], h[6], *h[7:]], {7, 8}),
        "status-path": (  # a second hop of Q2 that no dependency of its resource explains
            [*h[:7], events.StatusDelivered("cm", Q2, rr.Status.WARNING, 2, 0.0, "s1", pid=C)],
            {4, 8},
        ),
        "end": ([*h[:8], h[14]], {4, 9}),  # Q2 never released; its consumer stopped
    }


@pytest.mark.parametrize(
    "rule",
    ["kept", "unload-once", "dedup", "restore-first", "status-once", "status-path", "end"],
)
def test_one_seeded_violation_of_each_rule_is_found_with_its_window(rule: str) -> None:
    history, window = _seeded()[rule]
    verdict = check.check(numbered(history))
    assert "violated" == verdict.verdict
    found = [f for f in verdict.findings if f.rule == rule]
    assert found, verdict.findings
    assert window == set(found[0].lines)


def test_a_history_heard_from_after_the_start_judges_the_restores_of_restarts_only() -> None:
    """A plan's `listen = "after_start"` (`simlisten`): the log subscribed once the tree
    served, so erm's first life is heard from after its `CatalogRestored`; a restart that
    serves before restoring is still found."""
    restart = events.CatalogRestored("erm", (), (), (), pid=P + 1, seq=1)
    heard = [*clean()[1:], restart]
    assert {1} == _found(heard, "restore-first")  # (as if the log had heard the start)
    verdict = check.check(numbered(heard), heard_from_start=False)
    assert ("held", ()) == (verdict.verdict, verdict.findings)
    serving = events.ResourceLoaded("erm", "cam", RID2, Q2, 0.01, 7, pid=P + 2, seq=1)
    found = check.check(numbered([*heard, serving]), heard_from_start=False).findings
    assert {len(heard) + 1} == {n for f in found if f.rule == "restore-first" for n in f.lines}


def test_an_event_built_before_its_registrars_stop_and_sent_after_it_is_of_that_life() -> None:
    """A real `simslow` run (2026-11-26, load 7): db's status thread built a
    `ServerQueriesListed` (seq 108) as its actor stopped; the stop's `RegistrarStopped`
    (seq 109) reached the file first. Numbered below the stop, the listing is of the life
    that stopped, not a new one that served before restoring its backup; one numbered
    after it (a manager restarted in the same process) begins one."""
    h = clean()
    stop = dataclasses.replace(h[-1], seq=14)
    listed = events.ServerQueriesListed("erm", "cam", (), pid=P, seq=13)
    _holds([*h[:-1], stop, listed])
    later = dataclasses.replace(listed, seq=14)
    assert {len(h) + 1} == _found([*h, later], "restore-first")


def _as_file(history: list[events.Event], path: Path) -> Path:
    """`history` as a simulated run writes it: one JSON line per event, run 1, seed 7."""
    lines = [json.dumps({**events.to_dict(e), "run": 1, "seed": 7}) for e in history]
    path.write_text("".join(f"{line}\n" for line in lines), encoding="utf-8")
    return path


@pytest.mark.parametrize(  # (names, not `_seeded()`: a manager process imports this module,
    # and events built there at import would take numbers of its own events: a gap)
    "rule",
    ["held", "kept", "unload-once", "dedup", "restore-first", "status-once", "status-path", "end"],
)
def test_a_history_checked_as_published_and_as_its_file_gives_the_same_verdict(
    rule: str, tmp_path: Path
) -> None:
    history = clean() if rule == "held" else _seeded()[rule][0]
    in_memory = check.check(check.numbered(history))
    from_file = check.check_file(_as_file(history, tmp_path / "events.jsonl"))
    assert {1: in_memory} == from_file
    assert ("held" if rule == "held" else "violated") == in_memory.verdict


def test_a_row_too_short_as_published_is_refused_as_in_its_file(tmp_path: Path) -> None:
    short = events.CatalogRestored("erm", (), (("q1",),), (), pid=P, seq=1)
    history = [*clean()[1:3], short]
    with pytest.raises(rr.ConfigError, match=r"line 3: CatalogRestored\.consumers: a row") as seen:
        check.numbered(history)
    with pytest.raises(rr.ConfigError) as read:
        check.check_file(_as_file(history, tmp_path / "events.jsonl"))
    assert str(read.value).endswith(str(seen.value))


def test_an_equal_load_beside_a_resource_reported_fatal_is_no_dedup_violation() -> None:
    h = clean()
    fatal = events.StatusSent("erm", Q1, rr.Status.FATAL, "died", "s2", pid=P, seq=4)
    new = events.ResourceLoaded("erm", "cam", RID2, Q2, 0.01, 42, pid=P, seq=5)
    restored = events.CatalogRestored(  # after a restart, the mark is in the row
        "erm",
        ((RID, "cam", "loaded", "42", "failed"), (RID2, "cam", "loaded", "42", "")),
        ((Q1, RID, "cm"),),
        (),
        (2, 1, 0),
        pid=P + 1,
    )
    third = events.ResourceLoaded("erm", "cam", "r3333333-0000", "q3", 0.01, 42, pid=P + 1, seq=1)
    live = [*h[:3], fatal, new]

    assert "held" == check.check(numbered(live)).verdict
    assert ["dedup"] == [f.rule for f in check.check(numbered([*live, restored, third])).findings]
    unmarked = events.CatalogRestored("erm", ((RID, "cam", "loaded", "42", ""),), (), (), pid=P + 1)
    assert "violated" == check.check(numbered([*live, unmarked, third])).verdict


def test_a_load_without_a_digest_in_a_run_of_plain_requests_is_a_dedup_violation() -> None:
    # (the mutant digest.py:56 `cls <= str`, a TypeError: every request lost its digest)
    h = clean()
    undigested = dataclasses.replace(h[1], digest=None)
    bare = [h[0], undigested, *h[2:]]

    assert "held" == check.check(numbered(h), plain_requests=True).verdict
    assert "held" == check.check(numbered(bare)).verdict  # (a request may be no plain value)
    verdict = check.check(numbered(bare), plain_requests=True)
    assert [("dedup", "violation", (2,))] == [(f.rule, f.kind, f.lines) for f in verdict.findings]


def test_a_plans_requests_are_plain_without_a_factory_a_date_or_another_setup() -> None:
    service = (check.SERVICE, {"uses": ["db"], "uses_request": {"k": [1, 2.5, True]}})
    assert check.plain_plan([("{key}", None), ({"a": ["{key}"]}, None)], [service])
    assert not check.plain_plan([("{key}", "mod:make")], [service])
    assert not check.plain_plan([(datetime.date(2026, 1, 1), None)], [service])
    assert not check.plain_plan([], [(check.SERVICE, {"uses_request": datetime.time(1)})])
    assert not check.plain_plan([("{key}", None)], [("my.module:setup", {})])


def test_a_released_but_unheld_id_and_an_add_after_the_unload_are_violations() -> None:
    h = clean()
    late = events.ConsumerAdded("erm", RID, "q3", "cm", pid=P, seq=9)
    verdict = check.check(numbered([*h[:10], late]))
    assert ["unload-once"] == [f.rule for f in verdict.findings]
    assert {10, 11} == set(verdict.findings[0].lines)


def test_lost_events_make_the_run_unverifiable_not_violated() -> None:
    h = clean()
    gap = _without(h, 7)  # the provider's seq 6 (a release) is missing
    verdict = check.check(numbered(gap))
    assert "unverifiable" == verdict.verdict
    assert 0 == verdict.violations
    assert any(f.rule == "events" for f in verdict.findings)
    dropped = check.check(numbered([*h, events.EventsDropped(3, pid=C)]))
    assert ("unverifiable", 1) == (dropped.verdict, dropped.unverifiable)


def test_numbers_a_killed_process_never_used_are_no_gap() -> None:
    # Issue 68: a change's events numbered, then the SIGKILL before their commit; its
    # supervisor's process tells the numbers no event took (`EventsUnpublished`)
    h = [*clean()[:6], events.StatusSent("erm", Q1, rr.Status.WARNING, "hot", "s2", pid=P, seq=9)]
    assert "unverifiable" == check.check(numbered(h)).verdict  # 6 to 8 missing
    told = [*h, events.EventsUnpublished((6, 7, 8), pid=P)]
    assert "held" == check.check(numbered(told)).verdict
    partly = [*h, events.EventsUnpublished((7, 8), pid=P)]  # (6: still a gap)
    assert ["events"] == [f.rule for f in check.check(numbered(partly)).findings]


def test_a_lost_id_reported_fatal_holds() -> None:
    history, _ = _seeded()["kept"]
    answered = events.CallAnswered("cm", Q2, "erm", "cam", pid=C)
    fatal = events.StatusDelivered("cm", Q2, rr.Status.FATAL, 1, 0.0, "s9", pid=C)
    forgotten = events.QueryForgotten("cm", Q2, "erm", "unknown at reconcile", pid=C)
    assert "held" == check.check(numbered([*history, answered, fatal, forgotten])).verdict


def test_an_id_its_consumer_forgot_before_a_restore_lost_it_holds() -> None:
    # the provider committed the release and was killed before it published it
    history, _ = _seeded()["kept"]
    answered = events.CallAnswered("cm", Q2, "erm", "cam", pid=C)
    forgotten = events.QueryForgotten("cm", Q2, "erm", "unload", pid=C)
    let_go = [*history[:4], answered, forgotten, *history[4:]]
    assert "held" == check.check(numbered(_stamped(let_go))).verdict
    late = [*history[:4], answered, *history[4:], forgotten]  # forgotten after: lost
    assert ["kept"] == [f.rule for f in check.check(numbered(_stamped(late))).findings]


def test_an_id_of_a_consumer_killed_before_a_restore_lost_it_holds() -> None:
    # (kill_program: the consumer, without a backup, died with its provider; the events
    # of a release it made just before may be lost with them, and nobody holds the id)
    history, _ = _seeded()["kept"]
    answered = events.CallAnswered("cm", Q2, "erm", "cam", pid=C)
    again = events.RegistrarStopped("cm", (), (), (), pid=C + 2)  # (its next life)
    killed = [*history[:4], answered, *history[4:], again]
    assert "held" == check.check(numbered(_stamped(killed))).verdict
    alive = [*history[:4], answered, *history[4:]]  # (it lived on: owed a FATAL)
    assert ["kept"] == [f.rule for f in check.check(numbered(_stamped(alive))).findings]
    kept = events.CatalogRestored("cm", (), (), (), pid=C)  # (a backup keeps its holds)
    restored = [kept, *history[:4], answered, *history[4:], again]
    assert "kept" in [f.rule for f in check.check(numbered(_stamped(restored))).findings]


def program_killed_while_releasing(
    state: str = "unloading", *, seen_after: bool = False
) -> list[events.Event]:
    """`simprogram` seed 125: cm (a backup) loaded RID2 with a dependency Q1 at erm; app
    released RID2, so cm began unloading it (committed: RID2 `unloading`), and its release
    of Q1 reached erm, which committed it; then the program was SIGKILLed with both before
    either published it. erm's restore lacks Q1; cm's lists RID2 as `state` and Q1 as its
    dependency; cm's restart finishes the unload, which erm no longer knows (`dependency`).
    `seen_after`: cm's life before showed an event after erm's restore."""
    restored_erm = events.CatalogRestored("erm", (), (), (), pid=P + 1)
    restored_cm = events.CatalogRestored(
        "cm", ((RID2, "comp", state, "7", ""),), (), ((Q1, "erm", "leaf", RID2),), pid=C + 1
    )
    late = [events.StatusDelivered("cm", "q9", rr.Status.OK, 1, 0.0, "s9", pid=C)]
    return _stamped(
        [
            events.CatalogRestored("erm", (), (), (), pid=P),
            events.CatalogRestored("cm", (), (), (), pid=C),
            events.ConsumerAdded("erm", RID, Q1, "cm", pid=P),
            events.CallAnswered("cm", Q1, "erm", "leaf", RID2, pid=C),
            events.ConsumerAdded("cm", RID2, Q2, "app", pid=C),
            events.CallAnswered("app", Q2, "cm", "comp", pid=A),
            events.QueryForgotten("app", Q2, "cm", "unload", pid=A),
            events.ConsumerReleased("cm", RID2, Q2, "app", pid=C),
            restored_erm,
            *(late if seen_after else ()),
            restored_cm,
            events.QueryForgotten("cm", Q1, "erm", "dependency", pid=C + 1),
            events.ResourceUnloaded("cm", "comp", RID2, pid=C + 1),
        ]
    )


def test_a_release_its_consumer_committed_before_a_kill_of_both_lost_from_a_restore_holds() -> None:
    # (issue 68, finding 1: the release reached erm, which committed it; its events and
    # cm's answer died with the program; cm's restart released it again)
    _holds(program_killed_while_releasing())
    # a consumer that was not releasing it, or lived on after the restore, was owed the id
    assert {3, 9} == _found(program_killed_while_releasing("loaded"), "kept")
    assert {3, 9} == _found(program_killed_while_releasing(seen_after=True), "kept")


# -- the consumer's side and dependency paths ------------------------------------------------

A = 300  # the top consumer's process


def with_paths() -> list[events.Event]:
    """erm serves leaf RID to cm's Q1, a dependency of cm's RID2, which app holds (Q2); a
    status about the leaf climbs to app; app unloads, cm releases its dependency."""
    return [
        events.ConsumerAdded("erm", RID, Q1, "cm", pid=P),
        events.CallAnswered("cm", Q1, "erm", "leaf", RID2, pid=C),
        events.ConsumerAdded("cm", RID2, Q2, "app", pid=C),
        events.CallAnswered("app", Q2, "cm", "comp", pid=A),
        events.StatusSent("erm", Q1, rr.Status.ERROR, "hot", "s1", pid=P),
        events.StatusDelivered("cm", Q1, rr.Status.ERROR, 1, 0.0, "s1", pid=C),
        events.StatusDelivered("app", Q2, rr.Status.ERROR, 2, 0.0, "s1", pid=A),
        events.QueryForgotten("app", Q2, "cm", "unload", pid=A),
        events.ConsumerReleased("cm", RID2, Q2, "app", pid=C),
        events.QueryForgotten("cm", Q1, "erm", "dependency", pid=C),
        events.ConsumerReleased("erm", RID, Q1, "cm", pid=P),
        events.RegistrarStopped("app", (), (), (), pid=A),
    ]


def test_a_history_with_the_consumer_side_and_a_dependency_path_holds() -> None:
    _holds(with_paths())


def _found(history: list[events.Event], rule: str) -> set[int]:
    verdict = check.check(numbered(history))
    assert "violated" == verdict.verdict
    found = [f for f in verdict.findings if f.rule == rule and f.kind == "violation"]
    assert found, verdict.findings
    return set(found[0].lines)


def _holds(
    history: list[events.Event],
    resolve: str = "first_served",
    timeouts: dict[str, float] | None = None,
) -> None:
    verdict = check.check(numbered(history), resolve, timeouts=timeouts)
    assert ("held", ()) == (verdict.verdict, verdict.findings)


def _of_rule(history: list[events.Event], rule: str) -> list[check.Finding]:
    """The findings of `rule` in the verdict on `history`."""
    return [f for f in check.check(numbered(history)).findings if f.rule == rule]


def test_a_status_that_skips_a_hop_of_its_path_is_found() -> None:
    h = with_paths()
    assert {3, 6} == _found(_without(h, 5), "status-path")  # cm never got it


def test_a_status_reaching_a_consumer_of_a_resource_nothing_depends_on_is_found() -> None:
    h = with_paths()
    h[1] = events.CallAnswered("cm", Q1, "erm", "leaf", None, pid=C)  # not a dependency
    assert {3, 7} == _found(h, "status-path")


def test_a_status_reaching_a_holder_of_another_resource_is_found() -> None:
    h = with_paths()
    other = events.ConsumerAdded("erm", RID2, "q3", "cm", pid=P)
    stray = events.StatusDelivered("cm", "q3", rr.Status.ERROR, 1, 0.0, "s1", pid=C)
    assert {13, 14} == _found([*h, other, stray], "status-path")


def _with_callbacks(*calls: tuple[str, str, int, int, int, int]) -> list[events.Event]:
    """`clean()` with a second status (s2) to both ids, then a `StatusHandled` per call:
    (query id, status id, arrived, began, returned, opened). Every event is stamped 1,000
    apart in its order; the callbacks' stamps are 10,000 plus their times (0-999)."""
    h = clean()
    second = [
        events.StatusSent("erm", Q1, rr.Status.WARNING, "hotter", "s2", pid=P),
        events.StatusDelivered("cm", Q1, rr.Status.WARNING, 1, 0.001, "s2", pid=C),
        events.StatusDelivered("cm", Q2, rr.Status.WARNING, 1, 0.001, "s2", pid=C),
    ]
    handled = [
        events.StatusHandled(
            "cm",
            qid,
            rr.Status.WARNING,
            sid,
            arrived,
            10_000 + began,
            opened and 10_000 + opened,
            pid=C,
            host="h",
            hlc=10_000 + returned,
        )
        for qid, sid, arrived, began, returned, opened in calls
    ]
    stamps = iter(range(1_000, 1_000_000, 1_000))
    return [
        e
        if isinstance(e, events.StatusHandled)
        else dataclasses.replace(e, hlc=next(stamps), host="h")
        for e in [*h[:7], *second, *handled, *h[7:]]
    ]


def test_each_id_s_callbacks_one_at_a_time_in_arrival_order_hold() -> None:
    one_at_a_time = _with_callbacks(
        (Q1, "s1", 1, 10, 20, 0),
        (Q2, "s1", 2, 15, 60, 0),  # (another id's beside them: as it may)
        (Q1, "s2", 3, 21, 30, 0),
        (Q2, "s2", 4, 61, 70, 0),
    )
    _holds(one_at_a_time)


def test_a_callback_that_began_while_an_earlier_one_of_its_id_ran_is_found() -> None:
    h = _with_callbacks((Q1, "s1", 1, 10, 200, 0), (Q1, "s2", 2, 60, 80, 0))
    found = _of_rule(h, "status-order")
    assert [{11, 12}] == [set(f.lines) for f in found]
    assert "began while it ran" in found[0].message
    assert "violated" == check.check(numbered(h)).verdict


def test_a_callback_that_began_before_one_of_its_id_that_arrived_first_is_found() -> None:
    h = _with_callbacks((Q1, "s2", 2, 10, 20, 0), (Q1, "s1", 1, 30, 40, 0))
    found = _of_rule(h, "status-order")
    assert [{11, 12}] == [set(f.lines) for f in found]
    assert "began before it began" in found[0].message


def test_every_callback_that_began_beside_a_hung_one_of_its_id_is_found() -> None:
    h = _with_callbacks(
        (Q1, "s1", 1, 10, 900, 0),  # hung: the watchdog gave it up
        (Q1, "s2", 2, 60, 80, 0),
        (Q1, "s1", 3, 81, 90, 0),  # (after the one before it, but beside the hung one)
        (Q1, "s2", 4, 901, 910, 0),
    )
    assert [{11, 12}, {11, 13}] == [set(f.lines) for f in _of_rule(h, "status-order")]


def test_a_status_that_reached_its_id_after_one_its_provider_sent_later_is_found() -> None:
    h = _with_callbacks((Q1, "s2", 1, 10, 20, 0), (Q1, "s1", 2, 30, 40, 0))  # (one at a time)
    found = _of_rule(h, "status-order")
    assert [{5, 8, 11, 12}] == [set(f.lines) for f in found]
    assert "after status s2 (WARNING), which erm sent after it" in found[0].message
    in_order = _with_callbacks((Q1, "s1", 1, 10, 20, 0), (Q1, "s2", 2, 30, 40, 0))
    assert [] == _of_rule(in_order, "status-order")


def test_a_callback_that_waited_for_a_registrar_lets_its_id_s_next_begin() -> None:
    h = _with_callbacks((Q1, "s1", 1, 10, 200, 50), (Q1, "s2", 2, 60, 80, 0))
    assert [] == _of_rule(h, "status-order")
    early = _with_callbacks((Q1, "s1", 1, 10, 200, 50), (Q1, "s2", 2, 40, 80, 0))
    assert [{11, 12}] == [set(f.lines) for f in _of_rule(early, "status-order")]


def test_a_callback_at_the_arrival_place_of_another_of_its_process_is_found() -> None:
    """Each callback of a process has its own place in its status runner's arrival order
    (`StatusHandled.arrived`: 1, 2, ...): one at another's place, or at none (0), cannot be
    judged (the mutant status.py:650 `_arrived += 0` numbers every callback 0)."""
    twice = _with_callbacks((Q1, "s1", 1, 10, 20, 0), (Q2, "s1", 1, 15, 60, 0))
    found = _of_rule(twice, "status-order")
    assert [{11, 12}] == [set(f.lines) for f in found]
    assert "arrived at place 1 of its process's status runner, the place of the" in (
        found[0].message
    )
    unnumbered = _with_callbacks((Q1, "s1", 0, 10, 20, 0))
    assert [{11}] == [set(f.lines) for f in _of_rule(unnumbered, "status-order")]
    assert "violated" == check.check(numbered(unnumbered)).verdict
    other_pid = [
        dataclasses.replace(e, pid=P) if i == 11 else e for i, e in enumerate(twice)
    ]  # (another process's runner numbers its own from 1)
    assert [] == _of_rule(other_pid, "status-order")
    _holds(_with_callbacks((Q1, "s1", 1, 10, 20, 0), (Q2, "s1", 2, 15, 60, 0)))


def _answered(at: int, gave_up: tuple[str, ...] = ()) -> list[events.Event]:
    """`_with_callbacks` in one process (Q1's s2 callback returned at 20, Q2's at 60), with
    erm's answer to its send of s2 stamped `at` (10,000 plus it) listing the ids not in
    `gave_up` as reached: line 13."""
    h = _with_callbacks((Q1, "s2", 1, 10, 20, 0), (Q2, "s2", 2, 15, 60, 0))
    h = [dataclasses.replace(e, pid=P) for e in h]
    reached = tuple(q for q in (Q1, Q2) if q not in gave_up)
    answer = events.StatusAnswered("erm", Q1, "s2", reached, gave_up, pid=P, host="h")
    return [*h[:12], dataclasses.replace(answer, hlc=10_000 + at), *h[12:]]


def test_a_send_answered_after_the_callbacks_it_reached_returned_holds() -> None:
    _holds(_answered(70))
    _holds(_answered(40, gave_up=(Q2,)))  # (Q2's given up on: its patience ran out)


def test_a_send_answered_before_a_callback_it_reached_returned_is_found() -> None:
    found = _of_rule(_answered(40), "status-answered")  # (Q2's returned at 60)
    assert [{12, 13}] == [set(f.lines) for f in found]
    assert "q2222222 of cm reached before its callback returned" in found[0].message
    assert "violated" == check.check(numbered(_answered(40))).verdict


def _patient(patience: float | None, gave_up: tuple[str, ...] = ()) -> list[events.Event]:
    """`_answered(70, gave_up)` in seconds: each stamp `n` made `n / 1,000` s (erm's send of
    s2 at 8 s, line 8; Q2's callback returned at 10.06 s, line 12; the answer at 10.07 s),
    the send's `patience` that."""
    h = [
        dataclasses.replace(e, hlc=hlc.from_seconds(e.hlc / 1_000)) for e in _answered(70, gave_up)
    ]
    (i,) = (i for i, e in enumerate(h) if type(e) is events.StatusSent and e.status_id == "s2")
    return [*h[:i], dataclasses.replace(h[i], patience=patience), *h[i + 1 :]]


def test_a_send_answered_within_its_patience_or_giving_up_on_a_callback_past_it_holds() -> None:
    _holds(_patient(2.0))  # (Q2's returned 2.06 s after the send: within 2 + 0.5)
    _holds(_patient(1.0, gave_up=(Q1, Q2)))  # (past 1 + 0.5: given up on, as they must)
    _holds(_patient(None))  # (a send of no patience: not judged)


def test_a_send_that_waited_past_its_patience_for_a_callback_is_found() -> None:
    found = _of_rule(_patient(1.0, gave_up=(Q1,)), "status-patient")  # (Q1's given up on)
    assert [{8, 12}] == [set(f.lines) for f in found]
    assert "waited 2.06 s, past its patience of 1 s, for the callback of query q2222222" in (
        found[0].message
    )
    assert "violated" == check.check(numbered(_patient(1.0, gave_up=(Q1,)))).verdict


def test_a_call_answered_twice_is_found_unless_it_was_a_retry() -> None:
    h = with_paths()
    assert {2, 3} == _found([*h[:2], h[1], *h[2:]], "answered")
    retry = events.CallAnswered("cm", Q1, "erm", "leaf", RID2, retry=True, pid=C)
    assert "held" == check.check(numbered([*h[:2], retry, *h[2:]])).verdict


def test_a_call_answered_that_its_provider_never_added_is_found() -> None:
    h = with_paths()
    assert {1} == _found(_without(h, 0), "answered")


def test_an_answered_call_neither_forgotten_nor_listed_at_its_stop_is_found() -> None:
    h = with_paths()
    assert {4, 11} == _found(_without(h, 7), "answered")
    listed = events.RegistrarStopped("app", (), (), ((Q2, "cm", "comp", ""),), pid=A)
    verdict = check.check(numbered([*_without(h, 7, 11), listed]))
    assert ["left"] == [f.rule for f in verdict.findings]  # (listed: a row left, not lost)


def test_an_id_forgotten_that_was_not_held_is_found() -> None:
    h = with_paths()
    again = events.QueryForgotten("app", Q2, "cm", "unload", pid=A)
    assert {9} == _found([*h[:8], again, *h[8:]], "answered")


Q3 = "q3333333-0000"


def _asked_again(*then: events.Event) -> list[events.Event]:
    """`with_paths()` with a second call of app that cm added (Q3, line 5), then `then`
    before app's stop."""
    h = with_paths()
    added = events.ConsumerAdded(
        "cm", RID2, Q3, "app", pid=C, hlc=h[3].hlc + 1
    )  # (before the stop)
    return [*h[:4], added, *h[4:-1], *then, h[-1]]


def test_a_call_its_provider_added_with_no_outcome_before_its_callers_stop_is_found() -> None:
    assert {5, 13} == _found(_asked_again(), "outcome")


@pytest.mark.parametrize(  # (built in the test, not at import: the manager process of `real`
    "outcome",  # imports this module for `_serve`, and an event built there takes a number)
    [
        lambda: events.CallWithdrawn("app", Q3, "cm", "comp", pid=A),
        lambda: events.CallFailed("app", Q3, "cm", "comp", "RegistrarUnavailableError", "x", pid=A),
    ],
    ids=["withdrawn", "failed"],
)
def test_a_call_withdrawn_or_failed_at_its_caller_has_an_outcome(
    outcome: Callable[[], events.Event],
) -> None:
    assert [] == _of_rule(_asked_again(outcome()), "outcome")


def test_a_call_whose_caller_was_killed_before_its_stop_is_not_owed_an_outcome() -> None:
    h = _asked_again()
    killed = [*h[:-1], events.ChildExited("sup", "app", A, "killed by SIGKILL")]
    assert [] == _of_rule(killed, "outcome")


def test_a_call_whose_callers_stop_ended_its_process_is_not_owed_an_outcome() -> None:
    # simrest seed 5: db killed, rest_for_one stopped web while a load of web waited on
    # its call to api, which api had added; web's manager process exited after its stop
    # (its `ChildExited`), cutting the load and the call (its next start: `InDoubt`, and
    # api released the id at the reconcile). A stop withdraws top-level calls, not a
    # load's: the load settles them, and the process's end took the load.
    stopped = [*_asked_again(), events.ChildExited("sup", "app", A, "shutdown", stopped=True)]
    assert [] == _of_rule(stopped, "outcome")


def test_a_call_whose_callers_stop_left_its_process_running_is_owed_an_outcome() -> None:
    # the same, the exit another process of app's (an earlier one): app's own process
    # ran on after its stop, so the stop answered or withdrew what was in flight
    other = [*_asked_again(), events.ChildExited("sup", "app", A + 1, "shutdown", stopped=True)]
    found = _of_rule(other, "outcome")
    assert [{5, 13}] == [set(f.lines) for f in found]
    assert "cm added query q3333333 of app" in found[0].message


@pytest.mark.parametrize(
    "reason",
    [
        "registrar actor died",
        "exit code 1",
        "exited with code 0 without stopping its registrar",
        "failed to start: ValueError: setup raised",
    ],
)
def test_a_life_that_ended_by_itself_is_found(reason: str) -> None:
    h = clean()
    assert {len(h) + 1} == _found([*h, events.ChildExited("sup", "erm", P, reason)], "life-end")


def test_a_clean_stop_its_supervisor_reported_as_failed_is_found() -> None:
    """Issue 68 item 8: a mutant that reported every stop of `stop(parallel=True)` as
    failed (`stop failed: ManagerExit('shutdown', ...)`) survived every plan: no plan
    stopped so, and `life-end` judged no stopped child."""
    h = clean()  # (erm's registrar stopped cleanly: RegistrarStopped at pid P)
    failed = "stop failed: ManagerExit('shutdown', normal=True, clean=True)"
    exited = events.ChildExited("sup", "erm", P, failed, stopped=True)
    assert {len(h) + 1} == _found([*h, exited], "life-end")
    elsewhere = events.ChildExited("sup", "erm", P + 1, failed, stopped=True)  # (not clean)
    assert [] == _of_rule([*h, elsewhere], "life-end")


@pytest.mark.parametrize(
    ("reason", "stopped"),
    [
        ("killed by SIGKILL", False),
        ("hung: no heartbeat within 1 s (killed)", False),
        ("killed: no clean stop within 5 s", False),
        ("shutdown", False),
        ("failed to start: DuplicateNameError: 'erm' is served elsewhere", False),
        ("gave up: more than 2 restarts within 5 s", False),
        ("registrar actor died", True),  # (its supervisor stopped it: a stop)
    ],
)
def test_a_life_ended_by_a_fault_a_stop_or_its_supervisor_holds(reason: str, stopped: bool) -> None:
    exited = events.ChildExited("sup", "erm", P, reason, stopped=stopped)
    assert [] == _of_rule([*clean(), exited], "life-end")


REFUSED_START = (
    "failed to start: catalog backup 'erm.db' cannot be used: not an rr_actors catalog "
    "(application_id 0x0, tables [])"
)


def _damaged(*, refused: bool, whole: bool) -> list[events.Event]:
    """erm (pid P) holds Q1 and Q2 for cm and is SIGKILLed (line 7); a start refuses its
    backup (`refused`, line 8); the start that serves (pid P + 1) restores it `whole` or
    empty, and cm, told FATAL at its reconcile, forgets both ids then."""
    if whole:
        consumers = ((Q1, RID, "cm"), (Q2, RID, "cm"))
        rows = ((RID, "cam", "loaded", "42"),)
        restored = events.CatalogRestored("erm", rows, consumers, (), (1, 2, 0), pid=P + 1)
        told = []
    else:
        restored = events.CatalogRestored("erm", (), (), (), pid=P + 1)
        told = [
            told
            for q in (Q1, Q2)
            for told in (
                events.StatusDelivered("cm", q, rr.Status.FATAL, 1, 0.0, "s9", pid=C),
                events.QueryForgotten("cm", q, "erm", "unknown at reconcile", pid=C),
            )
        ]
    return _stamped(
        [
            *clean()[:4],
            *(events.CallAnswered("cm", q, "erm", "cam", pid=C) for q in (Q1, Q2)),
            events.ChildExited("sup", "erm", P, "killed by SIGKILL"),
            *([events.ChildExited("sup", "erm", 1, REFUSED_START)] if refused else []),
            restored,
            events.ChildRestarted("sup", "erm", P + 1, 0.1),
            *told,
        ]
    )


def _damage_found(history: list[events.Event], damaged: dict[int, str]) -> list[check.Finding]:
    verdict = check.check(numbered(history), damaged=damaged)
    return [f for f in verdict.findings if f.rule == "damaged-backup"]


@pytest.mark.parametrize("how", ["flip", "truncate", "foreign"])
def test_a_damaged_backup_refused_then_restored_empty_holds(how: str) -> None:
    history = _damaged(refused=True, whole=False)
    verdict = check.check(numbered(history), damaged={P: how})
    assert ("held", ()) == (verdict.verdict, verdict.findings)
    # (the refusal ended a start by itself, but for the fault that damaged its file)
    assert [8] == [line for f in _of_rule(history, "life-end") for line in f.lines]


@pytest.mark.parametrize("how", ["flip", "truncate", "foreign"])
def test_a_damaged_backup_a_restart_served_from_is_found(how: str) -> None:
    """Issue 68 item 8: mutants of the backup's checks (`schema.py:202`, `schema.py:262`)
    that took a damaged file for a good one survived: no plan damaged a backup."""
    history = _damaged(refused=False, whole=True)
    found = _damage_found(history, {P: how})
    assert [("violation", (7, 8))] == [(f.kind, f.lines) for f in found]
    assert "held" == check.check(numbered(history)).verdict  # (the damage: no event shows it)
    assert [] == _damage_found(_damaged(refused=False, whole=True), {P + 1: how})


def test_a_deleted_backup_restored_empty_holds_refused_or_restored_whole_is_found() -> None:
    verdict = check.check(numbered(_damaged(refused=False, whole=False)), damaged={P: "delete"})
    assert ("held", ()) == (verdict.verdict, verdict.findings)
    refused = _damage_found(_damaged(refused=True, whole=False), {P: "delete"})
    assert [("violation", (7, 8))] == [(f.kind, f.lines) for f in refused]
    whole = _damage_found(_damaged(refused=False, whole=True), {P: "delete"})
    assert [("violation", (7, 8))] == [(f.kind, f.lines) for f in whole]


def test_a_damaged_backup_with_no_start_after_is_unverifiable() -> None:
    history = _damaged(refused=True, whole=False)[:8]
    found = _damage_found(history, {P: "flip"})
    assert [("unverifiable", (7,))] == [(f.kind, f.lines) for f in found]


def test_a_backup_the_run_left_unreadable_is_found() -> None:
    """Issue 68 item 8: a page check that refused every good file (`files.py:436`,
    `NotEq_Eq`) survived: a simulation checks no page at open, and no plan read a backup
    after its run (`simulate` now does, as `rr-actors observe --state` would)."""
    history = clean()
    why = "catalog backup 'erm.db' is damaged: damaged pages: ok"
    verdict = check.check(numbered(history), unreadable={"erm": why})
    found = [f for f in verdict.findings if f.rule == "backup-readable"]
    assert [("violation", (len(history),), ("erm",))] == [
        (f.kind, f.lines, f.registrars) for f in found
    ]
    assert "violated" == verdict.verdict
    assert "held" == check.check(numbered(history), unreadable={}).verdict
    # (where the run's faults damaged a backup, its end may keep the damage: unverifiable)
    damaged = check.check(numbered(history), damaged={P: "flip"}, unreadable={"erm": why})
    assert ["unverifiable"] == [f.kind for f in damaged.findings if f.rule == "backup-readable"]


def test_a_resource_restored_with_another_digest_than_it_was_loaded_with_is_found() -> None:
    """Issue 68 item 8: a backup of another digest scheme (another Python's) restored
    without its digests recomputed, the mutants of `schema.py:326`, survived: no plan gave
    one. An equal request then no longer matches the restored resource."""
    history = _damaged(refused=False, whole=True)
    restored = history[7]
    assert isinstance(restored, events.CatalogRestored)
    other = dataclasses.replace(restored, resources=((RID, "cam", "loaded", "43"),))
    found = _of_rule([*history[:7], other, *history[8:]], "kept")
    assert [("violation", (2, 8))] == [(f.kind, f.lines) for f in found]
    assert [] == _of_rule(history, "kept")  # (restored with 42, as it was loaded)


def test_an_id_a_lost_backup_lost_that_its_consumer_released_after_holds() -> None:
    """A lost backup's restore loses every id: its consumer letting one go after it (its
    release, or told at its reconcile) keeps it; an id only a restore of a backup no fault
    touched lost is `kept`'s violation, as before."""
    history = _damaged(refused=False, whole=False)
    released = [
        *history[:9],
        *(events.QueryForgotten("cm", q, "erm", "unload", pid=C, hlc=2_000) for q in (Q1, Q2)),
    ]
    verdict = check.check(numbered(released), damaged={P: "delete"})
    assert ("held", ()) == (verdict.verdict, verdict.findings)
    assert {"kept"} == {f.rule for f in check.check(numbered(released)).findings}


# -- a real history, and rr-actors check -------------------------------------------------------


def _serve(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("camera", load=lambda r: f"camera {r}", unload=lambda q, r: None)


@pytest.fixture(scope="module")
def real(tmp_path_factory: pytest.TempPathFactory) -> list[str]:
    """A tree's events: a process manager with a backup, loads, a dedup hit, a status,
    unloads, a stop."""
    seen: list[events.Event] = []
    state = tmp_path_factory.mktemp("state")
    config = rr.RegistrarConfig("erm", backup_path=state / "erm.db", save_on_modify=True)
    sup = rr.Supervisor([rr.ManagerSpec("erm", _serve, isolation="process", config=config)])
    with sup.subscribe(seen.append) as subscription:
        with sup:
            app = sup.registrar("action")
            a = app.call("erm", "camera", 0)
            b = app.call("erm", "camera", 0)
            app.unload(a.id)
            app.unload(b.id)
            c = app.call("erm", "camera", 1)
            app.unload(c.id)
            sup.flush_events()
        assert subscription.wait_delivered(timeout=10.0)
    return [json.dumps(events.to_dict(e)) for e in seen]


def _kinds(lines: list[str]) -> list[str]:
    return [json.loads(line)["type"] for line in lines]


def test_a_real_history_holds_and_is_numbered(real: list[str]) -> None:
    kinds = _kinds(real)
    assert "CatalogRestored" in kinds
    assert kinds.count("RegistrarStopped") == 2
    assert {"CallAnswered", "QueryForgotten"} <= set(kinds)  # the consumer's side
    verdict = check.check(check.read_runs(real)[0])
    assert ("held", 0) == (verdict.verdict, len(verdict.findings))
    numbers = [json.loads(x)["seq"] for x in real if json.loads(x).get("seq")]
    assert numbers == list(range(1, len(numbers) + 1))  # the manager process numbers its own


def test_a_duplicated_unload_in_a_real_history_is_found(real: list[str]) -> None:
    at = _kinds(real).index("ResourceUnloaded")
    mutated = [*real[: at + 1], real[at], *real[at + 1 :]]
    verdict = check.check(check.read_runs(mutated)[0])
    assert "violated" == verdict.verdict
    assert {"unload-once"} == {f.rule for f in verdict.findings if f.kind == "violation"}


def test_a_deleted_release_in_a_real_history_is_found(real: list[str]) -> None:
    at = _kinds(real).index("ConsumerReleased")
    mutated = [*real[:at], *real[at + 1 :]]
    # without the numbers (as in a thread manager), the missing release is a violation
    stripped = [json.dumps({**json.loads(x), "seq": 0}) if '"seq"' in x else x for x in mutated]
    verdict = check.check(check.read_runs(stripped)[0])
    assert "violated" == verdict.verdict
    gap = check.check(check.read_runs(mutated)[0])
    assert "unverifiable" == gap.verdict  # with the numbers, the loss shows instead


def test_rr_actors_check_prints_the_verdict_and_the_window(
    real: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    at = _kinds(real).index("ResourceUnloaded")
    (tmp_path / "events.jsonl").write_text("\n".join([*real, real[at]]) + "\n")
    assert 1 == main(["check", str(tmp_path)])
    out = capsys.readouterr().out
    assert "run 0: violated" in out
    assert f"line {at + 1}: " in out
    assert f"line {len(real) + 1}: " in out
    (tmp_path / "events.jsonl").write_text("\n".join(real) + "\n")
    assert 0 == main(["check", str(tmp_path), "-q"])
    assert "run 0: held" in capsys.readouterr().out


def test_a_verdict_without_the_lines_texts_lists_their_numbers_alone(real: list[str]) -> None:
    at = _kinds(real).index("ResourceUnloaded")
    verdict = check.check(check.read_runs([*real, real[at]])[0])

    lines = check.format_verdict(0, verdict)

    assert f"    line {at + 1}" in lines
    assert [] == [line for line in lines if line.endswith(":")]


def test_rr_actors_check_reads_a_schema_2_file_as_a_schema_3_one(
    real: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A run written before events had `host` and `hlc` (schema 2) checks as it did."""
    old = []
    for text in real:
        line = json.loads(text)
        assert events.lines.SCHEMA == line.pop("schema")
        del line["host"], line["hlc"]
        old.append(json.dumps({**line, "schema": 2}))
    for name, lines in (("new", real), ("old", old)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "events.jsonl").write_text("\n".join(lines) + "\n")
        assert 0 == main(["check", str(tmp_path / name), "-q"])
        assert "run 0: held" in capsys.readouterr().out


# -- fetch (rule 10): what a consumer's fetch listed, against its provider's catalog ------------


def fetched(*listed: str, at: int = 5) -> list[events.Event]:
    """erm holds Q1 for cm (answered), adds Q2, then cm fetches what it holds at erm/cam
    (the fetch began just before event `at` (between it and the one before) and its answer
    came after; it listed `listed`), then both are released and cm forgets them."""
    h = [
        events.CatalogRestored("erm", (), (), (), pid=P, seq=1),
        events.ResourceLoaded("erm", "cam", RID, Q1, 0.01, 42, "cam 0", pid=P, seq=2),
        events.ConsumerAdded("erm", RID, Q1, "cm", pid=P, seq=3),
        events.CallAnswered("cm", Q1, "erm", "cam", None, False, pid=C),
        events.ConsumerAdded("erm", RID, Q2, "cm", pid=P, seq=4),
        events.CallAnswered("cm", Q2, "erm", "cam", None, False, pid=C),
        events.ConsumerReleased("erm", RID, Q1, "cm", pid=P, seq=5),
        events.ConsumerReleased("erm", RID, Q2, "cm", pid=P, seq=6),
        events.ResourceUnloaded("erm", "cam", RID, pid=P, seq=7),
        events.QueryForgotten("cm", Q1, "erm", "released", pid=C),
        events.QueryForgotten("cm", Q2, "erm", "released", pid=C),
        events.RegistrarStopped("cm", (), (), (), pid=C),
        events.RegistrarStopped("erm", (), (), (), pid=P, seq=8),
    ]
    h = [dataclasses.replace(e, hlc=1_000 + 10 * i, host="h") for i, e in enumerate(h)]
    fetch = events.QueriesFetched(
        "cm", "erm", "cam", listed, 1_000 + 10 * at - 5, pid=C, hlc=1_000 + 10 * at + 1, host="h"
    )
    return [*h[: at + 1], fetch, *h[at + 1 :]]


def asked(how: str, *ids: str, at: int) -> list[events.Event]:
    """The history of `fetched` (how="fetch": the consumer's fetch of erm/cam) or of
    `listed` (how="listing": erm's listing of its server cam), listing `ids`."""
    return fetched(*ids, at=at) if how == "fetch" else renumbered(listed(*ids, at=at))


@pytest.mark.parametrize("how", ["fetch", "listing"])
@pytest.mark.parametrize(
    ("ids", "at"),
    [
        ((Q1,), 4),  # Q2 added while it was asked: listed or not
        ((Q1, Q2), 4),
        ((Q1, Q2), 5),
        ((Q2,), 6),  # Q1 released while it was asked: listed or not
        ((Q1, Q2), 6),
        ((), 8),  # both released before
    ],
)
def test_a_fetch_or_a_listing_of_what_its_provider_held_holds(
    how: str, ids: tuple[str, ...], at: int
) -> None:
    _holds(asked(how, *ids, at=at))


@pytest.mark.parametrize("how", ["fetch", "listing"])
def test_a_fetch_or_a_listing_that_leaves_out_an_id_held_throughout_is_a_fetch_violation(
    how: str,
) -> None:
    # Q1 answered before it was asked and held by erm (on cam) until after: not listed
    verdict = check.check(numbered(asked(how, Q2, at=5)))

    found = [f for f in verdict.findings if f.rule == "fetch"]
    assert ("violated", [(3, 7)]) == (verdict.verdict, [f.lines for f in found])
    assert "did not list query q1111111" in found[0].message


@pytest.mark.parametrize("how", ["fetch", "listing"])
def test_a_fetch_or_a_listing_of_an_id_its_provider_did_not_hold_is_a_fetch_violation(
    how: str,
) -> None:
    never = "q3333333-0000"
    # Q1 released before it was asked; a third id never held at all
    verdict = check.check(numbered(asked(how, Q1, Q2, never, at=7)))

    found = sorted(f.message for f in verdict.findings if f.rule == "fetch")
    assert "violated" == verdict.verdict
    assert 2 == len(found), found
    assert "listed query q1111111, which erm did not hold while asked" in found[0]
    assert "listed query q3333333" in found[1]


def test_a_fetch_whose_window_a_restart_of_its_provider_falls_in_is_not_judged() -> None:
    h = fetched(at=5)  # (it lists nothing: Q1 is left out)
    restart = events.CatalogRestored(
        "erm", ((RID, "cam", "loaded", "42"),), ((Q1, RID, "cm"), (Q2, RID, "cm")), (), (1, 2, 0),
        pid=P + 1, seq=1, hlc=h[6].started + 1, host="h",
    )  # fmt: skip
    later = [dataclasses.replace(e, pid=P + 1) if e.pid == P else e for e in h[7:]]

    assert [] == _of_rule(renumbered([*h[:6], restart, h[6], *later]), "fetch")


def listed(*ids: str, at: int = 5, server: str = "cam") -> list[events.Event]:
    """`fetched`'s history, with erm listing its own server `server` (`server_queries`)
    instead of cm's fetch: begun just before event `at`, answered after it."""
    h = fetched(at=at)
    fetch = h[at + 1]
    listing = events.ServerQueriesListed(
        "erm", server, ids, fetch.started, pid=P, hlc=fetch.hlc, host="h"
    )
    return [*h[: at + 1], listing, *h[at + 2 :]]


def test_a_listing_of_another_server_need_not_list_the_ids_of_this_one() -> None:
    _holds(renumbered(listed(at=5, server="other")))


def test_a_listing_that_leaves_out_an_id_its_restore_listed_is_a_fetch_violation() -> None:
    # erm's restart restores Q1 on cam (a row of its backup), then lists cam: empty
    h = [
        events.CatalogRestored(
            "erm", ((RID, "cam", "loaded", "42"),), ((Q1, RID, "cm"),), (), (1, 1, 0), pid=P, seq=1
        ),
        events.ServerQueriesListed("erm", "cam", (), 1_005, pid=P),
        events.ConsumerReleased("erm", RID, Q1, "cm", pid=P, seq=2),
        events.ResourceUnloaded("erm", "cam", RID, pid=P, seq=3),
        events.RegistrarStopped("erm", (), (), (), pid=P, seq=4),
    ]
    h = [dataclasses.replace(e, hlc=1_000 + 10 * i, host="h") for i, e in enumerate(h)]

    found = _of_rule(h, "fetch")

    assert [(1, 2)] == [f.lines for f in found]
    assert "did not list query q1111111" in found[0].message


# -- the rules of issue 40: seeded violations, and the windows the docs admit --------------


def _stamped(history: list[events.Event]) -> list[events.Event]:
    """`history` with clock stamps in its order (as one host's events have)."""
    return [dataclasses.replace(e, hlc=1_000 + i, host="h") for i, e in enumerate(history)]


def test_a_release_that_names_another_resource_than_its_ids_is_found() -> None:
    h = clean()
    h[7] = dataclasses.replace(h[7], resource_id=RID2)  # Q1 was held on RID
    assert {3, 8} == _found(h, "release-match")


def test_a_held_id_added_again_on_a_second_resource_is_found() -> None:
    h = clean()
    again = events.ConsumerAdded("erm", "r3333333-0000", Q1, "cm", pid=P, seq=4)
    assert {3, 5} == _found([*h[:4], again, *h[4:]], "one-resource")


def test_an_in_doubt_report_of_a_resource_with_committed_holders_is_found() -> None:
    h = clean()
    restored = events.CatalogRestored(
        "erm", ((RID, "cam", "loading", "42", ""),), ((Q1, RID, "cm"),), (), (1, 1, 0), pid=P + 1
    )
    doubt = events.InDoubt("erm", RID, "cam", "load", pid=P + 1)
    assert {3, 6} == _found([*h[:4], restored, doubt], "in-doubt")
    # without holders (what a real restore of a load in doubt lists) it holds
    empty = dataclasses.replace(restored, consumers=(), counts=(1, 0, 0))
    assert "held" == check.check(numbered([*h[:2], empty, doubt])).verdict


def _restored_in_doubt(state: str, *after: events.Event) -> list[events.Event]:
    """erm loads RID for Q1, Q1 is released and erm begins its unload; killed, it restores
    RID as `state` (`"unloading"`, or `"loading"` for a load cut short), then `after`."""
    h = clean()
    restored = events.CatalogRestored("erm", ((RID, "cam", state, "42", ""),), (), (), pid=P + 1)
    return renumbered([*h[:3], h[5], restored, *after])


@pytest.mark.parametrize("state", ["unloading", "loading"])
def test_a_row_restored_in_doubt_and_reported_or_unloaded_by_its_life_holds(state: str) -> None:
    doubt = events.InDoubt("erm", RID, "cam", state.removesuffix("ing"), pid=P + 1)
    unloaded = events.ResourceUnloaded("erm", "cam", RID, pid=P + 1)
    again = events.ResourceLoaded("erm", "cam", RID2, Q2, 0.01, 7, "cam 1", pid=P + 1)
    for told in (doubt, unloaded):
        assert [] == _of_rule(_restored_in_doubt(state, told, again), "doubt-reported")


@pytest.mark.parametrize("state", ["unloading", "loading"])
def test_a_row_restored_in_doubt_that_its_life_never_reports_nor_unloads_is_found(
    state: str,
) -> None:
    """Issue 68 item 7: the plant `doubt-unloading-unseen` (benchmarks/planted_bugs.py;
    `simdoubt` seed 2 violates only this rule) drops an unload a kill cut short without
    its unload or its report; `left` and `no-leak` excuse a row restored `unloading`."""
    again = events.ResourceLoaded("erm", "cam", RID2, Q2, 0.01, 7, "cam 1", pid=P + 1)
    assert {5} == _found(_restored_in_doubt(state, again), "doubt-reported")


def test_a_row_restored_in_doubt_by_a_life_killed_before_it_went_on_is_not_judged() -> None:
    # (its start's turn, and the report in it, may have died with it: the next restore
    # lists the row again, and that life is judged)
    killed = events.CatalogRestored(
        "erm", ((RID, "cam", "unloading", "42", ""),), (), (), pid=P + 2
    )
    history = _restored_in_doubt("unloading", killed)
    assert [] == _of_rule(history, "doubt-reported")


def _released_then_answered(*between: events.Event) -> list[events.Event]:
    """erm adds Q1 for cm; its reconcile with cm releases Q1 (cm's list left it out);
    `between`; then cm records Q1's answer (stamped in that order)."""
    h = clean()
    released = events.ConsumerReleased("erm", RID, Q1, "cm", "reconcile", pid=P, seq=4)
    answer = events.CallAnswered("cm", Q1, "erm", "cam", pid=C)
    return _stamped(renumbered([*h[:3], released, *between, answer]))


def test_an_answer_its_consumer_records_after_its_providers_reconcile_released_it_is_found() -> (
    None
):
    """Issue 68 item 7: a `Reconcile` that leaves out a call whose answer is on its way
    (the plant `reconcile-due`) makes its provider release the id, and the consumer then
    holds it: `simretry` seeds 1-8 did it 2-9 times each, every verdict `held`."""
    assert {4, 5} == _found(_released_then_answered(), "answer-released")


def test_an_answer_after_a_reconcile_released_its_id_and_a_retry_added_it_again_holds() -> None:
    again = events.ConsumerAdded("erm", RID, Q1, "cm", pid=P, seq=5)
    assert [] == _of_rule(_released_then_answered(again), "answer-released")


def test_an_answer_recorded_before_its_providers_reconcile_released_it_is_not_this_rule() -> None:
    # (recorded first, then released by a reconcile: another story, that of a list that
    # left out an id it held; its stamps put the answer first)
    history = _released_then_answered()
    history[3], history[4] = (
        dataclasses.replace(history[3], hlc=history[4].hlc + 1),
        dataclasses.replace(history[4], hlc=history[3].hlc),
    )
    assert [] == _of_rule(history, "answer-released")


def _recorded_then_restored(
    *rows: tuple[str, ...], after: tuple[events.Event, ...] = ()
) -> list[events.Event]:
    """erm adds Q1 for cm, cm records its answer (a top-level call); cm is killed and
    restores `rows` (its client records), then `after`."""
    h = clean()
    restored = events.CatalogRestored("cm", (), (), rows, (0, 0, len(rows)), pid=C + 1)
    answer = events.CallAnswered("cm", Q1, "erm", "cam", pid=C)
    return _stamped(renumbered([*h[:3], answer, restored, *after]))


def test_an_answer_its_consumer_recorded_that_its_next_restore_lacks_is_found() -> None:
    """Issue 68 item 7: the plant `record-lost` (a client row's INSERT dropped) makes
    `simchain`'s api restore without the dependencies it recorded; their provider
    releases them at the reconcile, quietly, and every other rule holds."""
    assert {4, 5} == _found(_recorded_then_restored(), "record-kept")


def test_an_answer_its_next_restore_lists_or_its_provider_released_first_holds() -> None:
    listed = _recorded_then_restored((Q1, "erm", "cam", ""))
    released = events.ConsumerReleased("erm", RID, Q1, "cm", pid=P, seq=4)
    h = clean()
    gone = _stamped(
        renumbered(
            [
                *h[:3],
                events.CallAnswered("cm", Q1, "erm", "cam", pid=C),
                released,  # (cm's forget committed, then killed before its event left)
                events.CatalogRestored("cm", (), (), (), (0, 0, 0), pid=C + 1),
            ]
        )
    )
    for history in (listed, gone):
        assert [] == _of_rule(history, "record-kept")


def test_a_dependency_its_restore_lacks_under_a_parent_restored_unloading_holds() -> None:
    """`simprogram` seed 67 (215 before a restart was told only to the manager processes
    that monitor it; since a tree's ordered start changed, issue 69): cm's
    resource began its unload, whose release of the dependency Q1 was committed, and the
    whole program was killed before that release's events left. The restore lists the
    parent `unloading` and lacks Q1: rule 12's release under way, not a lost record. Under
    a parent restored `loaded` the missing record is still found."""

    def restored_with_parent(state: str) -> list[events.Event]:
        h = clean()
        answer = events.CallAnswered("cm", Q1, "erm", "cam", parent=RID2, pid=C)
        parent = ((RID2, "srv", state, "0", ""),)
        restored = events.CatalogRestored("cm", parent, (), (), (1, 0, 0), pid=C + 1)
        return _stamped(renumbered([*h[:3], answer, restored]))

    assert [] == _of_rule(restored_with_parent("unloading"), "record-kept")
    assert {4, 5} == _found(restored_with_parent("loaded"), "record-kept")


def test_a_recorded_top_level_call_restored_then_handed_back_in_doubt_is_found() -> None:
    doubt = events.QueryForgotten("cm", Q1, "erm", "in doubt", pid=C + 1)
    history = _recorded_then_restored((Q1, "erm", "cam", ""), after=(doubt,))
    assert {4, 6} == _found(history, "record-kept")
    dependency = _recorded_then_restored((Q1, "erm", "cam", RID2), after=(doubt,))
    assert [] == _of_rule(dependency, "record-kept")  # (an orphan: not judged)


def _shed(left: float, rounds: int = 0, *, pid: int = P) -> events.LoadFailed:
    """erm's load for Q2 shed with `left` seconds of its callers' timeout (as the provider
    words it), `rounds` of loads queued ahead."""
    ahead = f" after {rounds} rounds of its loads queued ahead" if rounds else ""
    return events.LoadFailed(
        "erm", "cam", RID2, Q2, "DeadlineExceededError",
        f"the load of 'x' at 'erm/cam' was shed before it started: {left:.3f} s were left of "
        f"its callers' timeout{ahead}, and its loads take 2.000 s lately (it needs 1.5 times "
        "that)",
        pid=pid,
    )  # fmt: skip


def test_a_load_shed_with_time_left_for_its_servers_longest_load_is_found() -> None:
    """Issue 68 item 7: the plant `shed-ms` (a load's time learned in milliseconds) sheds
    every load of `simdoubt`'s api with 3 s left where its loads take 0.05 s; the run held."""
    h = clean()  # (erm's load of RID took 0.01 s)
    assert {4} == _found(renumbered([*h[:3], _shed(1.0)]), "shed-needed")


@pytest.mark.parametrize(
    ("left", "rounds", "pid"),
    [  # (built in the test: an event made at import takes a number of this process's own)
        pytest.param(0.012, 0, P, id="too-little-left"),
        pytest.param(1.0, 2, P, id="behind-queued-loads"),
        pytest.param(1.0, 0, P + 1, id="before-any-load-of-its-process"),
    ],
)
def test_a_load_shed_that_could_not_start_in_time_or_is_not_judged_holds(
    left: float, rounds: int, pid: int
) -> None:
    h = clean()
    shed = _shed(left, rounds, pid=pid)
    assert [] == _of_rule(renumbered([*h[:3], shed]), "shed-needed")


def _overloaded(
    at: float, refused: int = 1, pending: int = 8, *, pid: int = P
) -> events.ServerOverloaded:
    """erm's server `cam` told overloaded at `at` (its bound 8), `refused` calls counted."""
    return events.ServerOverloaded("erm", "cam", pending, 8, refused, at=at, pid=pid)


def test_a_server_told_overloaded_again_within_a_second_is_found() -> None:
    """Issue 68 item 8: the mutant `provider.py:536` (`<` made `is`) publishes a
    `ServerOverloaded` at every refusal, hundreds a second, where one a second is the bound;
    every seed of every plan held."""
    h = clean()
    told = [_overloaded(5.0), _overloaded(5.3)]
    assert {4, 5} == _found(renumbered([*h[:3], *told]), "overload-paced")


def test_a_server_first_told_overloaded_with_refusals_counted_before_is_found() -> None:
    """Issue 68 item 8: the mutant `provider.py:538` (`now - _REFUSALS_EVERY` made
    `now / _REFUSALS_EVERY`) starts a server's count as if told just now: its first refusal
    is not told, the first `ServerOverloaded` comes a second later counting all since."""
    h = clean()
    told = [_overloaded(5.0, 40), _overloaded(6.0, 30)]
    assert {4} == _found(renumbered([*h[:3], *told]), "overload-paced")


@pytest.mark.parametrize(
    ("refused", "pending"),
    [pytest.param(0, 8, id="no-refusal-counted"), pytest.param(3, 7, id="below-its-bound")],
)
def test_a_server_told_overloaded_without_a_refusal_at_its_bound_is_found(
    refused: int, pending: int
) -> None:
    h = clean()
    assert {4} == _found(renumbered([*h[:3], _overloaded(5.0, refused, pending)]), "overload-paced")


@pytest.mark.parametrize(
    ("after", "pid"),
    [  # (built in the test: an event made at import takes a number of this process's own)
        pytest.param(0.97, P, id="a-second-apart-within-slack"),
        pytest.param(0.3, P + 1, id="in-a-new-process"),
    ],
)
def test_a_server_told_overloaded_once_a_second_or_afresh_in_a_new_life_holds(
    after: float, pid: int
) -> None:
    h = clean()
    told = [_overloaded(5.0), _overloaded(5.0 + after, 600 if pid == P else 1, pid=pid)]
    assert [] == _of_rule(renumbered([*h[:3], *told]), "overload-paced")


def _share_refused(
    pending: int,
    under_way: int,
    share: int,
    consumers: int = 2,
    ahead: int = 0,
    waiting: tuple[int, ...] = (),
    since: float = 5.0,
    firsts: tuple[float, ...] = (),
) -> events.ShareRefused:
    """erm's server `cam` (its bound 8) refused a load of consumer `api` at 5.0 (by default
    nobody else waiting told: as a line before schema 9 reads)."""
    return events.ShareRefused(
        "erm", "cam", "api", pending, under_way, share, consumers, ahead, 8, since, waiting,
        firsts, at=5.0, pid=P,
    )  # fmt: skip


@pytest.mark.parametrize(
    "refused",
    [
        pytest.param((5, 3, 4), id="under-its-share-with-a-free-slot"),
        pytest.param((6, 5, 5), id="a-share-not-the-bound-among-its-consumers"),
        pytest.param((8, 4, 4), id="at-the-bound-not-a-share-refusal"),
        pytest.param((3, 4, 4), id="more-of-its-own-under-way-than-in-all"),
        pytest.param((6, 1, 4, 2, 0, (3, 3)), id="more-loads-of-its-consumers-than-under-way"),
    ],
)
def test_a_refusal_of_a_consumer_a_server_with_room_did_not_need_is_found(
    refused: tuple[int, int, int],
) -> None:
    """Issue 68 items 7-8: the mutants of the share (`provider.py:246`, `bound // consumers`
    made `>>`, `%`, `+`, ...) refuse a consumer under its fair share, or tell a share that is
    not the bound divided among the consumers."""
    h = clean()
    assert {4} == _found(renumbered([*h[:3], _share_refused(*refused)]), "share-needed")


@pytest.mark.parametrize(
    "refused",
    [
        pytest.param((6, 4, 4), id="at-its-share"),
        pytest.param((7, 1, 2, 4, 1), id="its-free-slot-kept-for-one-ahead"),
        pytest.param((1, 1, 1, 9), id="at-least-1-among-more-consumers-than-slots"),
        pytest.param(
            (7, 1, 2, 4, 1, (0, 2), 5.0, (4.9, 4.0)), id="behind-the-one-of-three-with-fewer"
        ),
        pytest.param((7, 1, 2, 3, 1, (1,), 5.0, (4.0,)), id="behind-one-as-many-waiting-longer"),
    ],
)
def test_a_refusal_at_a_consumers_share_or_behind_others_waiting_holds(
    refused: tuple[int, ...],
) -> None:
    h = clean()
    assert [] == _of_rule(renumbered([*h[:3], _share_refused(*refused)]), "share-needed")


@pytest.mark.parametrize(
    "refused",
    [
        pytest.param(
            (7, 1, 2, 4, 2, (1, 2), 4.0, (4.5, 3.0)), id="none-ahead-told-as-two-different"
        ),
        pytest.param((7, 1, 2, 3, 1, (1,), 4.0, (4.0,)), id="one-as-many-waiting-as-long-told"),
    ],
)
def test_a_refusal_whose_ahead_is_not_the_count_of_those_waiting_ahead_of_it_is_found(
    refused: tuple[Any, ...],
) -> None:
    """Issue 68 item 8: the mutants of the order of those waiting (`provider.py:249`,
    `other < (mine, since)` made `!=`, `is not`, `<=`) count more ahead than wait ahead: a
    refusal kept a free slot for them, its `ahead` the server's. The check counts it itself
    from those waiting that the refusal tells (schema 9): here none is ahead (one with as
    many loads waiting a shorter time, or as long, one with more), and the slot was free."""
    h = clean()
    assert {4} == _found(renumbered([*h[:3], _share_refused(*refused)]), "share-needed")


def _share_admitted(
    pending: int,
    under_way: int,
    share: int,
    waiting: tuple[int, ...] = (1,),
    since: float = 5.0,
    firsts: tuple[float, ...] = (4.5,),
    consumers: int = 2,
) -> events.ShareAdmitted:
    """erm's server `cam` (its bound 8) admitted a load of consumer `api` at 5.0 while others
    waited (by default one, holding 1 load, first refused 0.5 s before)."""
    return events.ShareAdmitted(
        "erm", "cam", "api", pending, under_way, share, consumers, 8, since, waiting, firsts,
        at=5.0, pid=P,
    )  # fmt: skip


@pytest.mark.parametrize(
    "admitted",
    [
        pytest.param((5, 4, 4), id="at-its-share"),
        pytest.param((7, 2, 4), id="the-free-slot-kept-for-one-with-fewer"),
        pytest.param((7, 2, 4, (2,), 4.9), id="the-free-slot-kept-for-one-as-many-waiting-longer"),
        pytest.param((8, 1, 4, (2,)), id="at-the-bound"),
        pytest.param((5, 1, 3), id="a-share-not-the-bound-among-its-consumers"),
        pytest.param((3, 2, 4, (2,)), id="more-loads-of-its-consumers-than-under-way"),
        pytest.param((3, 1, 4, (), 5.0, ()), id="nobody-waiting"),
    ],
)
def test_a_load_admitted_past_a_consumers_share_or_the_slot_kept_for_those_waiting_is_found(
    admitted: tuple[Any, ...],
) -> None:
    """Issue 68 items 7-8: the mutants of the order of those waiting (`provider.py:249`,
    `other < (mine, since)` made `==`, `is`, `>`, ...) and of the admission's test
    (`provider.py:252`, `pending + ahead < bound` made `-`, `<=`, `or`, ...) admit a load past
    the consumer's share, or into the free slot kept for a consumer waiting ahead of it."""
    h = clean()
    assert {4} == _found(renumbered([*h[:3], _share_admitted(*admitted)]), "share-kept")


@pytest.mark.parametrize(
    "admitted",
    [
        pytest.param((6, 2, 4, (3,)), id="under-its-share-none-ahead"),
        pytest.param((6, 2, 4), id="a-free-slot-left-for-one-ahead"),
        pytest.param((7, 2, 4, (2,), 4.5, (4.8,)), id="waiting-longer-than-one-with-as-many"),
        pytest.param((3, 0, 1, (0, 0), 4.5, (4.6, 4.7), 9), id="at-least-1-among-9-consumers"),
    ],
)
def test_a_load_admitted_under_a_consumers_share_with_a_slot_for_each_ahead_holds(
    admitted: tuple[Any, ...],
) -> None:
    h = clean()
    assert [] == _of_rule(renumbered([*h[:3], _share_admitted(*admitted)]), "share-kept")


def _plant(monkeypatch: pytest.MonkeyPatch, where: str, old: str, new: str) -> None:
    """The function at `where` ("module:name" or "module:Class.name") replaced, for this
    test, by its source with `old` (found once) made `new`: the same edit as a plant of
    benchmarks/planted_bugs.py, in this process (a module's function is replaced in its
    module, which its callers call it through)."""
    module_name, _, path = where.partition(":")
    module = importlib.import_module(module_name)
    *owners, name = path.split(".")
    owner = getattr(module, owners[0]) if owners else module
    source = textwrap.dedent(inspect.getsource(getattr(owner, name)))
    assert 1 == source.count(old), f"{where} moved: write the plant again"
    made: dict[str, object] = {}
    exec(compile(source.replace(old, new), module.__file__ or "", "exec"), vars(module), made)  # noqa: S102
    monkeypatch.setattr(owner, name, made[name])


@pytest.mark.timeout(600)  # a planted plan's seed takes a few CPU seconds; under load more
@pytest.mark.parametrize(
    ("plan_name", "where", "old", "new", "rule"),
    [
        pytest.param(
            "simchain",
            "rr_actors._store.schema:plan_client",
            'ops.append(\n            (\n                "INSERT INTO clients',
            '[].append(\n            (\n                "INSERT INTO clients',
            "record-kept",
            id="the plant record-lost is caught by record-kept at simchain seed 1",
        ),
        pytest.param(
            "simdoubt",
            "rr_actors._registrar.provider:ServerActor.ran",
            "(took - pace.load_s)",
            "(took * 1000 - pace.load_s)",
            "shed-needed",
            id="the plant shed-ms is caught by shed-needed at simdoubt seed 1",
        ),
        pytest.param(
            "simretry",
            "rr_actors._registrar.consumer:Reconciling.listing",
            "held |= due\n",
            "\n",
            "answer-released",
            id="the plant reconcile-due is caught by answer-released at simretry seed 1",
        ),
        pytest.param(  # (each of its managers' actors dies at its first load)
            "simdoubt",
            "rr_actors._registrar.provider:Provider.serve",
            "    refusal = self.refusal(message)\n",
            "    raise RuntimeError('planted')\n",
            "life-end",
            id="the plant load-raises is caught by life-end at simdoubt seed 1",
        ),
        pytest.param(
            "simcancel",
            "rr_actors._registrar.consumer:publish_failed",
            "    if message.withdrawn:\n        shared.events.publish(",
            "    if message.withdrawn:\n        (lambda _event: None)(",
            "outcome",
            id="the plant withdrawal-unpublished is caught by outcome at simcancel seed 1",
        ),
        pytest.param(  # (a load's time learned as ~1 s: loads with 0.5 s left shed at once)
            "simshed",
            "rr_actors._registrar.provider:ServerActor._load",
            "self.ran(runtime.monotonic() - began)",
            "self.ran(runtime.monotonic() // began)",
            "shed-needed",
            id="the plant load-time-divided is caught by shed-needed at simshed seed 1",
        ),
        pytest.param(  # (a ServerOverloaded at every refusal, hundreds a second)
            "simoverload",
            "rr_actors._registrar.provider:Provider.refused",
            "if now - last < _REFUSALS_EVERY:",
            "if now - last is _REFUSALS_EVERY:",
            "overload-paced",
            id="the mutant provider.py:536 is caught by overload-paced at simoverload seed 1",
        ),
        pytest.param(  # (a share of `bound >> consumers`: 5 >> 2, 1 where 2 is api's share)
            "simfair",
            "rr_actors._registrar.provider:Admission.refusal",
            "share = max(1, bound // len(consumers))",
            "share = max(1, bound >> len(consumers))",
            "share-needed",
            id="the mutant provider.py:246 is caught by share-needed at simfair seed 1",
        ),
        pytest.param(  # (all those waiting but one with its own count and wait counted ahead:
            "simfair",  # refusals keep slots for them, the `ahead` share-needed counts itself)
            "rr_actors._registrar.provider:Admission.refusal",
            "ahead = sum(other < (mine, since) for",
            "ahead = sum(other != (mine, since) for",
            "share-needed",
            id="the mutant provider.py:249 is caught by share-needed at simfair seed 1",
        ),
        pytest.param(  # (simshed's end stops its tree with `stop(parallel=True)`)
            "simshed",
            "rr_actors._supervision.policy:Stopping.stop_in_parallel",
            "if not isinstance(result, ManagerExit):",
            "if isinstance(result, ManagerExit):",
            "life-end",
            id="the plant parallel-stop-failed is caught by life-end at simshed seed 1",
        ),
        pytest.param(  # (a turn's answers released before its commit: a kill between loses
            "simcommit",  # the change the caller was told of)
            "rr_actors._registrar.state:Shared.commit_then",
            "if not self.dirty:  # nothing of it",
            "if self.dirty:  # nothing of it",
            "answered",
            id="the mutant state.py:279 is caught by answered at simcommit seed 1",
        ),
        pytest.param(  # (a relay's own notice told to its own mailbox too: that copy finds
            "simanswer",  # its ids seen and answers their part while client-0's callback runs)
            "rr_actors._registrar.status:Desk.deliver",
            "if origin != here[0]:",
            "if origin != here[1]:",
            "status-answered",
            id="the mutant status.py:990 is caught by status-answered at simanswer seed 1",
        ),
        pytest.param(  # (every status callback run on a thread numbered 0 in its process)
            "crashloop",
            "rr_actors._registrar.status:Runner.run",
            "self._arrived += 1\n",
            "self._arrived += 0\n",
            "status-order",
            id="the mutant status.py:650 is caught by status-order at crashloop seed 1",
        ),
        pytest.param(  # (an unsettled id of a load that failed kept, not given back: kept
            "simkeptdep",  # for a retry none can make at api's reconcile, call_timeout long)
            "rr_actors._registrar.consumer:Flights.take_dependencies",
            "if flight is not None and flight.unsettled_at is not None:",
            "if flight is not None and flight.unsettled_at is None:",
            "retry-ended",
            id="the mutant consumer.py:273 is caught by retry-ended at simkeptdep seed 1",
        ),
        pytest.param(  # (no watchdog for an idle period's first status: its 2.7 s callback
            "simpatient",  # waited for past the send's patience of 2 s, not given up on)
            "rr_actors._registrar.status:Runner._kick",
            "if watch:",
            "if not watch:",
            "status-patient",
            id="the mutant status.py:757 is caught by status-patient at simpatient seed 1",
        ),
        pytest.param(  # (a backup whose application id was flipped, its tables all there,
            "simbackup",  # taken for a catalog: api's restart serves from it)
            "rr_actors._store.schema:schema_version",
            'if application_id != APPLICATION_ID or "rr_actors_schema" not in tables:',
            'if application_id != APPLICATION_ID and "rr_actors_schema" not in tables:',
            "damaged-backup",
            id="the mutant schema.py:202 is caught by damaged-backup at simbackup seed 1",
        ),
        pytest.param(  # (no object the file has beyond the schema's is looked at: a backup
            "simbackup",  # given a view is used)
            "rr_actors._store.schema:check_objects",
            "for kind, name, _, sql in found - expected:",
            "for kind, name, _, sql in []:",
            "damaged-backup",
            id="the mutant schema.py:262 is caught by damaged-backup at simbackup seed 1",
        ),
        pytest.param(  # (a backup of another digest scheme restored with its digests as
            "simbackup",  # they were: front's resources match no equal request again)
            "rr_actors._store.schema:refresh_digests",
            "if scheme == DIGEST_SCHEME:",
            "if scheme != DIGEST_SCHEME:",
            "kept",
            id="the mutant schema.py:326 is caught by kept at simbackup seed 1",
        ),
        pytest.param(  # (every `acall_with_retry` times out at once, before it sends its call:
            "simcancel",  # its `CallWithdrawn`, 0 s after its start, of a 3 s timeout)
            "rr_actors._supervision.retry:call_with_retry",
            "runtime.monotonic() + limit",
            "runtime.monotonic() / limit",
            "timed-out",
            id="the mutant retry.py:84 is caught by timed-out at simcancel seed 1",
        ),
    ],
)
def test_a_planted_bug_is_caught_by_its_rule_at_a_seed_its_plan_holds_at_unplanted(
    monkeypatch: pytest.MonkeyPatch, plan_name: str, where: str, old: str, new: str, rule: str
) -> None:
    plan = load_plan(plans.find(plan_name))
    assert "held" == simulate.run_seed(plan, 1).verdict
    _plant(monkeypatch, where, old, new)
    found = simulate.run_seed(plan, 1).findings
    assert any(f"[{rule}]" in line for line in found), found


@pytest.mark.timeout(600)
def test_the_mutant_status_py_990_lte_is_caught_by_status_answered_at_simanswer_seed_3(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A relay that tells its notice to its own mailbox too and to no registrar whose name
    sorts after its own (`<=` for `!=`, issue 68 item 8): its own copy answers its ids at
    once, as the `here[1]` plant's. Seeds 1 and 2 never take that path with a slow
    callback: the search's one seed of each plan missed it (20 runs, none of seed 3)."""
    plan = load_plan(plans.find("simanswer"))
    assert "held" == simulate.run_seed(plan, 3).verdict
    where, old = "rr_actors._registrar.status:Desk.deliver", "if origin != here[0]:"
    _plant(monkeypatch, where, old, "if origin <= here[0]:")
    found = simulate.run_seed(plan, 3).findings
    assert any("[status-answered]" in line for line in found), found


@pytest.mark.timeout(600)
def test_the_mutant_policy_py_955_crashes_the_parallel_stop_of_simstop_at_seed_1(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Issue 68 item 8: `stop(parallel=True)` with `or` for `and` in its cycle test
    (`policy.py:955:ReplaceAndWithOr`) stops one child at a time, the last started first.
    Where a dependency runs against start order (`simstop`: front, started first, holds a
    query at back), it stops back under front's query; front's stop then ends by counting
    down back's dependents again, a `KeyError`, and the stop raises. No rule sees that order:
    the seed crashes before it has a verdict (the mutant is crashed, no longer a survivor).
    Where no dependency runs against start order, that order is one the docs allow."""
    plan = load_plan(plans.find("simstop"))
    assert "held" == simulate.run_seed(plan, 1).verdict
    where = "rr_actors._supervision.policy:Stopping.stop_in_parallel"
    _plant(monkeypatch, where, "if not ready and not under_way:", "if not ready or not under_way:")
    run = simulate.run_seed(plan, 1)
    assert "crashed" == run.verdict
    assert any("crashed: KeyError" in line for line in run.findings), run.findings


def renumbered(history: list[events.Event]) -> list[events.Event]:
    """`history` with each process's numbers (`seq`) in its order again: an event a
    mutation removed or added is then one the registrar did not (or did) publish, not
    one the stream lost."""
    counts: dict[int, int] = {}
    out = []
    for event in history:
        if getattr(event, "seq", 0):
            counts[event.pid] = counts.get(event.pid, 0) + 1
            out.append(dataclasses.replace(event, seq=counts[event.pid]))  # type: ignore[call-arg]
        else:
            out.append(event)
    return out


def test_a_resource_released_by_its_last_consumer_and_never_unloaded_is_a_leak() -> None:
    h = clean()
    assert {9, 15} == _found(renumbered(_without(h, 9)), "no-leak")  # RID's unload is gone
    # in doubt, cut short by the stop, or kept as unloading at the stop: no leak
    doubt = events.InDoubt("erm", RID, "cam", "unload", pid=P)
    cut = events.UnloadCutShort("erm", "cam", RID, pid=P)
    kept = dataclasses.replace(h[15], resources=((RID, "cam", "unloading", "42", ""),))
    for ending in ([doubt, *h[10:]], [h[14], cut, h[15]], [h[14], kept]):
        assert "held" == check.check(numbered(renumbered([*h[:9], *ending]))).verdict


def test_an_unload_committed_just_before_a_kill_is_no_leak_and_the_restore_decides() -> None:
    h = clean()
    # killed after the unload's commit, before its event: the restore does not list RID
    gone = events.CatalogRestored("erm", (), (), (), pid=P + 1)
    assert "held" == check.check(numbered([*h[:9], gone])).verdict
    # the restore lists it unheld: the new life must unload it (its sweep) before a stop
    unheld = events.CatalogRestored("erm", ((RID, "cam", "loaded", "42", ""),), (), (), pid=P + 1)
    stop = events.RegistrarStopped("erm", (), (), (), pid=P + 1)
    assert {9, 11} == _found([*h[:9], unheld, stop], "no-leak")
    swept = events.ResourceUnloaded("erm", "cam", RID, pid=P + 1)
    assert "held" == check.check(numbered([*h[:9], unheld, swept, stop])).verdict
    listed = dataclasses.replace(stop, resources=unheld.resources)  # kept for the next start
    verdict = check.check(numbered([*h[:9], unheld, listed]))
    assert ["left"] == [f.rule for f in verdict.findings]  # (no leak: a row left at the end)


def _reported(reason: str, host: str = "h") -> list[events.Event]:
    """cm holds Q1 at erm (erm's life goes on: it releases Q1 later) and forgets it as lost."""
    h = clean()
    told = events.StatusDelivered("cm", Q1, rr.Status.FATAL, 1, 0.0, "s9", pid=C)
    forgot = events.QueryForgotten("cm", Q1, "erm", reason, pid=C)
    history = _stamped([*h[:4], told, forgot, *h[4:]])
    history[5] = dataclasses.replace(history[5], host=host)
    return history


@pytest.mark.parametrize("reason", ["unknown at reconcile", "provider lost"])
def test_a_consumer_telling_itself_fatal_for_an_id_its_provider_holds_is_found(
    reason: str,
) -> None:
    assert {3, 6} == _found(_reported(reason), "reported-lost")


def test_a_provider_lost_across_hosts_is_a_cut_not_a_finding() -> None:
    # a cut link makes a provider on the far side lost while it runs on over there
    assert [] == _of_rule(_reported("provider lost", host="other"), "reported-lost")


def test_an_id_told_lost_after_its_providers_life_ended_holds() -> None:
    h = _stamped(clean())
    exited = events.ChildExited("sup", "erm", P, "killed", hlc=2_000)
    told = events.StatusDelivered("cm", Q1, rr.Status.FATAL, 1, 0.0, "s9", pid=C, hlc=2_001)
    forgot = events.QueryForgotten("cm", Q1, "erm", "provider lost", pid=C, hlc=2_002)
    assert [] == _of_rule([*h[:4], exited, told, forgot], "reported-lost")


def test_an_id_told_lost_that_the_providers_restart_restores_is_found() -> None:
    """Rule 19: a provider its supervisor restarts is not lost. erm is killed, cm is told it
    is lost (a nested supervisor's give-up below the root reported its crashed child dead:
    the mutant policy.py:412 at simescalate seed 1), then erm's next life restores Q1 held
    for cm: the FATAL was wrong."""
    h = _stamped(clean())
    exited = events.ChildExited("sup", "erm", P, "killed", hlc=2_000)
    told = events.StatusDelivered("cm", Q1, rr.Status.FATAL, 1, 0.0, "s9", pid=C, hlc=2_001)
    forgot = events.QueryForgotten("cm", Q1, "erm", "provider lost", pid=C, hlc=2_002, host="h")
    rows = ((RID, "cam", "loaded", "42", ""),)
    back = events.CatalogRestored(
        "erm", rows, ((Q1, RID, "cm"), (Q2, RID, "cm")), (), pid=P + 1, hlc=1_999, host="h"
    )  # (its stamp before the forget's: a new process's clock, at the same instant)
    lost = [*h[:4], exited, told, forgot]
    assert {7, 8} == _found([*lost, back], "reported-lost")
    # restored elsewhere (a cut: lost on this side), or without it, or no restart: no finding
    for after in ([dataclasses.replace(back, host="other")], [_without_q1(back)], []):
        assert [] == _of_rule([*lost, *after], "reported-lost")


def _without_q1(restored: events.CatalogRestored) -> events.CatalogRestored:
    return dataclasses.replace(restored, consumers=((Q2, RID, "cm"),))


def test_a_consumer_that_forgets_an_id_as_lost_without_telling_itself_fatal_is_found() -> None:
    history = _without(_reported("provider lost", host="other"), 4)
    assert {5} == _found(history, "status-reached")


def test_a_status_that_never_reaches_a_holder_that_held_it_throughout_is_found() -> None:
    h = with_paths()
    assert {6, 7} == _found(_without(h, 6), "status-reached")  # app's hop 2 dropped
    # a holder that let its id go before the status's last delivery: not expected
    early = [*h[:4], h[7], *h[4:6], *h[8:]]  # app forgot Q2 before the status came
    assert [] == _of_rule(_stamped(early), "status-reached")


def crossed() -> list[events.Event]:
    """Run 2 of the shipped plan `resource` (CI, 2026-11-24), its status's part: erm sends
    FATAL about cm's dependency Q1; cm gets it (hop 1) and sends it on to app's Q2 and
    app2's Q3; cm then releases Q2 on app's `Unload` (its answer carries the status);
    app gets it, then forgets Q2 on that answer; app2 gets it after that."""
    a2 = A + 1
    fatal = rr.Status.FATAL
    return _stamped(
        [
            events.ConsumerAdded("erm", RID, Q1, "cm", pid=P),
            events.CallAnswered("cm", Q1, "erm", "leaf", RID2, pid=C),
            events.ConsumerAdded("cm", RID2, Q2, "app", pid=C),
            events.CallAnswered("app", Q2, "cm", "comp", pid=A),
            events.ConsumerAdded("cm", RID2, "q3", "app2", pid=C),
            events.CallAnswered("app2", "q3", "cm", "comp", pid=a2),
            events.StatusSent("erm", Q1, fatal, "died", "s1", pid=P),
            events.StatusDelivered("cm", Q1, fatal, 1, 0.0, "s1", pid=C),
            events.ConsumerReleased("cm", RID2, Q2, "app", "unload", pid=C),
            events.StatusDelivered("app", Q2, fatal, 2, 0.0, "s1", pid=A),  # (the answer's)
            events.QueryForgotten("app", Q2, "cm", "unload", pid=A),
            events.StatusDelivered("app2", "q3", fatal, 2, 0.0, "s1", pid=a2),
            events.ConsumerReleased("cm", RID2, "q3", "app2", "unload", pid=C),
            events.QueryForgotten("app2", "q3", "cm", "unload", pid=a2),
            events.QueryForgotten("cm", Q1, "erm", "dependency", pid=C),
            events.ConsumerReleased("erm", RID, Q1, "cm", pid=P),
            events.RegistrarStopped("app", (), (), (), pid=A),
            events.RegistrarStopped("app2", (), (), (), pid=a2),
        ]
    )


def test_a_status_its_holders_release_crossed_reaches_it_on_the_answer() -> None:
    h = crossed()
    _holds(h)
    # app's delivery lost: it let Q2 go before the status's last delivery (app2's), but
    # on the answer to its Unload, which cm gave after it sent the status on (rule 9)
    assert {8, 9, 10} == _found(_without(h, 9), "status-reached")
    # forgotten unanswered (its provider gone, say): no answer carried it, not expected
    unanswered = dataclasses.replace(h[10], reason="unload unanswered")
    assert [] == _of_rule([*h[:9], unanswered, *h[11:]], "status-reached")
    # released before cm sent it on: not a holder then, not expected
    before = [*h[:7], h[8], h[7], *h[10:]]
    _holds(_stamped(before))


def test_a_status_to_an_id_forgotten_as_its_unload_went_unanswered_by_its_dead_sender_holds() -> (
    None
):
    """A real `simways` run (2026-11-26): db sent statuses on to an id and was killed with
    that id's `Unload` on its way; its consumer forgot it as `unload unanswered` after
    the statuses' last deliveries elsewhere. The answer that would carry them died with
    db, and what came after found the id forgotten (failure-semantics.md): not owed."""
    h = crossed()
    fatal = rr.Status.FATAL
    earlier = [  # (an earlier status reached app from cm's life: connected)
        events.StatusSent("erm", Q1, fatal, "died", "s0", pid=P),
        events.StatusDelivered("cm", Q1, fatal, 1, 0.0, "s0", pid=C),
        events.StatusDelivered("app", Q2, fatal, 2, 0.0, "s0", pid=A),
        events.StatusDelivered("app2", "q3", fatal, 2, 0.0, "s0", pid=A + 1),
    ]
    exited = events.ChildExited("sup", "cm", C, "killed by SIGKILL")
    unanswered = dataclasses.replace(h[10], reason="unload unanswered")
    # cm sends it on to app's Q2 and app2's q3, app2 gets it, cm goes on and is killed;
    # app's Unload of Q2 goes unanswered
    died = _stamped([*h[:6], *earlier, *h[6:8], h[11], h[12], h[13], exited, unanswered, *h[16:]])
    assert [] == _of_rule(died, "status-reached")
    # while cm lives on, app's Unload is answered: one forgotten unanswered then is owed it
    alive = _stamped([*h[:6], *earlier, *h[6:8], h[11], h[12], h[13], unanswered, *h[14:]])
    assert "status-reached" in {f.rule for f in check.check(numbered(alive)).findings}


@pytest.mark.parametrize("reached_beside", [False, True])
def test_a_status_that_reached_another_id_of_its_holder_is_owed_to_one_forgotten_unanswered(
    reached_beside: bool,
) -> None:
    """A real `simways` run (CI, 2026-11-27): db sent a status that reached one of
    client-3's two ids at hop 1 and not the other, then was killed; the other was later
    forgotten as `unload unanswered`. A status desk delivers to all of a registrar's ids at
    a hop in one pass: the status arrived, so the id held throughout is owed it, dead
    sender or not. Without a delivery beside it, it may have died on its way: excused."""
    fatal = rr.Status.FATAL
    h = _stamped(
        [
            events.ConsumerAdded("erm", RID, Q1, "cm", pid=P),
            events.CallAnswered("cm", Q1, "erm", "cam", pid=C),
            events.ConsumerAdded("erm", RID, Q2, "cm", pid=P),
            events.CallAnswered("cm", Q2, "erm", "cam", pid=C),
            events.StatusSent("erm", Q1, fatal, "died", "s1", pid=P),
            *([events.StatusDelivered("cm", Q2, fatal, 1, 0.0, "s1", pid=C)] * reached_beside),
            events.ConsumerReleased("erm", RID, Q2, "cm", "unload", pid=P),
            events.QueryForgotten("cm", Q2, "erm", "unload", pid=C),
            events.ChildExited("sup", "erm", P, "killed by SIGKILL"),
            events.QueryForgotten("cm", Q1, "erm", "unload unanswered", pid=C),
            events.RegistrarStopped("cm", (), (), (), pid=C),
        ]
    )
    found = _of_rule(h, "status-reached")
    assert reached_beside == bool(found), found


def test_a_status_whose_sender_died_before_it_sent_it_on_reaches_nobody() -> None:
    h = with_paths()
    # erm sends and dies at once (its journal kept the StatusSent): nobody gets it, and
    # nothing of erm's life follows
    sent = events.StatusSent("erm", Q1, rr.Status.ERROR, "hot", "s1", pid=P)
    assert [] == _of_rule([*h[:4], sent, h[7]], "status-reached")


def sent_then_holder_killed(after_s: float | None) -> list[events.Event]:
    """erm sends a status about cm's Q1 (cm's only holder); cm goes on handling other
    messages, and its process is killed `after_s` seconds after the send (`None`: not
    killed) before the status reached anyone. (`simshare` seed 70: api, the only holder
    of db's shared resource, killed three events after db sent a status.)"""
    from rr_actors._core import hlc  # noqa: PLC0415

    h = with_paths()
    sent = h[4]
    went_on = events.ConsumerAdded("cm", RID2, "q9", "app", pid=C)
    erm_on = events.ConsumerAdded("erm", RID, "q8", "other", pid=P)  # (it sent it on)
    history = _stamped([*h[:4], sent, went_on, erm_on])
    if after_s is not None:
        at, _ = hlc.unpack(history[4].hlc)
        exited = events.ChildExited("sup", "cm", C, "killed by SIGKILL")
        history.append(dataclasses.replace(exited, hlc=hlc.pack(at + int(after_s * 1e6), 0)))
    return history


@pytest.mark.parametrize(
    ("after_s", "found"), [(0.05, set()), (2.0, {5}), (None, {5})], ids=["at once", "late", "no"]
)
def test_a_status_that_reached_nobody_is_lost_with_a_holder_killed_within_a_second(
    after_s: float | None, found: set[int]
) -> None:
    # rule 9 promises no delivery to a process killed while the status was on its way;
    # a holder killed later, or not at all, was owed it
    verdict = check.check(numbered(sent_then_holder_killed(after_s)))
    reached = [set(f.lines) for f in verdict.findings if f.rule == "status-reached"]
    assert ([found] if found else []) == reached, verdict.findings


def first_status_of_a_life(
    killed_after_s: float,
    *,
    earlier: bool = False,
    beside: bool = False,
    again: bool = False,
    carried: bool = False,
    later: bool = False,
) -> list[events.Event]:
    """A real `simslow` run (CI, 2026-11-26, load 20): db, just restarted, adds the ids of
    client-0 and client-1 (one process) and sends the first status of its life; client-1
    gets it, client-0 never does; db goes on (adds another id) and is SIGKILLed
    `killed_after_s` after the send. `earlier`: a status of that life reached client-0
    first (its connection there was made); `beside`: this one reached client-0's other id;
    `again`: db's next life sends client-0 a status that never reaches it either;
    `carried`: client-0 unloads its other id after the send, and the answer carries this
    status to that id; `later`: db's next status reaches client-0 (this one left before
    it). client-0 then goes on (erm answers it a call)."""
    from rr_actors._core import hlc  # noqa: PLC0415

    warning = rr.Status.WARNING
    h = [
        events.ConsumerAdded("db", RID, Q1, "client-0", pid=P),
        events.CallAnswered("client-0", Q1, "db", "resource", pid=C),
        events.ConsumerAdded("db", RID, Q2, "client-1", pid=P),
        events.CallAnswered("client-1", Q2, "db", "resource", pid=C),
    ]
    if beside or carried:
        h += [
            events.ConsumerAdded("db", RID, "q3", "client-0", pid=P),
            events.CallAnswered("client-0", "q3", "db", "resource", pid=C),
        ]

    def to_both(status_id: str) -> list[events.Event]:
        return [
            events.StatusSent("db", Q1, warning, "hot", status_id, pid=P),
            events.StatusDelivered("client-0", Q1, warning, 1, 0.0, status_id, pid=C),
            events.StatusDelivered("client-1", Q2, warning, 1, 0.0, status_id, pid=C),
        ]

    if earlier:
        h += to_both("s0")
    h += [
        events.StatusSent("db", Q1, warning, "hot", "s1", pid=P),
        events.StatusDelivered("client-1", Q2, warning, 1, 0.0, "s1", pid=C),
    ]
    if beside:
        h.append(events.StatusDelivered("client-0", "q3", warning, 1, 0.0, "s1", pid=C))
    if carried:
        h += [
            events.ConsumerReleased("db", RID, "q3", "client-0", "unload", pid=P),
            events.StatusDelivered("client-0", "q3", warning, 1, 0.0, "s1", pid=C),
            events.QueryForgotten("client-0", "q3", "db", "unload", pid=C),
        ]
    if later:
        h += to_both("s3")
    h.append(events.ConsumerAdded("db", RID, "q9", "client-2", pid=P))  # (it went on)
    history = _stamped(h)
    sent = next(e for e in history if type(e) is events.StatusSent and e.status_id == "s1")
    at, _ = hlc.unpack(sent.hlc)
    killed = at + int(killed_after_s * 1e6)
    next_life = [
        events.ConsumerAdded("db", RID2, "q6", "client-0", pid=P + 1),
        events.CallAnswered("client-0", "q6", "db", "resource", pid=C),
        events.StatusSent("db", "q6", warning, "hot", "s2", pid=P + 1),
        events.ConsumerAdded("db", RID2, "q7", "client-2", pid=P + 1),
    ]
    later = [  # (client-0 goes on: a call to erm answered)
        events.ChildExited("sup", "db", P, "killed by SIGKILL"),
        *(next_life if again else ()),
        events.ConsumerAdded("erm", RID2, "q5", "client-0", pid=A),
        events.CallAnswered("client-0", "q5", "erm", "cam", pid=C),
    ]
    return [
        *history,
        *(dataclasses.replace(e, hlc=hlc.pack(killed + i, 0)) for i, e in enumerate(later)),
    ]


def test_a_status_lost_with_a_sender_killed_before_its_connection_to_the_holder_holds() -> None:
    """Each process's connection to a registrar is made at its first send there, and what
    is sent meanwhile waits in the sender: a life killed before it connected loses it all,
    though it went on after the send (failure-semantics.md). One that lived on, or that
    sent that registrar a later status that arrived, or reached its other id with this
    status, or whose next life reached it no better, was owed it."""
    h = first_status_of_a_life(0.062)
    _holds(h)
    assert {5} == _found(first_status_of_a_life(2.0), "status-reached")
    assert {5} == _found(first_status_of_a_life(0.062, later=True), "status-reached")
    assert {7} == _found(first_status_of_a_life(0.062, beside=True), "status-reached")
    # nothing of two lives reached client-0: no connection's delay, a way that is broken
    assert {5} == _found(first_status_of_a_life(0.062, again=True), "status-reached")


def test_a_status_queued_behind_earlier_ones_in_a_sender_killed_just_after_is_not_owed() -> None:
    """A real `simways` run (load 18): db's statuses took 165 ms to arrive; the 13 it sent
    in the 43 ms before its SIGKILL reached nobody (one reached client-3 alone), though
    earlier ones had reached every client and db wrote events after them: what a
    connection cannot take yet waits in the sender and dies with it (failure-semantics.md).
    A later status of that life that arrived shows this one left: owed."""
    _holds(first_status_of_a_life(0.062, earlier=True))
    h = first_status_of_a_life(0.062, earlier=True, later=True)
    assert {8} == _found(h, "status-reached")


def test_a_status_an_unload_s_answer_carried_to_a_holder_s_other_id_shows_no_connection() -> None:
    """A real `simways` run (load 27): db, restarted, sent 17 statuses in the 134 ms
    before it was SIGKILLed; three clients of one process got them, client-1 none on its
    own way (its connection not made yet), but the first two reached one of its three
    ids on the answer to that id's `Unload`, over client-1's connection to db. That
    delivery was read as db's connection to client-1 made, and the other two ids as owed
    them (as twice in CI, client-3's). One that came before the release came its way."""
    _holds(first_status_of_a_life(0.062, carried=True))
    assert {7} == _found(first_status_of_a_life(0.062, beside=True), "status-reached")


def first_status_to_a_restarted_holder(killed_after_s: float) -> list[events.Event]:
    """`simdoubt` seed 58: a status of db's reached api's process; api, killed, is restored
    in a new process, holding its id at db again; db's next status about that id is its
    first to api's new process, and db is SIGKILLed `killed_after_s` after that send (it
    went on: it added another id). api goes on (db answers it a call)."""
    from rr_actors._core import hlc  # noqa: PLC0415

    warning = rr.Status.WARNING
    a1, a2 = A, A + 1  # (api's two processes)
    restored = events.CatalogRestored("api", (), (), ((Q1, "db", "resource", ""),), pid=a2)
    history = _stamped(
        [
            events.CatalogRestored("db", (), (), (), pid=P),
            events.CatalogRestored("api", (), (), (), pid=a1),
            events.ConsumerAdded("db", RID, Q1, "api", pid=P),
            events.CallAnswered("api", Q1, "db", "resource", pid=a1),
            events.StatusSent("db", Q1, warning, "hot", "s0", pid=P),
            events.StatusDelivered("api", Q1, warning, 1, 0.0, "s0", pid=a1),
            events.ChildExited("sup", "api", a1, "killed by SIGKILL"),
            restored,
            events.ChildRestarted("sup", "api", a2, 0.0),
            events.StatusSent("db", Q1, warning, "hot", "s1", pid=P),
            events.ConsumerAdded("db", RID, "q9", "client-2", pid=P),  # (it went on)
        ]
    )
    at, _ = hlc.unpack(history[9].hlc)
    rows = ((Q1, RID, "api"), ("q9", RID, "client-2"))
    later = [
        events.ChildExited("sup", "db", P, "killed by SIGKILL"),
        events.CatalogRestored("db", ((RID, "resource", "loaded", "42", ""),), rows, (), pid=P + 1),
        events.ConsumerAdded("db", RID2, "q5", "api", pid=P + 1),
        events.CallAnswered("api", "q5", "db", "resource", pid=a2),
    ]
    killed = at + int(killed_after_s * 1e6)
    return [
        *history,
        *(dataclasses.replace(e, hlc=hlc.pack(killed + i, 0)) for i, e in enumerate(later)),
    ]


def test_a_status_lost_with_a_sender_killed_before_it_connected_to_a_restarted_holder_holds() -> (
    None
):
    """A holder restarted in a new process is connected to anew at the sender's first send
    there: what reached its process before shows no connection to the new one. A sender
    that lived on after that send was owed it."""
    h = first_status_to_a_restarted_holder(0.0017)
    _holds(h)
    assert {10} == _found(first_status_to_a_restarted_holder(2.0), "status-reached")


def sent_to_a_restarted_holder(served_first: bool) -> list[events.Event]:
    """cm, killed, is restored (holding Q1 at erm) in a new process; erm sends a status
    about Q1 before cm's supervisor says it serves again (`served_first`: after), and
    nothing delivers it; cm then unloads Q1 and stops. (A real run of `simshare` at CI
    load: db sent its WARNING 5 ms before the restarted api served again.)"""
    sent = events.StatusSent("erm", Q1, rr.Status.WARNING, "hot", "s1", pid=P)
    served = events.ChildRestarted("sup", "cm", C + 1, 0.3)
    return _stamped(
        [
            events.CatalogRestored("cm", (), (), (), (0, 0, 0), pid=C),
            events.ConsumerAdded("erm", RID, Q1, "cm", pid=P),
            events.CallAnswered("cm", Q1, "erm", "leaf", pid=C),
            events.ChildExited("sup", "cm", C, "killed by SIGKILL"),
            events.CatalogRestored("cm", (), (), ((Q1, "erm", "leaf", ""),), (0, 0, 1), pid=C + 1),
            *((served, sent) if served_first else (sent, served)),
            events.ConsumerReleased("erm", RID, Q1, "cm", "unload", pid=P),
            events.QueryForgotten("cm", Q1, "erm", "unload", pid=C + 1),
            events.RegistrarStopped("cm", (), (), (), pid=C + 1),
        ]
    )


def test_a_status_sent_before_its_restarted_holder_serves_again_is_not_owed_to_it() -> None:
    # nobody can reach a restarted consumer before it serves again: the status is lost
    # to it (failure-semantics.md); one sent once it serves is owed (rule 9)
    _holds(sent_to_a_restarted_holder(served_first=False))
    assert {7, 9} == _found(sent_to_a_restarted_holder(served_first=True), "status-reached")


# -- `end` across a provider's restart: what its new life holds ------------------------------


def without_backup(pid: int = P + 1) -> list[events.Event]:
    """erm (no backup) serves cm's Q1 and is killed; its restart (`pid`) forgets Q1, serves
    Q2; cm is told Q1 is lost at its reconcile (rule 20), releases Q2, stops; erm stops."""
    return _stamped(
        [
            events.ResourceLoaded("erm", "cam", RID, Q1, 0.01, 42, "cam 0", pid=P, seq=1),
            events.ConsumerAdded("erm", RID, Q1, "cm", pid=P, seq=2),
            events.CallAnswered("cm", Q1, "erm", "cam", pid=C),
            events.ChildExited("sup", "erm", P, "killed by SIGKILL"),
            events.ResourceLoaded("erm", "cam", RID2, Q2, 0.01, 7, "cam 1", pid=pid, seq=3),
            events.ConsumerAdded("erm", RID2, Q2, "cm", pid=pid, seq=4),
            events.CallAnswered("cm", Q2, "erm", "cam", pid=C),
            events.StatusDelivered("cm", Q1, rr.Status.FATAL, 1, 0.0, "s9", pid=C),
            events.QueryForgotten("cm", Q1, "erm", "unknown at reconcile", pid=C),
            events.ConsumerReleased("erm", RID2, Q2, "cm", pid=pid, seq=5),
            events.ResourceUnloaded("erm", "cam", RID2, pid=pid, seq=6),
            events.QueryForgotten("cm", Q2, "erm", "unload", pid=C),
            events.RegistrarStopped("cm", (), (), (), pid=C),
            events.RegistrarStopped("erm", (), (), (), pid=pid, seq=7),
        ]
    )


@pytest.mark.parametrize("pid", [P + 1, P], ids=["new process", "same process"])
def test_a_restart_without_a_backup_forgets_what_its_last_life_held(pid: int) -> None:
    # a new process (a process manager), or the same one after its ChildExited (a thread
    # manager): either way a new life with an empty catalog, not still holding Q1
    _holds(without_backup(pid))


def test_an_id_the_new_life_holds_after_a_restart_without_a_backup_is_still_an_end() -> None:
    h = without_backup()
    # Q2, added by the restarted erm: cm gave it back, erm never released it
    kept = renumbered(_without(h, 9, 10, 13))
    assert {6, 11} == _found(kept, "end")
    assert ["end"] == [f.rule for f in check.check(numbered(kept)).findings]


def test_a_restart_without_a_backup_that_publishes_only_its_stop_holds_nothing() -> None:
    # erm's last restart (another process) serves nothing before the run's end: its
    # RegistrarStopped begins that life and lists nothing; cm was told Q1 is lost
    h = without_backup()
    late = [*h[:4], h[7], h[8], h[12], h[13]]
    _holds(_stamped(late))
    # cm never told: the restart lost Q1, found at the stop that shows the restart
    assert {2, 6} == _found(_stamped([*h[:4], h[12], h[13]]), "kept")


def _failed() -> events.CallFailed:
    return events.CallFailed(
        "cm", Q1, "erm", "cam", "RegistrarUnavailableError", "gone", True, pid=C
    )


@pytest.mark.parametrize("seen", ["before", "after"])
def test_a_restart_without_a_backup_may_lose_an_id_whose_call_failed_for_its_caller(
    seen: str,
) -> None:
    # erm committed Q1 and was killed before its answer left: cm's call failed (its
    # caller holds no id, rule 17), seen before or after erm's restart began; the restart
    # forgets Q1 and nobody is owed a FATAL
    h = without_backup()
    gone = [*h[:2], h[3], _failed(), *h[4:7], *h[9:]]
    if seen == "after":
        gone = [*h[:2], h[3], h[4], _failed(), *h[5:7], *h[9:]]
    _holds(_stamped(gone))


def test_an_answered_id_a_restart_without_a_backup_lost_is_owed_a_fatal() -> None:
    h = without_backup()
    silent = [*h[:7], *h[9:12], h[13]]  # cm never told; cm does not stop
    assert {2, 5} == _found(_stamped(silent), "kept")
    # a failed call, then its retry answered by the same life: held, and lost
    retried = dataclasses.replace(h[2], retry=True)
    again = [*h[:2], _failed(), retried, *h[3:7], *h[9:12], h[13]]
    assert {2, 6} == _found(_stamped(again), "kept")


def test_a_held_id_whose_retry_failed_as_its_provider_died_is_owed_a_fatal() -> None:
    # `simnostate` (CI, 2026-11-28; simulated seed 37): cm holds Q1 and calls it again (the
    # same id); erm (no backup) is killed and the retry fails, which leaves Q1 held (the
    # consumer's `retry_failed`); the restart lost it, and cm forgot it at its reconcile
    h = without_backup()
    failed = dataclasses.replace(_failed(), retry=True)
    _holds(_stamped([*h[:4], failed, *h[4:]]))
    untold = [*h[:4], failed, *h[4:7], *h[8:]]  # (no FATAL)
    assert {2, 6} == _found(_stamped(untold), "kept")


def test_an_id_forgotten_untold_at_reconcile_is_lost_though_its_holder_is_killed_later() -> None:
    # `simnostate` (simulated seed 147): cm forgets Q1 at its reconcile with erm's restart
    # (no backup), its last event before the restart's first, and is killed later. Its
    # forget shows it lived to reconcile: no event of its release was lost with it
    h = without_backup()
    forgot = events.QueryForgotten("cm", Q1, "erm", "unknown at reconcile", pid=C)
    restart = events.RegistrarStopped("erm", (), (), (), pid=P + 1, seq=1)
    killed = [events.ChildExited("sup", "cm", C, "killed by SIGKILL")]
    later = [events.RegistrarStopped("cm", (), (), (), pid=C + 1)]
    _holds(_stamped([*h[:4], h[7], forgot, restart, *killed, *later]))
    assert {2, 6} == _found(_stamped([*h[:4], forgot, restart, *killed, *later]), "kept")


def test_an_id_held_again_once_forgotten_is_owed_a_fatal_when_a_restart_loses_it() -> None:
    # cm forgets Q1 (its retry timed out) and erm releases it; cm calls Q1 again (the same
    # id, a workload's `again`) and holds it anew; erm (no backup) is killed, its restart
    # loses it, and cm is never told: that first forget let go of the first holding only
    h = without_backup()
    forgot = events.QueryForgotten("cm", Q1, "erm", "withdrawn", pid=C)
    gone = [
        events.ConsumerReleased("erm", RID, Q1, "cm", pid=P, seq=3),
        events.ResourceUnloaded("erm", "cam", RID, pid=P, seq=4),
    ]
    anew = [
        events.ResourceLoaded("erm", "cam", RID2, Q1, 0.01, 42, "cam 0", pid=P, seq=5),
        events.ConsumerAdded("erm", RID2, Q1, "cm", pid=P, seq=6),
        h[2],
    ]
    restart = events.RegistrarStopped("erm", (), (), (), pid=P + 1, seq=1)
    told = [events.StatusDelivered("cm", Q1, rr.Status.FATAL, 1, 0.0, "s9", pid=C)]
    _holds(_stamped([*h[:3], forgot, *gone, *anew, h[3], *told, restart]))
    assert {8, 11} == _found(_stamped([*h[:3], forgot, *gone, *anew, h[3], restart]), "kept")
    # `simnostate` seed 30: the first holding was lost too, told FATAL at its reconcile; the
    # second's loss is owed a FATAL of its own, after its answer
    lost = [events.ChildExited("sup", "erm", P, "killed by SIGKILL"), h[7], h[8]]
    again = [*(dataclasses.replace(e, pid=P + 1) for e in anew[:2]), h[2]]
    second = [events.ChildExited("sup", "erm", P + 1, "killed by SIGKILL")]
    restart = dataclasses.replace(restart, pid=P + 2)
    told = [dataclasses.replace(told[0], status_id="s10")]
    _holds(_stamped([*h[:3], *lost, *again, *second, *told, restart]))
    assert {8, 11} == _found(_stamped([*h[:3], *lost, *again, *second, restart]), "kept")


def retried_at_the_restart(*, answered: bool) -> list[events.Event]:
    """cm holds Q1 and calls it again (the same id, a workload's `again`) as erm (no backup)
    is killed; the retry reaches the restart, which loads Q1 anew (`answered`) or whose load
    raises; cm releases Q1 later, unanswered by a `FATAL` (the restart's Q2 as before)."""
    h = without_backup()
    anew = [
        events.ResourceLoaded("erm", "cam", RID, Q1, 0.01, 42, "cam 0", pid=P + 1, seq=1),
        events.ConsumerAdded("erm", RID, Q1, "cm", pid=P + 1, seq=2),
        dataclasses.replace(h[2], retry=True),
    ]
    if not answered:
        anew = [
            events.LoadFailed("erm", "cam", RID, Q1, "InjectedLoadError", "gone", pid=P + 1, seq=1),
            events.CallFailed(
                "cm", Q1, "erm", "cam", "ResourceLoadError", "gone", retry=True, pid=C
            ),
        ]
    released = [
        events.ConsumerReleased("erm", RID, Q1, "cm", pid=P + 1, seq=3),
        events.ResourceUnloaded("erm", "cam", RID, pid=P + 1, seq=4),
    ]
    forgot = events.QueryForgotten("cm", Q1, "erm", "unload", 1020, 1004, pid=C)
    tail = [*(released if answered else ()), forgot, *h[9:]]
    return renumbered(_stamped([*h[:4], *anew, *h[4:7], *tail]))


def test_a_held_id_whose_retry_the_restart_answered_is_owed_no_fatal_one_it_failed_is() -> None:
    # issue 51: the restart (no backup) that answered cm's retry of Q1 holds Q1 again (cm's
    # reconcile found it known: a due id is reconciled again once its call ends, rule 20);
    # a retry the restart failed leaves Q1 lost there, its FATAL owed
    _holds(retried_at_the_restart(answered=True))
    assert {2, 5} == _found(retried_at_the_restart(answered=False), "kept")


# -- issue 51: a release that crossed a restart without a backup ----------------------------


def crossing(reconciled: int, reason: str = "unload", *, exited: bool = True) -> list[events.Event]:
    """cm releases Q1 after erm (no backup) was killed (its `ChildExited` at stamp 1003)
    and before cm reconciled with the restart (which begins at 1004): the restarted erm no
    longer knows Q1, and cm forgets it on that answer, told no `FATAL` (its reconcile skips
    an id being released). `reconciled`: the stamp at which the list of cm's last
    reconcile with erm answered before its `Unload` left (at 1004) had left."""
    h = without_backup()
    released = events.QueryForgotten("cm", Q1, "erm", reason, 1004, reconciled, pid=C)
    crossed = [*h[:7], released, *h[9:]]  # (no FATAL, no "unknown at reconcile")
    return _stamped(crossed if exited else _without(crossed, 3))


@pytest.mark.parametrize("reason", ["unload", "unload unanswered"])
@pytest.mark.parametrize("reconciled", [0, 1000], ids=["never", "before the kill"])
def test_a_release_that_crossed_a_restart_without_a_backup_holds(
    reconciled: int, reason: str
) -> None:
    _holds(crossing(reconciled, reason))


def test_a_release_sent_after_its_consumer_reconciled_with_the_restart_is_a_lost_id() -> None:
    # cm's reconcile with the restarted erm (its list left at 1005, after the kill) was
    # answered before the Unload left: it was told Q1 was unknown, and owed a FATAL
    assert {2, 5} == _found(crossing(1005), "kept")
    assert ["kept"] == [f.rule for f in check.check(numbered(crossing(1005))).findings]


def test_a_release_after_reconciling_answered_before_the_restart_published_is_a_lost_id() -> None:
    # the restart (no backup) publishes its first event late (at 1050): cm reconciled
    # with it (its list left at 1032, after the kill at 1030), then released Q1 (1035)
    # and forgot it (1040), before that first event; it was owed a FATAL all the same
    h = without_backup()
    released = events.QueryForgotten("cm", Q1, "erm", "unload", 1035, 1032, pid=C)
    early = [*h[:4], released, *h[4:7], *h[9:]]
    spaced = [dataclasses.replace(e, hlc=1000 + 10 * i, host="h") for i, e in enumerate(early)]

    assert {2, 6} == _found(spaced, "kept")


def test_a_restart_whose_exit_is_not_shown_is_reconciled_after_the_life_befores_last_event() -> (
    None
):
    # without erm's ChildExited, cm may have reconciled with the restart any time after
    # the last event of erm's life before (its ConsumerAdded of Q1, at 1001)
    assert "held" == check.check(numbered(crossing(1000, exited=False))).verdict
    assert {2, 4} == _found(crossing(1002, exited=False), "kept")


def both_killed(*, held_by_restart: bool = False) -> list[events.Event]:
    """Issue 51, a real `simnostate` run at load 23: cm (no backup) holds Q1 at erm (no
    backup) and is killed; its restart (C + 1) holds Q2 there; erm is killed before cm's
    restart reconciled with it (no release of Q1), and its restart (P + 1) forgets both. Q1's
    holder died first: nobody is owed a `FATAL`; Q2's is told at its reconcile.
    `held_by_restart`: Q1 is added for cm's restart instead, and never reported."""
    q1 = [
        events.ResourceLoaded("erm", "cam", RID, Q1, 0.01, 42, "cam 0", pid=P, seq=1),
        events.ConsumerAdded("erm", RID, Q1, "cm", pid=P, seq=2),
        events.CallAnswered("cm", Q1, "erm", "cam", pid=C + 1 if held_by_restart else C),
    ]
    killed = [events.ChildExited("sup", "cm", C, "killed by SIGKILL")]
    return _stamped(
        [
            *([*killed, *q1] if held_by_restart else [*q1, *killed]),
            events.ResourceLoaded("erm", "cam", RID2, Q2, 0.01, 7, "cam 1", pid=P, seq=3),
            events.ConsumerAdded("erm", RID2, Q2, "cm", pid=P, seq=4),
            events.CallAnswered("cm", Q2, "erm", "cam", pid=C + 1),
            events.ChildExited("sup", "erm", P, "killed by SIGKILL"),
            events.RegistrarStopped("erm", (), (), (), pid=P + 1, seq=1),
            events.StatusDelivered("cm", Q2, rr.Status.FATAL, 1, 0.0, "s9", pid=C + 1),
            events.QueryForgotten("cm", Q2, "erm", "unknown at reconcile", pid=C + 1),
            events.RegistrarStopped("cm", (), (), (), pid=C + 1),
        ]
    )


def test_an_id_whose_holder_died_before_its_provider_restarted_without_a_backup_holds() -> None:
    # the checker looked at cm's life begun last before erm's restart (C + 1, alive then),
    # not at the one that held Q1 (C, dead): "lost ..., neither released nor reported FATAL"
    _holds(both_killed())


def test_an_id_of_the_holder_s_restart_lost_with_its_provider_s_restart_is_found() -> None:
    assert {3, 9} == _found(both_killed(held_by_restart=True), "kept")


def answered_to_a_life_shown_late(*, answered: bool = True) -> list[events.Event]:
    """cm (no backup) is killed; erm adds Q1 for cm's restart (C + 1), whose first event, its
    answer, comes after erm (no backup) was killed and restarted: no life of cm shown then
    held Q1, yet the restart did, and was told nothing. `answered=False`: no answer, as of a
    `Load` the killed life sent, added after its death (nobody is owed a `FATAL`)."""
    late = [events.CallAnswered("cm", Q1, "erm", "cam", pid=C + 1)] if answered else []
    late.append(events.ServerQueriesListed("cm", "x", pid=C + 1))
    return _stamped(
        [
            events.ServerQueriesListed("cm", "x", pid=C),
            events.ChildExited("sup", "cm", C, "killed by SIGKILL"),
            events.ResourceLoaded("erm", "cam", RID, Q1, 0.01, 42, "cam 0", pid=P, seq=1),
            events.ConsumerAdded("erm", RID, Q1, "cm", pid=P, seq=2),
            events.ChildExited("sup", "erm", P, "killed by SIGKILL"),
            events.RegistrarStopped("erm", (), (), (), pid=P + 1, seq=1),
            *late,
        ]
    )


@pytest.mark.parametrize(("begun", "found"), [(-1, set()), (1, {17})], ids=["before", "after"])
def test_a_listing_begun_before_its_registrar_stopped_and_published_after_is_of_that_life(
    begun: int, found: set[int]
) -> None:
    """A real `simways` run (load 15): db's status thread listed its queries; the answer
    came before db's stop, the `ServerQueriesListed` (its caller's thread) after its
    `RegistrarStopped`, numbered after it. Read as a new life of db, it was found
    `restore-first`. One begun after the stop is one."""
    h = _stamped(clean())
    stop = h[-1].hlc
    listed = events.ServerQueriesListed("erm", "cam", (), stop + begun, pid=P, seq=14)
    history = [*h, dataclasses.replace(listed, hlc=stop + 2, host="h")]
    findings = check.check(numbered(history)).findings
    assert found == {line for f in findings if f.rule == "restore-first" for line in f.lines}


def test_an_id_answered_to_a_consumer_life_shown_after_its_provider_s_restart_is_found() -> None:
    # the checker took the killed life C (the last begun) for Q1's holder and excused it
    assert {4, 6} == _found(answered_to_a_life_shown_late(), "kept")
    _holds(answered_to_a_life_shown_late(answered=False))


def retried_on_a_new_resource() -> list[events.Event]:
    """api (no backup) loads RID for cm's Q1, depending on db's D1; it is killed before
    its answer, and cm's retry of Q1 loads RID2 in api's restart (depending on D2); db
    sends FATAL about D2: it reaches D2 at api (hop 1), then Q1, held on RID2 (hop 2)."""
    d1, d2, db = "d1111111-0000", "d2222222-0000", 300
    return _stamped(
        [
            events.ResourceLoaded("db", "cam", "rd1", d1, 0.01, 1, "d 1", pid=db, seq=1),
            events.ConsumerAdded("db", "rd1", d1, "api", pid=db, seq=2),
            events.CallAnswered("api", d1, "db", "cam", RID, pid=P),
            events.ResourceLoaded("api", "cam", RID, Q1, 0.01, 42, "cam 0", pid=P),
            events.ConsumerAdded("api", RID, Q1, "cm", pid=P),
            events.ChildExited("sup", "api", P, "killed by SIGKILL"),
            _failed_at("api"),
            events.ResourceLoaded("db", "cam", "rd2", d2, 0.01, 2, "d 2", pid=db, seq=3),
            events.ConsumerAdded("db", "rd2", d2, "api", pid=db, seq=4),
            events.CallAnswered("api", d2, "db", "cam", RID2, pid=P + 1),
            events.ResourceLoaded("api", "cam", RID2, Q1, 0.01, 42, "cam 0", pid=P + 1),
            events.ConsumerAdded("api", RID2, Q1, "cm", pid=P + 1),
            events.CallAnswered("cm", Q1, "api", "cam", retry=True, pid=C),
            events.StatusSent("db", d2, rr.Status.FATAL, "broken", "s9", pid=db, seq=5),
            events.StatusDelivered("api", d2, rr.Status.FATAL, 1, 0.0, "s9", pid=P + 1),
            events.StatusDelivered("cm", Q1, rr.Status.FATAL, 2, 0.0, "s9", pid=C),
        ]
    )


def _failed_at(provider: str) -> events.CallFailed:
    return events.CallFailed(
        "cm", Q1, provider, "cam", "RegistrarUnavailableError", "gone", True, pid=C
    )


def test_a_status_climbing_to_an_id_retried_on_a_new_resource_is_on_its_path() -> None:
    assert [] == _of_rule(retried_on_a_new_resource(), "status-path")


def test_a_status_climbing_to_an_id_from_the_resource_it_left_is_off_its_path() -> None:
    # the same, but the FATAL climbs from D1, a dependency of RID (Q1's first resource):
    # by then Q1 is held on RID2
    h = retried_on_a_new_resource()
    d1 = "d1111111-0000"
    from_d1 = [
        *h[:13],
        dataclasses.replace(h[13], query_id=d1),
        dataclasses.replace(h[14], query_id=d1),
        h[15],
    ]
    assert {12, 16} == _found(_stamped(from_d1), "status-path")


def withdrawn_then_restored(released_after: float) -> list[events.Event]:
    """Issue 51: cm withdraws Q1 after erm committed it; erm is killed before its
    `Abandon`, restored holding Q1, and releases it `released_after` s after the restore."""
    restored = 20.0
    return [
        events.CatalogRestored("erm", (), (), (), pid=P, seq=1, at=10.0),
        events.ResourceLoaded("erm", "cam", RID, Q1, 0.01, 42, "cam 0", pid=P, seq=2, at=10.0),
        events.ConsumerAdded("erm", RID, Q1, "cm", pid=P, seq=3, at=10.0),
        events.CallWithdrawn("cm", Q1, "erm", "cam", "interrupted", pid=C, at=10.001),
        events.CatalogRestored(
            "erm",
            ((RID, "cam", "loaded", "42"),),
            ((Q1, RID, "cm"),),
            (),
            (1, 1, 0),
            pid=P + 1,
            seq=1,
            at=restored,
        ),
        events.ConsumerReleased(
            "erm", RID, Q1, "cm", "reconcile", pid=P + 1, seq=2, at=restored + released_after
        ),
        events.ResourceUnloaded("erm", "cam", RID, pid=P + 1, seq=3, at=restored + released_after),
        events.RegistrarStopped("cm", (), (), (), pid=C, at=restored + 3.0),
        events.RegistrarStopped("erm", (), (), (), pid=P + 1, seq=4, at=restored + 3.0),
    ]


def test_a_withdrawn_id_its_restarted_provider_holds_on_is_a_withdrawn_violation() -> None:
    verdict = check.check(numbered(withdrawn_then_restored(released_after=2.0)))

    found = [f for f in verdict.findings if f.rule == "withdrawn"]
    assert ("violated", [(4, 5)]) == (verdict.verdict, [f.lines for f in found])
    assert "erm held query q1111111 of cm for 2.0 s after cm withdrew that call" in found[0].message


def test_a_withdrawn_id_its_restarted_provider_releases_at_the_reconcile_holds() -> None:
    _holds(withdrawn_then_restored(released_after=0.01))


def test_a_withdrawn_id_answered_again_by_a_retry_is_no_withdrawn_violation() -> None:
    history = withdrawn_then_restored(released_after=2.0)
    retry = events.CallAnswered("cm", Q1, "erm", "cam", None, True, pid=C, at=20.001)

    assert [] == _of_rule([*history[:5], retry, *history[5:]], "withdrawn")


def held_then_retry_withdrawn(given_back: bool) -> list[events.Event]:
    """The last review: cm holds Q1 at erm; its caller calls again with Q1 (the workload's
    `_call_again`) and that retry is withdrawn at its timeout. `given_back` (the runtime
    before): erm releases Q1 `"abandoned"` and cm forgets it `"withdrawn"`; else Q1 stays
    held until cm's unload (lines 4 the withdrawal, 5 the release)."""
    kept = [
        events.QueryForgotten("cm", Q1, "erm", "unload", pid=C, at=12.0),
        events.ConsumerReleased("erm", RID, Q1, "cm", "unload", pid=P, seq=4, at=12.001),
    ]
    gave_back = [
        events.ConsumerReleased("erm", RID, Q1, "cm", "abandoned", pid=P, seq=4, at=11.01),
        events.QueryForgotten("cm", Q1, "erm", "withdrawn", pid=C, at=11.011),
    ]
    return [
        events.CatalogRestored("erm", (), (), (), pid=P, seq=1, at=10.0),
        events.ResourceLoaded("erm", "cam", RID, Q1, 0.01, 42, "cam 0", pid=P, seq=2, at=10.0),
        events.ConsumerAdded("erm", RID, Q1, "cm", pid=P, seq=3, at=10.0),
        events.CallWithdrawn("cm", Q1, "erm", "cam", "timeout", pid=C, at=11.0),
        *(gave_back if given_back else kept),
        events.ResourceUnloaded("erm", "cam", RID, pid=P, seq=5, at=12.002),
        events.RegistrarStopped("cm", (), (), (), pid=C, at=13.0),
        events.RegistrarStopped("erm", (), (), (), pid=P, seq=6, at=13.0),
    ]


def _answered_first(history: list[events.Event]) -> list[events.Event]:
    """`history` with cm's answer to Q1 after erm added it (line 4; the rest one later)."""
    answered = events.CallAnswered("cm", Q1, "erm", "cam", pid=C, at=10.001)
    return [*history[:3], answered, *history[3:]]


@pytest.mark.parametrize("first", ["released", "forgot"])
def test_a_withdrawn_retry_that_gave_a_held_id_back_is_a_withdrawn_violation(first: str) -> None:
    history = _answered_first(held_then_retry_withdrawn(given_back=True))
    if first == "forgot":  # (as the simulation showed it: its provider hung, the Abandon late)
        history[5], history[6] = history[6], history[5]
    found = _of_rule(history, "withdrawn")

    assert [(5, 6)] == [f.lines for f in found]
    who = {"released": "erm released query q1111111 of cm", "forgot": "cm forgot query q1111111"}
    assert f"{who[first]} after a withdrawn retry of it" in found[0].message


def test_a_withdrawn_retry_of_a_held_id_that_keeps_it_holds() -> None:
    _holds(_answered_first(held_then_retry_withdrawn(given_back=False)))


def test_a_withdrawn_retry_whose_new_load_was_undone_is_no_withdrawn_violation() -> None:
    # rule 20: erm had lost Q1; the retry added it again (a dedup hit, published before the
    # withdrawal), so its release "abandoned" undoes what the retry added
    history = _answered_first(held_then_retry_withdrawn(given_back=True))
    again = events.ConsumerAdded("erm", RID, Q1, "cm", pid=P, seq=3, at=10.5)

    assert [] == _of_rule([*history[:4], again, *history[4:]], "withdrawn")


def dependency_failed_then_restored(released_after: float) -> list[events.Event]:
    """Rule 17, issue 68 item 8: cm's load of RID2 called erm (Q1), which committed Q1 and
    died before its answer left: cm's call failed (`may_have_executed`, parent RID2), so
    that load failed; erm's next life restores Q1 and releases it `released_after` s after
    its restore (lines 4 the failure, 5 the load's, 6 the restore)."""
    withdrawn = withdrawn_then_restored(released_after)
    return [
        *withdrawn[:3],
        events.CallFailed(
            "cm",
            Q1,
            "erm",
            "cam",
            "RegistrarUnavailableError",
            "gone",
            True,
            parent=RID2,
            pid=C,
            at=10.001,
        ),
        events.LoadFailed(
            "cm", "map", RID2, Q2, "RegistrarUnavailableError", "gone", pid=C, at=10.002
        ),
        *withdrawn[4:],
    ]


def test_a_failed_dependency_s_id_held_on_after_its_load_ended_is_a_retry_ended_violation() -> None:
    history = dependency_failed_then_restored(released_after=2.0)
    verdict = check.check(numbered(history))

    found = [f for f in verdict.findings if f.rule == "retry-ended"]
    assert ("violated", [(5, 6)]) == (verdict.verdict, [f.lines for f in found])
    assert "erm held query q1111111 of cm for 2.0 s after the load that made" in found[0].message


def test_a_failed_dependency_s_id_released_at_the_reconcile_holds() -> None:
    history = dependency_failed_then_restored(released_after=0.01)
    _holds(history)


def test_a_failed_call_of_no_load_or_whose_load_goes_on_is_no_retry_ended_violation() -> None:
    """A top-level call (no `parent`) waits for its caller's retry (`kept-unclaimed`); a
    dependency whose load has not ended may still be retried: `retry-ended` judges
    neither (nor one answered again by a retry)."""
    history = dependency_failed_then_restored(released_after=2.0)
    top = dataclasses.replace(history[3], parent=None)
    assert [] == _of_rule([*history[:3], top, *history[4:]], "retry-ended")
    assert [] == _of_rule([*history[:4], *history[5:]], "retry-ended")
    retry = events.CallAnswered("cm", Q1, "erm", "cam", RID2, True, pid=C, at=10.0015)
    assert [] == _of_rule([*history[:4], retry, *history[4:]], "retry-ended")


def failed_then_released(lives: int, *, then: events.Event | None = None) -> list[events.Event]:
    """Rule 17 case 3: erm committed cm's Q1 and died before its answer left (cm's call
    failed, `may_have_executed`); its next life restores Q1 and a reconcile releases it,
    in that life (`lives=1`) or in the one after (`lives=2`). `then`: an event of cm's
    between its failure and the release."""
    restore = events.CatalogRestored(
        "erm", ((RID, "cam", "loaded", "42"),), ((Q1, RID, "cm"),), (), (1, 1, 0), seq=1
    )
    history: list[events.Event] = [
        events.CatalogRestored("erm", (), (), (), pid=P, seq=1),
        events.ResourceLoaded("erm", "cam", RID, Q1, 0.01, 42, "cam 0", pid=P, seq=2),
        events.ConsumerAdded("erm", RID, Q1, "cm", pid=P, seq=3),
        events.ChildExited("sup", "erm", P, "killed by SIGKILL"),
        _failed(),
        *([then] if then is not None else []),
    ]
    for life in range(1, lives + 1):
        history.append(dataclasses.replace(restore, pid=P + life))
        if life < lives:
            history.append(events.ChildExited("sup", "erm", P + life, "killed by SIGKILL"))
    last = P + lives
    history += [
        events.ConsumerReleased("erm", RID, Q1, "cm", "reconcile", pid=last, seq=2),
        events.ResourceUnloaded("erm", "cam", RID, pid=last, seq=3),
        events.RegistrarStopped("cm", (), (), (), pid=C),
        events.RegistrarStopped("erm", (), (), (), pid=last, seq=4),
    ]
    return _stamped(history)


def test_a_failed_calls_id_released_by_a_reconcile_of_the_life_that_restored_it_is_retry_kept() -> (
    None
):
    verdict = check.check(numbered(failed_then_released(lives=1)))

    found = [f for f in verdict.findings if f.rule == "retry-kept"]
    assert ("violated", [(5, 7)]) == (verdict.verdict, [f.lines for f in found])
    assert "erm released query q1111111 of cm at a reconcile of the life that restored it" in (
        found[0].message
    )


@pytest.mark.parametrize(
    "then",
    [
        None,
        lambda: events.CallWithdrawn("cm", Q1, "erm", "cam", "timeout", pid=C),
        lambda: events.QueryForgotten("cm", Q1, "erm", "unload", pid=C),
        lambda: events.LoadFailed("cm", "composite", "r3", "q3", "ValueError", "x", pid=C),
        lambda: events.RegistrarStopped("cm", (), (), (), pid=C),
    ],
    ids=["a later life", "withdrawn", "forgotten", "its load failed", "stopped"],
)
def test_a_failed_calls_id_released_when_no_retry_can_come_is_no_retry_kept_violation(
    then: Callable[[], events.Event] | None,
) -> None:
    # released by a later life (no retry came while the first lived), or after cm gave
    # the call up: it withdrew or forgot it, the load that made it ended, it stopped.
    # (Made in the test: an event made at import takes a number of this process's.)
    event = None if then is None else then()
    history = failed_then_released(lives=2 if event is None else 1, then=event)

    assert [] == _of_rule(history, "retry-kept")


def kept_then_given_back(after: float, *, claimed: bool = False) -> list[events.Event]:
    """Rule 17 case 3 with no retry: erm died with cm's Q1 committed, its next life
    restores Q1 at 10 s and keeps it for cm's retry, which never comes (`claimed`: a retry
    is answered at 10.5 s, unloaded later); erm gives it back `after` s after the restore;
    both stop at 14 s. Stamped by time (cm's `call_timeout`: 1 s, the bound 2 s)."""
    from rr_actors._core import hlc  # noqa: PLC0415

    history: list[tuple[float, events.Event]] = [
        (9.0, events.CatalogRestored("erm", (), (), (), pid=P, seq=1)),
        (9.1, events.ResourceLoaded("erm", "cam", RID, Q1, 0.01, 42, "cam 0", pid=P, seq=2)),
        (9.1, events.ConsumerAdded("erm", RID, Q1, "cm", pid=P, seq=3)),
        (9.2, events.ChildExited("sup", "erm", P, "killed by SIGKILL")),
        (9.2, _failed()),
        (
            10.0,
            events.CatalogRestored(
                "erm", ((RID, "cam", "loaded", "42"),), ((Q1, RID, "cm"),), (), pid=P + 1, seq=1
            ),
        ),
        (
            10.0 + after,
            events.ConsumerReleased("erm", RID, Q1, "cm", "abandoned", pid=P + 1, seq=2),
        ),
        (10.0 + after, events.ResourceUnloaded("erm", "cam", RID, pid=P + 1, seq=3)),
        (14.0, events.RegistrarStopped("cm", (), (), (), pid=C)),
        (14.0, events.RegistrarStopped("erm", (), (), (), pid=P + 1, seq=4)),
    ]
    if claimed:  # (then released by its unload)
        history.append((10.5, events.CallAnswered("cm", Q1, "erm", "cam", None, True, pid=C)))
        history.append((10.0 + after, events.QueryForgotten("cm", Q1, "erm", "unload", pid=C)))
    history.sort(key=lambda pair: pair[0])  # (stable: the order above at equal times)
    return [
        dataclasses.replace(e, hlc=hlc.from_seconds(1e9 + at) + i, host="h")
        for i, (at, e) in enumerate(history)
    ]


def test_an_id_kept_for_a_retry_that_never_comes_held_past_call_timeout_is_kept_unclaimed() -> None:
    verdict = check.check(numbered(kept_then_given_back(after=3.5)), timeouts={"cm": 1.0})

    found = [f for f in verdict.findings if f.rule == "kept-unclaimed"]
    assert ("violated", [(5, 6, 7)]) == (verdict.verdict, [f.lines for f in found])
    assert "erm still held query q1111111 of cm 2 s after its restore" in found[0].message


@pytest.mark.parametrize(
    ("after", "claimed", "timeouts"),
    [(1.5, False, {"cm": 1.0}), (3.5, True, {"cm": 1.0}), (3.5, False, {})],
    ids=["given back in time", "claimed by a retry", "call_timeout not known"],
)
def test_an_id_kept_for_a_retry_given_back_in_time_or_claimed_is_no_kept_unclaimed_violation(
    after: float, claimed: bool, timeouts: dict[str, float]
) -> None:
    _holds(kept_then_given_back(after=after, claimed=claimed), timeouts=timeouts)


def timed_out(took: float, *, reason: str = "timeout", retried: bool = True) -> list[events.Event]:
    """`clean()` with a call of cm (Q3) that `call_with_retry` tried at 100.0 (its provider
    died: `CallFailed`) and again at 100.5 (with the first try's deadline), withdrawn `took`
    seconds after its first try began, before cm stops."""
    h = clean()
    tries = [
        events.CallFailed(
            "cm",
            Q3,
            "erm",
            "cam",
            "RegistrarUnavailableError",
            "died",
            True,
            started=100.0,
            at=100.1,
            pid=C,
        )
    ]
    if retried:
        tries.append(
            events.CallFailed(
                "cm",
                Q3,
                "erm",
                "cam",
                "RegistrarUnavailableError",
                "died",
                True,
                True,
                started=100.5,
                at=100.6,
                pid=C,
            )
        )
    gone = events.CallWithdrawn(
        "cm", Q3, "erm", "cam", reason, started=100.0, at=100.0 + took, pid=C
    )
    return [*h[:-2], *tries, gone, *h[-2:]]


def test_a_call_withdrawn_at_a_timeout_before_its_call_timeout_ran_out_is_timed_out() -> None:
    """Issue 68 item 8: the mutant `retry.py:84` (`monotonic() / limit` for `+`) made every
    `call_with_retry` time out at once, before it sent anything: its `CallWithdrawn`."""
    verdict = check.check(numbered(timed_out(0.3)), timeouts={"cm": 1.0})

    found = [f for f in verdict.findings if f.rule == "timed-out"]
    assert ("violated", [(15, 17)]) == (verdict.verdict, [f.lines for f in found])
    assert "cm's call q3333333 to erm/cam timed out 0.300 s after it began" in found[0].message
    at_once = check.check(numbered(timed_out(0.0, retried=False)), timeouts={"cm": 1.0})
    assert [(15, 16)] == [f.lines for f in at_once.findings if f.rule == "timed-out"]


@pytest.mark.parametrize(
    ("took", "reason", "timeouts", "manager"),
    [
        (1.0, "timeout", {"cm": 1.0}, False),
        (0.97, "timeout", {"cm": 1.0}, False),
        (0.3, "interrupted", {"cm": 1.0}, False),
        (0.3, "timeout", {}, False),
        (0.3, "timeout", {"cm": 1.0}, True),
    ],
    ids=[
        "at its timeout (the retry's own start is later)",
        "within the clocks' slack",
        "cancelled",
        "call_timeout not known",
        "a manager's call (its load may pass its own timeout)",
    ],
)
def test_a_call_withdrawn_once_its_timeout_ran_out_or_not_judged_is_no_timed_out_violation(
    took: float, reason: str, timeouts: dict[str, float], manager: bool
) -> None:
    started = [events.ChildStarted("sup", "cm", C)] if manager else []
    _holds([*started, *timed_out(took, reason=reason)], timeouts=timeouts)


def test_a_restart_with_a_restore_holds_what_the_restore_lists() -> None:
    h = without_backup()
    # erm has a backup: its restart lists Q1 again, and nobody releases it
    restored = events.CatalogRestored(
        "erm", ((RID, "cam", "loaded", "42", ""),), ((Q1, RID, "cm"),), (), (1, 1, 0), pid=P + 1
    )
    first = events.CatalogRestored("erm", (), (), (), pid=P)
    history = _stamped([first, *h[:4], restored, *h[4:7], *h[9:]])
    assert {6, 13} == _found(history, "end")
    # a restore that lists no ids (Q1 told lost at the reconcile) holds
    empty = dataclasses.replace(restored, resources=(), consumers=(), counts=(0, 0, 0))
    assert "held" == check.check(numbered(_stamped([first, *h[:4], empty, *h[4:]]))).verdict


def lost_consumer(then: str) -> list[events.Event]:
    """erm serves manager cm's Q1; cm is killed and nobody restarts it (lost for good,
    rule 19); `then`: what erm does before its stop ("release": lets Q1 go; "keep": lists
    it at its stop; "restart": cm comes back, as a new life, before erm's stop)."""
    h = [
        events.ChildStarted("sup", "cm", C),
        events.ResourceLoaded("erm", "cam", RID, Q1, 0.01, 42, "cam 0", pid=P, seq=1),
        events.ConsumerAdded("erm", RID, Q1, "cm", pid=P, seq=2),
        events.CallAnswered("cm", Q1, "erm", "cam", pid=C),
        events.ChildExited("sup", "cm", C, "killed by SIGKILL"),
    ]
    row = ((RID, "cam", "loaded", "42", ""),), ((Q1, RID, "cm"),)
    if then == "release":
        h += [
            events.ConsumerReleased("erm", RID, Q1, "cm", "lost", pid=P, seq=3),
            events.ResourceUnloaded("erm", "cam", RID, pid=P, seq=4),
            events.RegistrarStopped("erm", (), (), (), pid=P, seq=5),
        ]
    elif then == "restart":
        h += [
            events.CatalogRestored("cm", (), (), (), pid=C + 1),
            events.RegistrarStopped("erm", *row, (), pid=P, seq=3),
        ]
    else:
        h += [events.RegistrarStopped("erm", *row, (), pid=P, seq=3)]
    return _stamped(h)


def test_an_id_of_a_consumer_lost_for_good_kept_to_the_providers_stop_is_an_end() -> None:
    # (mutant `_registrar/life.py:606:ReplaceComparisonOperator_Eq_GtE`: a registrar lost
    # for good with a name after the provider's was never released there; crashloop seed 1)
    assert {3, 5} == _found(lost_consumer("keep"), "end")


@pytest.mark.parametrize("then", ["release", "restart"])
def test_an_id_of_a_consumer_lost_for_good_released_or_back_is_no_end(then: str) -> None:
    assert [] == _of_rule(lost_consumer(then), "end")


# -- mutations of the shipped plans' real runs: each is caught, by its rule ----------------
#
# A mutation turns a clean history into one where a registrar broke a rule (the events
# then renumbered: what it removes was never published, what it adds was, so that no
# mutation looks like a loss). Each takes the first place it applies to, or returns None.

History = list[events.Event]


def _index(h: History, kind: type) -> int | None:
    """The index of the first event of `kind`."""
    return next((i for i, e in enumerate(h) if type(e) is kind), None)


def _moved(h: History, i: int, to: int) -> History:
    out = [*h[:i], *h[i + 1 :]]
    out.insert(to if to < i else to - 1, h[i])
    return out


def _fresh(event: events.Event, **changes: object) -> events.Event:
    """A new event like `event` (its clock stamp right after it)."""
    return dataclasses.replace(event, hlc=event.hlc + 1, **changes)  # type: ignore[arg-type]


def _after(before: events.Event, event: events.Event) -> events.Event:
    """`event`, stamped right after `before` (on the host of `before`)."""
    return dataclasses.replace(event, hlc=before.hlc + 1, host=before.host)  # type: ignore[arg-type]


def _last_release(h: History) -> tuple[int, int] | None:
    """(index of a resource's last ConsumerReleased, index of its ResourceUnloaded)."""
    for u, unload in enumerate(h):
        if type(unload) is events.ResourceUnloaded:
            for c in range(u - 1, -1, -1):
                e = h[c]
                if getattr(e, "registrar", None) != unload.registrar:
                    continue
                if type(e) is events.ConsumerReleased and e.resource_id == unload.resource_id:
                    return c, u
                if type(e) in (events.ConsumerAdded, events.CatalogRestored):
                    break  # (its last holder went before a restart: not this one)
    return None


def _stops_later(h: History, i: int) -> bool:
    """Whether the registrar of `h[i]` stops cleanly in the same life (with its rows)."""
    name, pid = h[i].registrar, h[i].pid  # type: ignore[union-attr]
    for e in h[i + 1 :]:
        if getattr(e, "registrar", None) == name:
            if type(e) is events.CatalogRestored or e.pid != pid:
                return False
            if type(e) is events.RegistrarStopped:
                return e.complete
    return False


def duplicate(kind: type) -> Callable[[History], History | None]:
    def mutate(h: History) -> History | None:
        i = _index(h, kind)
        return None if i is None else [*h[: i + 1], h[i], *h[i + 1 :]]

    return mutate


def unload_before_release(h: History) -> History | None:
    found = _last_release(h)
    return None if found is None else _moved(h, found[1], found[0])


def drop_unload(h: History) -> History | None:
    """A resource's unload, in a life that ends in a clean stop. Not one whose equal
    request (server and digest) is loaded again later in that life: without its unload
    that history reads as an equal request loaded twice, which `dedup` reports, not
    `no-leak` (a real run under load reloads now and then: in `strategies`' run 3, in a
    run of the suite beside two busy loops, only `dedup` saw it; the shape is the test
    below). Nor one of a resource no consumer held (its callers gave up before its load
    ended, as most of `simshed`'s loads): `no-leak` judges a resource whose last consumer
    was released."""
    digests = {
        (e.registrar, e.resource_id): (e.server, e.digest)
        for e in h
        if type(e) is events.ResourceLoaded
    }
    held = {(e.registrar, e.resource_id) for e in h if type(e) is events.ConsumerReleased}
    for i, e in enumerate(h):
        if type(e) is not events.ResourceUnloaded or not _stops_later(h, i):
            continue
        if (e.registrar, e.resource_id) not in held:
            continue
        equal = digests.get((e.registrar, e.resource_id))
        if (
            equal is not None
            and equal[1] is not None
            and any(
                type(later) is events.ResourceLoaded
                and later.registrar == e.registrar
                and later.pid == e.pid
                and (later.server, later.digest) == equal
                for later in h[i + 1 :]
            )
        ):
            continue
        return _without(h, i)
    return None


def test_drop_unload_leaves_an_unload_whose_equal_request_is_loaded_again() -> None:
    # `clean()` has the shape of `strategies`' run 3 in a loaded run of the suite: the
    # first resource's unload, then an equal request (digest 42) loaded again.
    h = clean()
    first = h.index(next(e for e in h if type(e) is events.ResourceUnloaded))
    dropped = check.check(numbered(renumbered(_without(h, first))))
    assert "dedup" in {f.rule for f in dropped.findings if f.kind == "violation"}
    mutated = drop_unload(h)
    assert mutated is not None
    assert len(h) - 1 == len(mutated)
    assert first < len(mutated)
    assert h[first] in mutated  # (the second unload is the one dropped)
    verdict = check.check(numbered(renumbered(mutated)))
    assert {"no-leak"} == {f.rule for f in verdict.findings if f.kind == "violation"}


def drop_last_release(h: History) -> History | None:
    found = _last_release(h)
    return None if found is None else _without(h, found[0])


def _release_before_stop(h: History) -> tuple[int, int] | None:
    """A resource's last release and its unload, in a life that ends in a clean stop."""
    done = 0
    while (found := _last_release(h[done:])) is not None:
        c, u = found[0] + done, found[1] + done
        if _stops_later(h, c):
            return c, u
        done = u + 1
    return None


def release_unpublished(h: History) -> History | None:
    """A release made without its event (and its unload not published either): the
    stop's rows no longer list the id. (In a life that ends in a restart, that is what
    a kill right after the commit shows: the restore decides.)"""
    found = _release_before_stop(h)
    return None if found is None else _without(h, *found)


def provider_keeps_id(h: History) -> History | None:
    """A provider that never releases an id (it lists it at its last stop) that its
    consumer gave back before that consumer stopped."""
    done = 0
    while (found := _last_release(h[done:])) is not None:
        c, u = found[0] + done, found[1] + done
        done = u + 1
        release, unload = h[c], h[u]
        assert type(release) is events.ConsumerReleased
        assert type(unload) is events.ResourceUnloaded
        names = [getattr(e, "registrar", None) for e in h]
        mine = [i for i in range(c, len(h)) if names[i] == release.registrar]
        s = next((i for i in mine if type(h[i]) is events.RegistrarStopped), mine[-1])
        stop = h[s]  # the stop of this life: its last event
        gone = [i for i in range(s) if names[i] == release.consumer]
        if not (
            type(stop) is events.RegistrarStopped
            and s == mine[-1]
            and stop.complete
            and _stops_later(h, c)
            and gone
            and type(h[gone[-1]]) is events.RegistrarStopped
        ):
            continue
        kept = dataclasses.replace(
            stop,
            resources=(*stop.resources, (unload.resource_id, unload.server, "loaded", "", "")),
            consumers=(*stop.consumers, (release.query_id, release.resource_id, release.consumer)),
        )
        return [*_without(h[:s], c, u), kept, *h[s + 1 :]]
    return None


def add_after_unload(h: History) -> History | None:
    i = _index(h, events.ResourceUnloaded)
    if i is None:
        return None
    unload = h[i]
    late = events.ConsumerAdded(
        unload.registrar, unload.resource_id, "q-late", "client-0", pid=unload.pid, seq=1
    )
    return [*h[: i + 1], _after(unload, late), *h[i + 1 :]]


def _two_resources(h: History) -> tuple[int, str] | None:
    """(index of a ConsumerAdded, another resource its provider served before it)."""
    seen: dict[str, str] = {}  # provider -> a resource it served
    for i, e in enumerate(h):
        if type(e) is events.ConsumerAdded:
            other = seen.get(e.registrar)
            if other is not None and other != e.resource_id:
                return i, other
            seen[e.registrar] = e.resource_id
    return None


def release_names_other_resource(h: History) -> History | None:
    for i, e in enumerate(h):
        if type(e) is events.ConsumerReleased:
            others = [
                x.resource_id
                for x in h[:i]
                if type(x) is events.ConsumerAdded
                and x.registrar == e.registrar
                and x.resource_id != e.resource_id
            ]
            if others:
                return [*h[:i], dataclasses.replace(e, resource_id=others[-1]), *h[i + 1 :]]
    return None


def add_held_id_elsewhere(h: History) -> History | None:
    found = _two_resources(h)
    if found is None:
        return None
    i, other = found
    return [*h[: i + 1], _fresh(h[i], resource_id=other), *h[i + 1 :]]


def load_equal_twice(h: History) -> History | None:
    for i, e in enumerate(h):
        if type(e) is events.ResourceLoaded and e.digest is not None:
            twin = _fresh(e, resource_id="r-twin", query_id="q-twin")
            return [*h[: i + 1], twin, *h[i + 1 :]]
    return None


def serve_before_restore(h: History) -> History | None:
    for i, e in enumerate(h):
        if type(e) is events.CatalogRestored:
            mine = (
                j for j in range(i + 1, len(h)) if getattr(h[j], "registrar", "") == e.registrar
            )
            j = next(mine, None)
            serves = (events.CatalogRestored, events.RegistrarStopped, events.StatusDelivered)
            if j is not None and h[j].pid == e.pid and type(h[j]) not in serves:
                return _moved(h, i, j + 1)  # (its next event of that life first)
    return None


def _killed_before(h: History, i: int, consumer: str) -> bool:
    """Whether `consumer`, without a backup (it never restores), was killed before `h[i]`:
    its last event before and its first after are of two processes."""
    if any(type(e) is events.CatalogRestored and e.registrar == consumer for e in h):
        return False
    before = [e.pid for e in h[:i] if getattr(e, "registrar", None) == consumer]
    after = (e.pid for e in h[i + 1 :] if getattr(e, "registrar", None) == consumer)
    return bool(before) and next(after, before[-1]) != before[-1]


def restore_loses_id(h: History) -> History | None:
    """A restore without an id held before the restart (its consumer still holds it, and
    was not told it was lost). Not an id of a consumer without a backup killed before the
    restore (`simprogram`'s clients, killed with the program): the events of a release it
    made just before may be lost with it, and nobody holds the id any more, so `kept`
    excuses that row's loss (only the later release by its reconcile, of an id the
    provider no longer holds, shows the mutation: `unload-once` sees that, not `kept`;
    `simprogram` seeds 6, 7, 9, 11 lost a client's row). Nor an id its consumer's restore
    lists as a dependency of a resource it was unloading: its release may have been
    committed at the provider before the kill (`simprogram` seed 125)."""
    releasing = {
        (e.registrar, row[0])
        for e in h
        if type(e) is events.CatalogRestored
        for row in e.clients
        if row[3] in {r[0] for r in e.resources if r[2] == "unloading"}
    }
    held: dict[str, set[str]] = {}
    for i, e in enumerate(h):
        if type(e) is events.ConsumerAdded:
            held.setdefault(e.registrar, set()).add(e.query_id)
        elif type(e) is events.ConsumerReleased:
            held.get(e.registrar, set()).discard(e.query_id)
        elif type(e) is events.CatalogRestored and e.complete:
            rows = [
                row
                for row in e.consumers
                if row[0] in held.get(e.registrar, set())
                and not _killed_before(h, i, row[2])
                and (row[2], row[0]) not in releasing
            ]
            forgotten = {  # (before the restore: a release a kill cut off from its event)
                x.query_id for x in h if type(x) is events.QueryForgotten and x.hlc < e.hlc
            }
            told = {  # (its consumer told of its loss: no violation)
                x.query_id
                for x in h
                if type(x) is events.StatusDelivered and x.status is rr.Status.FATAL
            }
            rows = [row for row in rows if row[0] not in forgotten | told]
            if rows:
                lost = rows[0][0]
                kept = tuple(row for row in e.consumers if row[0] != lost)
                return [*h[:i], dataclasses.replace(e, consumers=kept), *h[i + 1 :]]
            held[e.registrar] = {row[0] for row in e.consumers}
    return None


def two_servers(second_exit: str) -> list[events.Event]:
    """`erm` served by process P, and by P + 1 too from its second load on (a cut let
    each side serve it); P + 1's process ends with `second_exit`, then the tree's
    shutdown stops P."""
    p2 = P + 1
    return [
        events.CatalogRestored("erm", (), (), (), pid=P, seq=1),
        events.ResourceLoaded("erm", "cam", RID, Q1, 0.01, 42, "cam 0", pid=P, seq=2),
        events.ConsumerAdded("erm", RID, Q1, "cm", pid=P, seq=3),
        events.CatalogRestored("erm", (), (), (), pid=p2, seq=1),  # (behind a cut)
        events.ResourceLoaded("erm", "cam", RID2, Q2, 0.01, 42, "cam 0", pid=p2, seq=2),
        events.ConsumerAdded("erm", RID2, Q2, "cm", pid=p2, seq=3),
        events.ConsumerReleased("erm", RID2, Q2, "cm", "name yielded", pid=p2, seq=4),
        events.ResourceUnloaded("erm", "cam", RID2, pid=p2, seq=5),
        events.RegistrarStopped("erm", (), (), (), pid=p2, seq=6),
        events.ChildExited("beyond", "erm", p2, second_exit),
        events.ConsumerReleased("erm", RID, Q1, "cm", pid=P, seq=4),
        events.ResourceUnloaded("erm", "cam", RID, pid=P, seq=5),
        events.RegistrarStopped("cm", (), (), (), pid=C),
        events.RegistrarStopped("erm", (), (), (), pid=P, seq=6),
        events.ChildExited("root", "erm", P, "shutdown"),
    ]


def test_a_second_server_of_a_name_that_yields_holds() -> None:
    _holds(two_servers("normal"))


def test_two_servers_of_a_name_to_the_end_of_the_run_are_a_one_name_violation() -> None:
    verdict = check.check(numbered(two_servers("shutdown")))

    assert "violated" == verdict.verdict
    [found] = verdict.findings
    assert "one-name" == found.rule
    assert (1, 4, 9) == found.lines  # (each one's first line, the second's last)
    assert "two registrars erm served to the end of the run" in found.message


REFUSED = (
    "failed to start: manager 'erm' failed to start:\nrr_actors.errors.DuplicateNameError: a "
    "registrar named 'erm' is already served on system 'simulated' (by process 101)"
)
"""A restart's exit into a name another serves (the simulation's words, shortened)."""


def first_yields(restart_exit: str | None) -> list[events.Event]:
    """`erm` served by P, and by P + 1 from its second load on (a cut); at the heal P
    yields (a majority policy keeps P + 1) and its `permanent` supervisor restarts it:
    the restart (P + 2) restores, then exits with `restart_exit` (`None`: it serves on
    to the tree's shutdown); P + 1 serves to the end."""
    p2, p3 = P + 1, P + 2
    restart = [events.CatalogRestored("erm", (), (), (), pid=p3, seq=1)]
    if restart_exit is None:
        restart += [
            events.RegistrarStopped("erm", (), (), (), pid=p3, seq=2),
            events.ChildExited("root", "erm", p3, "shutdown"),
        ]
    else:
        restart.append(events.ChildExited("root", "erm", P - 1, restart_exit))
    return [
        events.CatalogRestored("erm", (), (), (), pid=P, seq=1),
        events.ResourceLoaded("erm", "cam", RID, Q1, 0.01, 42, "cam 0", pid=P, seq=2),
        events.ConsumerAdded("erm", RID, Q1, "cm", pid=P, seq=3),
        events.CatalogRestored("erm", (), (), (), pid=p2, seq=1),  # (behind a cut)
        events.ResourceLoaded("erm", "cam", RID2, Q2, 0.01, 42, "cam 0", pid=p2, seq=2),
        events.ConsumerAdded("erm", RID2, Q2, "cm", pid=p2, seq=3),
        events.ConsumerReleased("erm", RID, Q1, "cm", "name yielded", pid=P, seq=4),
        events.ResourceUnloaded("erm", "cam", RID, pid=P, seq=5),
        events.RegistrarStopped("erm", (), (), (), pid=P, seq=6),
        events.ChildExited("root", "erm", P, "normal"),
        *restart,
        events.ConsumerReleased("erm", RID2, Q2, "cm", pid=p2, seq=4),
        events.ResourceUnloaded("erm", "cam", RID2, pid=p2, seq=5),
        events.RegistrarStopped("cm", (), (), (), pid=C),
        events.RegistrarStopped("erm", (), (), (), pid=p2, seq=6),
        events.ChildExited("beyond", "erm", p2, "shutdown"),
    ]


POLICIES = ("first_served", "majority", "policy:keep")
"""Rule 22 policies (`[hosts]` `resolve`): both named ones, and a function's."""


@pytest.mark.parametrize("resolve", POLICIES)
def test_a_yielded_registrars_restart_refused_its_name_does_not_serve(resolve: str) -> None:
    """Issue 56: a `permanent` registrar that yields at a heal is restarted into
    `DuplicateNameError` (OTP's `already_started`): the one kept serves alone."""
    _holds(first_yields(REFUSED), resolve=resolve)


@pytest.mark.parametrize("resolve", POLICIES)
def test_two_servers_kept_after_a_heal_are_a_one_name_violation_under_each_policy(
    resolve: str,
) -> None:
    """The mutations: the restart serves on (it started), or the second server is kept
    beside the first; each policy's words say which one yields."""
    for history in (first_yields(None), two_servers("shutdown")):
        verdict = check.check(numbered(history), resolve)

        assert ["one-name"] == [f.rule for f in verdict.findings if f.kind == "violation"]
        keeps = check.KEEPS.get(resolve, f"resolve = {resolve!r} keeps one and the other yields")
        assert f"healed, {keeps} (rule 22)" in verdict.findings[0].message


def test_one_name_says_what_the_plan_beside_the_file_keeps(tmp_path: Path) -> None:
    (tmp_path / "events.jsonl").write_text(
        "".join(json.dumps(events.to_dict(e)) + "\n" for e in two_servers("shutdown"))
    )
    (tmp_path / "plan.toml").write_text('[hosts]\nresolve = "majority"\n')

    [verdict] = check.check_file(tmp_path).values()

    assert "the one begun on a minority side yields" in verdict.findings[0].message


# -- rows left at the end, rule 7's order, the supervisor's intensity (issue 51) --------------


def test_a_row_no_running_consumer_holds_at_the_last_stop_is_left() -> None:
    h = clean()
    unheld = events.CatalogRestored("erm", ((RID, "cam", "loaded", "42", ""),), (), (), pid=P + 1)
    stop = events.RegistrarStopped("erm", unheld.resources, (), (), pid=P + 1)
    assert {10, 11} == _found([*h[:9], unheld, stop], "left")  # (listed at the restore)
    app = events.RegistrarStopped("app", (), (), ((Q2, "cm", "comp", ""),), pid=A)
    assert {4, 11} == _found([*with_paths()[:7], *with_paths()[8:11], app], "left")


def test_rows_a_running_consumer_holds_at_a_providers_last_stop_are_not_left() -> None:
    h = clean()
    held = events.RegistrarStopped(  # erm stops first: cm still runs and holds both ids
        "erm", ((RID, "cam", "loaded", "42", ""),), ((Q1, RID, "cm"), (Q2, RID, "cm")), (), pid=P
    )
    _holds([*h[:4], held, h[14]])


@pytest.mark.parametrize("published", ["before", "after"])
def test_rows_at_a_stop_by_a_give_up_are_not_judged_as_left(published: str) -> None:
    # a give-up is published once the children it stopped are stopped ("after": seed 91
    # of intensity's plan with clients, a load it cut short still `loading`)
    h = clean()
    gave_up = events.SupervisorGaveUp("root", "more than 0 restarts", 0, 1.0, pid=1)
    stop = events.RegistrarStopped(
        "erm",
        ((RID, "cam", "loaded", "42", ""), (RID2, "cam", "loading", "7", "")),
        ((Q1, RID, "cm"),),
        (),
        pid=P,
        seq=5,
    )
    order = [gave_up, stop] if published == "before" else [stop, gave_up]
    verdict = check.check(numbered([*h[:4], *order]))
    assert [] == [f for f in verdict.findings if f.rule == "left"]
    verdict = check.check(numbered([*h[:4], stop]))  # (no give-up: the loading row is left)
    assert ["left"] == [f.rule for f in verdict.findings if f.rule == "left"]


def test_a_dependency_forgotten_while_its_resource_is_held_is_found() -> None:
    h = with_paths()
    early = events.QueryForgotten("cm", Q1, "erm", "in doubt", pid=C)  # Q2 still holds RID2
    assert {2, 3, 8} == _found([*h[:7], early, *h[7:9], *h[10:]], "dependency-held")


def test_a_dependency_forgotten_once_its_resource_has_no_consumer_holds() -> None:
    assert [] == _of_rule(with_paths(), "dependency-held")  # (forgotten after RID2's last release)


def test_a_dependency_its_provider_ended_may_be_forgotten_while_its_resource_is_held() -> None:
    h = with_paths()
    for reason in ("unknown at reconcile", "provider lost", "revoked"):
        lost = events.QueryForgotten("cm", Q1, "erm", reason, pid=C)
        assert [] == _of_rule([*h[:7], lost, *h[7:9], *h[10:]], "dependency-held")


def test_a_restore_that_gives_back_a_held_resources_dependency_is_found() -> None:
    # (the restart finds cm's RID2 held by app's Q2, and its dependency Q1's record)
    restored = events.CatalogRestored(
        "cm",
        ((RID2, "comp", "loaded", "7", ""),),
        ((Q2, RID2, "app"),),
        ((Q1, "erm", "leaf", RID2),),
        (1, 1, 1),
        pid=C + 1,
    )
    doubt = events.QueryForgotten("cm", Q1, "erm", "in doubt", pid=C + 1)
    assert {1, 2} == _found([restored, doubt], "dependency-held")
    unlisted = dataclasses.replace(restored, resources=(), consumers=(), clients=(), complete=False)
    assert [] == _of_rule([unlisted, doubt], "dependency-held")  # (rows not listed: not judged)


def test_a_resource_unloaded_before_its_dependency_was_released_is_found() -> None:
    h = with_paths()
    unloaded = events.ResourceUnloaded("cm", "comp", RID2, pid=C)
    assert {2, 10} == _found([*h[:9], unloaded, *h[9:]], "unload-order")
    _holds([*h[:10], unloaded, *h[10:]])  # its dependency first


def _exits(*times: float, restart: str = "permanent", stopped: bool = False) -> list[events.Event]:
    """db exits at each of `times` (s) under root (at most 2 restarts within 5 s), each
    exit followed by its restart."""
    out: list[events.Event] = []
    for i, at in enumerate(times):
        exit_ = events.ChildExited(
            "root", "db", 10 + i, "killed", restart, False, stopped, 2, 5.0, at=at
        )
        out += [exit_, events.ChildRestarted("root", "db", 11 + i, 0.01, at=at + 0.01)]
    return out


def _gives_up(history: list[events.Event]) -> list[events.Event]:
    """`history`'s last restart replaced by the supervisor's give-up."""
    return [*history[:-1], events.SupervisorGaveUp("root", "more than 2", 2, 5.0, pid=1)]


def test_a_supervisor_that_does_not_give_up_past_its_intensity_is_found() -> None:
    assert {1, 3, 5} == _found(_exits(0.0, 1.0, 2.0), "intensity")  # 3 within 5 s


def test_a_supervisor_that_gives_up_within_its_intensity_is_found() -> None:
    assert {1, 3, 4} == _found(_gives_up(_exits(0.0, 1.0)), "intensity")  # only 2
    assert {3, 5, 6} == _found(_gives_up(_exits(0.0, 1.0, 5.5)), "intensity")  # 0.0 is out


def test_a_supervisor_that_gives_up_exactly_past_its_intensity_holds() -> None:
    for history in (
        _gives_up(_exits(0.0, 1.0, 2.0)),  # the third within 5 s: it gives up there
        _exits(0.0, 1.0, 6.0),  # 0.0 and 1.0 left the window: 1 restart
        _exits(0.0, 1.0, 2.0, restart="temporary"),  # never counted (OTP)
        _exits(0.0, 1.0, 2.0, stopped=True),  # its supervisor stopped it: not counted
        [*_exits(0.0, 1.0)[:2], *_gives_up(_exits(1.0, 2.0))],  # (an exit's restart failed)
    ):
        _holds(history)


def test_a_supervisor_started_again_counts_its_exits_afresh() -> None:
    # (its program killed and started again: kill_program) a second ChildStarted of db
    first = [events.ChildStarted("root", "db", 9, at=0.0)]
    again = [events.ChildStarted("root", "db", 20, at=2.5)]
    _holds([*first, *_exits(0.5, 1.0), *again, *_exits(3.0)])
    # (without the second start, the third exit within 5 s is one past its intensity)
    assert {2, 4, 6} == _found([*first, *_exits(0.5, 1.0), *_exits(3.0)], "intensity")


def test_an_exit_at_the_edge_of_the_intensity_window_is_not_judged() -> None:
    slack = _supervision_rules.SLACK_S / 2
    for history in (_exits(0.0, 1.0, 5.0 - slack), _gives_up(_exits(0.0, 1.0, 5.0 + slack))):
        _holds(history)


# -- the supervisor's strategy and restart types, escalation (OTP, issue 51) ---------------


def _tree(
    strategy: str,
    *steps: str,
    children: tuple[str, ...] = ("db", "api", "web"),
    types: dict[str, str] | None = None,
    supervisor: str = "root",
    at: float = 0.0,
) -> list[events.Event]:
    """`supervisor`'s `children` started in order, then each of `steps`: `"api crash"`
    (an abnormal exit it did not cause), `"api normal"`, `"api stop"` (it stopped api),
    `"api restart"`, `"give-up"`; events `at` seconds, 0.1 s apart."""
    kinds = types or {}
    most = 0 if "give-up" in steps else 2  # (a give-up at the first crash: intensity holds)
    out: list[events.Event] = [
        events.ChildStarted(supervisor, c, 10 + i, at=at) for i, c in enumerate(children)
    ]
    for i, step in enumerate(steps, start=1):
        when = at + 0.1 * i
        if step == "give-up":
            out.append(events.SupervisorGaveUp(supervisor, "gave up", most, 5.0, pid=1, at=when))
            continue
        child, what = step.split()
        if what == "restart":
            out.append(events.ChildRestarted(supervisor, child, 50 + i, 0.01, at=when))
            continue
        out.append(
            events.ChildExited(
                supervisor,
                child,
                10,
                "killed by SIGKILL" if what == "crash" else what,  # (a fault: `life-end` holds)
                kinds.get(child, "permanent"),
                what == "normal",
                what == "stop",
                most,
                5.0,
                strategy,
                children,
                at=when,
            )
        )
    return out


@pytest.mark.parametrize(
    ("strategy", "steps", "types"),
    [
        ("one_for_one", ["api crash", "api restart"], {}),
        ("rest_for_one", ["api crash", "web stop", "api restart", "web restart"], {}),
        ("rest_for_one", ["web crash", "web restart"], {}),  # (nothing started after it)
        (
            "one_for_all",
            ["api crash", "web stop", "db stop", "db restart", "api restart", "web restart"],
            {},
        ),
        (
            "one_for_all",
            ["api crash", "web stop", "db stop", "db restart", "api restart"],
            {"web": "temporary"},
        ),  # a temporary sibling is stopped for good (OTP)
        ("one_for_one", ["api normal"], {"api": "transient"}),  # left down
        ("one_for_one", ["api crash", "api restart"], {"api": "transient"}),
        ("one_for_one", ["api crash"], {"api": "temporary"}),
        (  # a transient sibling that had exited normally comes back with a group (OTP)
            "one_for_all",
            ["web normal", "api crash", "db stop", "db restart", "api restart", "web restart"],
            {"web": "transient"},
        ),
        (  # api's restart failed to start: its exit decides again, the group with it
            "one_for_all",
            [
                "api crash",
                "web stop",
                "db stop",
                "db restart",
                "api crash",
                "db stop",
                "db restart",
                "api restart",
                "web restart",
            ],
            {},
        ),
        ("one_for_all", ["api crash", "web stop", "db stop", "give-up"], {}),
        ("rest_for_one", ["api crash", "web stop", "db stop", "give-up"], {}),  # every child
        ("one_for_all", ["api crash", "web stop", "db stop"], {}),  # a backoff the end cut
        ("one_for_one", ["api crash", "web stop", "db stop"], {}),  # ... and the shutdown
    ],
)
def test_a_decision_that_follows_its_strategy_and_restart_types_holds(
    strategy: str, steps: list[str], types: dict[str, str]
) -> None:
    _holds(_tree(strategy, *steps, types=types))


@pytest.mark.parametrize(
    ("strategy", "steps", "types", "lines"),
    [
        (  # rest_for_one restarting the children started before the failed one
            "rest_for_one",
            ["api crash", "db stop", "db restart", "api restart"],
            {},
            {4, 5},
        ),
        (  # ... the last one: stops that look like a shutdown, but it restarts them
            "rest_for_one",
            ["web crash", "api stop", "db stop", "db restart", "api restart", "web restart"],
            {},
            {4, 5, 6},
        ),
        (  # one_for_all not stopping a sibling
            "one_for_all",
            ["api crash", "web stop", "db restart", "api restart", "web restart"],
            {},
            {4, 5},
        ),
        (  # siblings stopped in start order, not its reverse
            "one_for_all",
            ["api crash", "db stop", "web stop", "db restart", "api restart", "web restart"],
            {},
            {4, 5, 6},
        ),
        (  # the group restarted out of start order
            "one_for_all",
            ["api crash", "web stop", "db stop", "web restart", "db restart", "api restart"],
            {},
            {4, 7},
        ),
        (  # a member of the group never restarted (web: nor did it fail to start)
            "one_for_all",
            ["api crash", "web stop", "db stop", "db restart", "api restart"],
            {},
            {4, 8},
        ),
        ("one_for_one", ["api normal", "api restart"], {"api": "transient"}, {4, 5}),
        ("one_for_one", ["api crash", "api restart"], {"api": "temporary"}, {4, 5}),
        (  # a temporary sibling brought back with its group
            "one_for_all",
            ["api crash", "web stop", "db stop", "db restart", "api restart", "web restart"],
            {"web": "temporary"},
            {5, 9},
        ),
        (  # a give-up that leaves a child running
            "one_for_one",
            ["api crash", "web stop", "give-up"],
            {},
            {4, 5},
        ),
    ],
)
def test_a_decision_against_its_strategy_or_restart_types_is_found(
    strategy: str, steps: list[str], types: dict[str, str], lines: set[int]
) -> None:
    assert lines == _found(_tree(strategy, *steps, types=types), "strategy")


def _later(*steps: str, at: float) -> list[events.Event]:
    """root's `steps` (as `_tree`'s) from `at` seconds on, its children already started."""
    return _tree("one_for_one", *steps, at=at - 0.1)[3:]


def test_a_group_never_restarted_nor_given_up_nor_shut_down_is_found() -> None:
    """The mutant `policy.py:336` (`!=` -> `is`: no restart ever runs) held on `simchain`
    and `crashloop`: a killed permanent child stayed down to the end of the run."""
    due = _supervision_rules.DUE_S
    crashed = _tree("one_for_one", "api crash")  # (api's exit: line 4)
    assert {4} == _found([*crashed, *_later("db crash", "db restart", at=due + 1.0)], "strategy")
    group = _tree("one_for_all", "api crash", "web stop", "db stop")
    late = [events.ChildStarted("other", "x", 99, at=due + 1.0)]  # (the history goes on)
    assert {4} == _found([*group, *late], "strategy")
    escalated = _escalated(_pool_exit(0.5, stopped=False))  # root never restarts the pool
    assert {8} == _found([*escalated, *_later("db crash", "db restart", at=due + 1.0)], "strategy")


def test_a_restart_due_that_a_backoff_delays_or_a_shutdown_cuts_within_its_bound_holds() -> None:
    due = _supervision_rules.DUE_S
    crashed = _tree("one_for_one", "api crash")
    late = [events.ChildStarted("other", "x", 99, at=due + 1.0)]  # (the history goes on)
    _holds([*crashed, *_later("api restart", at=due - 0.5), *late])  # (a backoff)
    _holds([*crashed, *_later("web stop", "db stop", at=due - 0.5), *late])  # a shutdown
    _holds([*_tree("one_for_one", "api crash", "web stop", "db stop"), *late])  # (right after)
    waited = check.check(numbered([*crashed, *late]), backoff_s=1.5)  # (the plan's backoff)
    assert ("held", ()) == (waited.verdict, waited.findings)
    pool = _tree("one_for_all", "worker crash", "cache stop",
                 children=("worker", "cache"), supervisor="pool")  # fmt: skip
    stopped = _pool_exit(due - 0.5, stopped=True)  # (its parent stops it: the tree's shutdown)
    _holds([*pool, stopped, *late])


def test_a_decision_written_before_schema_6_is_not_judged() -> None:
    old = [
        dataclasses.replace(e, strategy="", children=())
        if isinstance(e, events.ChildExited) else e
        for e in _tree("rest_for_one", "api crash", "db stop", "db restart", "api restart")
    ]  # fmt: skip
    _holds(old)


def _escalated(*then: events.Event) -> list[events.Event]:
    """root (db, pool) and pool (worker, cache, one_for_all): worker's crash past pool's
    intensity makes it give up (at 0.2 s); then `then`."""
    pool = _tree("one_for_all", "worker crash", "cache stop", "give-up",
                 children=("worker", "cache"), supervisor="pool")  # fmt: skip
    return [
        events.ChildStarted("root", "db", 10, at=0.0),
        *pool[:2],
        events.ChildStarted("root", "pool", 1, at=0.0),
        *pool[2:],
        *then,
    ]


def _pool_exit(at: float, *, stopped: bool) -> events.ChildExited:
    return events.ChildExited(
        "root", "pool", 1, "gave up", "permanent", True, stopped, 5, 10.0, "one_for_one",
        ("db", "pool"), at=at,
    )  # fmt: skip


def test_a_give_up_its_parent_takes_as_its_childs_exit_holds() -> None:
    _holds(
        _escalated(
            _pool_exit(0.3, stopped=False), events.ChildRestarted("root", "pool", 1, 0.1, at=0.4)
        )
    )
    _holds(_escalated(_pool_exit(0.5, stopped=True)))  # the parent was stopping it
    _holds(_escalated(events.ChildExited("root", "db", 10, "killed", at=0.3)))  # events end


def test_a_give_up_its_parent_never_takes_is_an_escalation_violation() -> None:
    stopped_late = _pool_exit(3.0, stopped=True)  # (at the tree's shutdown)
    assert {7, 8} == _found(_escalated(stopped_late), "escalation")
    later = events.ResourceLoaded("db", "cam", RID, Q1, 0.01, 42, pid=10, seq=1, at=3.0)
    assert {7} == _found(_escalated(later), "escalation")
    restarted = events.ChildRestarted("root", "pool", 1, 0.1, at=0.3)  # (no exit taken)
    assert {7, 8} == _found(_escalated(restarted), "escalation")


def in_doubt_while_held(h: History) -> History | None:
    i = _index(h, events.ConsumerAdded)
    if i is None:
        return None
    added = h[i]
    doubt = events.InDoubt(added.registrar, added.resource_id, "resource", "load", pid=added.pid)
    return [*h[: i + 1], _after(added, doubt), *h[i + 1 :]]


def drop_in_doubt(h: History) -> History | None:
    """A restarted registrar's report of a row its restore listed in doubt is gone, in a
    life that went on after it and never unloaded that resource (rule 16)."""
    for i, e in enumerate(h):
        if type(e) is not events.InDoubt:
            continue
        life = []  # (the rest of its life: up to its registrar's next restore)
        for x in h[i + 1 :]:
            if getattr(x, "registrar", None) != e.registrar:
                continue
            if x.pid != e.pid or type(x) is events.CatalogRestored:
                break
            life.append(x)
        unloaded = any(
            type(x) is events.ResourceUnloaded and x.resource_id == e.query_id for x in life
        )
        if life and not unloaded:
            return _without(h, i)
    return None


def _delivered(h: History) -> list[int]:
    return [i for i, e in enumerate(h) if type(e) is events.StatusDelivered and e.status_id]


def _its_own_way(
    h: History, paths: Callable[[events.StatusDelivered], set[tuple[str, int, str, int]]]
) -> dict[tuple[str, int, str, int, int], list[events.StatusDelivered]]:
    """(sender, pid, holder, pid, hop) -> the deliveries on that path no `Unload`'s answer
    may have carried: none after its id's first release on an `Unload` (as
    `status-reached` reads them)."""
    on_unload: dict[str, int] = {}
    for e in h:
        if type(e) is events.ConsumerReleased and e.reason == "unload":
            on_unload[e.query_id] = min(on_unload.get(e.query_id, e.hlc), e.hlc)
    ways: dict[tuple[str, int, str, int, int], list[events.StatusDelivered]] = {}
    for e in h:
        if type(e) is not events.StatusDelivered or not e.status_id:
            continue
        if on_unload.get(e.query_id, e.hlc + 1) >= e.hlc:
            for path in paths(e):
                ways.setdefault((*path, e.hop), []).append(e)
    return ways


def drop_delivery(h: History) -> History | None:
    """The last hop of a status a provider sent (or a consumer told itself) is lost.

    Not a delivery to a consumer whose id was already released at its provider or
    forgotten, by the lines, when it came (its release crossed the status, or it forgot
    the id some other way: unanswered, told lost): `status-reached` excuses some of
    those (a holder that let its id go before the status's last delivery, but on no
    answer that carried it). The lines of two processes are no causal order, so this may
    take a delivery whose provider released its id first by the stamps: in run 2 of
    `resource` (CI, 2026-11-24) cm released client-3's id after it sent the status on,
    and the answer to client-3's `Unload` carried it (rule 9); `status-reached` now
    expects that one (`crossed()` is that history). Nor one to an id answered after the
    status was sent (by the stamps): `status-reached` owes a status only to a holder that
    held its id from before it was sent (`simslow` sends one every 20 ms: its first
    status reaches ids whose calls were being answered). Nor one whose sender (the
    provider's `StatusSent`, or the delivery at the hop below it climbs from) has no
    event of its own life after it: killed right after, it may have died before the
    notice left, which no line tells from a lost one (`simdoubt` seed 15, and a real run
    of it in CI, 2026-11-25: api killed right after a WARNING reached it at hop 1, its
    climb to client-0 already on its way). Nor the only delivery of its sender's life to
    its registrar's process: it may have waited in the sender for a connection never made
    (a real `simslow` run in CI, 2026-11-26; a restarted holder's new process, `simdoubt`
    seed 58; `status-reached` excuses a sender life that ended soon after). Nor one to an
    id its holder later forgot as `unload unanswered`, when the status reached no other id
    of that registrar at that hop: its sender died with the batch maybe unsent (real
    `simways` runs, 2026-11-27: another process's registrars had it, this one not);
    one that reached another id of it arrived, and is owed (`status-reached`). Only one
    whose sender's way to that registrar took the same status to another id, or a later
    status, that no `Unload`'s answer carried: else it may have waited in a sender killed
    soon after (a real `simways` run in CI, 2026-11-27; `status-reached`'s `_queued`).
    """
    left: set[str] = set()  # ids released at their provider or forgotten so far
    answered = {e.query_id: e.hlc for e in h if type(e) is events.CallAnswered}
    sent = {e.status_id: e.hlc for e in h if type(e) is events.StatusSent}
    last = {(e.registrar, e.pid): i for i, e in enumerate(h) if hasattr(e, "registrar")}
    senders: dict[tuple[str, int], list[int]] = {}  # (status id, hop) -> its senders' lines
    for i, e in enumerate(h):
        if type(e) is events.StatusSent and e.status_id:
            senders.setdefault((e.status_id, 1), []).append(i)
        elif type(e) is events.StatusDelivered and e.status_id:
            senders.setdefault((e.status_id, e.hop + 1), []).append(i)

    def went_on(e: events.StatusDelivered) -> bool:
        lines = senders.get((e.status_id, e.hop), [])
        return all(last[h[j].registrar, h[j].pid] > j for j in lines)  # type: ignore[attr-defined]

    def paths(e: events.StatusDelivered) -> set[tuple[str, int, str, int]]:
        lines = senders.get((e.status_id, e.hop), [])
        return {(h[j].registrar, h[j].pid, e.registrar, e.pid) for j in lines}  # type: ignore[attr-defined]

    reached: dict[tuple[str, int, str, int], int] = {}  # (sender, pid, holder, pid) -> count
    for e in h:
        if type(e) is events.StatusDelivered and e.status_id:
            for path in paths(e):
                reached[path] = reached.get(path, 0) + 1

    unanswered = {
        e.query_id
        for e in h
        if type(e) is events.QueryForgotten and e.reason == "unload unanswered"
    }
    at_hop: dict[tuple[str, str, int], set[str]] = {}  # (status, holder, hop) -> its ids
    for e in h:
        if type(e) is events.StatusDelivered and e.status_id:
            at_hop.setdefault((e.status_id, e.registrar, e.hop), set()).add(e.query_id)

    def alone(e: events.StatusDelivered) -> bool:
        return at_hop[e.status_id, e.registrar, e.hop] == {e.query_id}

    ways = _its_own_way(h, paths)

    def owed(e: events.StatusDelivered) -> bool:
        """Something its sender sent the holder's registrar with it or after it came its own
        way (`status-reached` owes it then: a sender killed right after may have held it)."""
        return any(
            (d.status_id == e.status_id and d.query_id != e.query_id)
            or (e.hop == 1 and sent.get(d.status_id, 0) > sent.get(e.status_id, 0))
            for path in paths(e)
            for d in ways.get((*path, e.hop), ())
        )

    found = []
    for i, e in enumerate(h):
        if type(e) is events.ConsumerReleased or type(e) is events.QueryForgotten:
            left.add(e.query_id)
        elif (
            type(e) is events.StatusDelivered
            and e.status_id
            and e.query_id not in left
            and answered.get(e.query_id, 0) < sent.get(e.status_id, 0)
            and went_on(e)
            and all(reached[path] > 1 for path in paths(e))
            and not (e.query_id in unanswered and alone(e))
            and owed(e)
        ):
            found.append(i)
    if not found:
        return None
    latest = max(found, key=lambda i: (h[i].hop, -i))  # type: ignore[union-attr]
    return _without(h, latest)


def deliver_at_wrong_hop(h: History) -> History | None:
    found = _delivered(h)
    if not found:
        return None
    i = found[0]
    return [*h[:i], dataclasses.replace(h[i], hop=h[i].hop + 1), *h[i + 1 :]]  # type: ignore[union-attr]


def drop_status_sent(h: History) -> History | None:
    """A status delivered that its provider never sent. Not one whose provider's life
    wrote nothing after its deliveries: killed then, its journal's tail (the send among
    it) may be lost, which `status-path` excuses (a real `simslow` run, 2026-11-25)."""
    last = {(e.registrar, e.pid): i for i, e in enumerate(h) if hasattr(e, "registrar")}
    for i, e in enumerate(h):
        if type(e) is not events.StatusSent or not e.status_id:
            continue
        reached = [
            j
            for j, x in enumerate(h)
            if type(x) is events.StatusDelivered and x.status_id == e.status_id
        ]
        if reached and last[e.registrar, e.pid] > max(i, *reached):  # (not the send itself)
            return _without(h, i)
    return None


def answer_early(h: History) -> History | None:
    """A send answered (`StatusAnswered`) before a callback of an id it reached returned.
    Not a callback that returned after its id's release on an `Unload` (`status-answered`
    excuses it: the status may have come on that Unload's answer; a real `simdoubt` run,
    CI 2026-11-28, had only such a callback in its first answer)."""
    handled = {(e.status_id, e.query_id): e.hlc for e in h if type(e) is events.StatusHandled}
    unloaded: dict[str, int] = {}  # query id -> its first release on an Unload
    for e in h:
        if type(e) is events.ConsumerReleased and e.reason == "unload":
            unloaded.setdefault(e.query_id, e.hlc)
    for i, e in enumerate(h):
        if type(e) is not events.StatusAnswered:
            continue
        for query_id in e.reached:
            at = handled.get((e.status_id, query_id))
            if at is not None and unloaded.get(query_id, at) >= at:
                return [*h[:i], dataclasses.replace(e, hlc=at - 1), *h[i + 1 :]]
    return None


def wait_past_patience(h: History) -> History | None:
    """A send answered with an id reached whose callback returned past the send's patience
    (and 0.5 s more): its `StatusHandled` and the answer moved past it, as a runner whose
    watchdog never started leaves it (`simpatient`)."""
    sent = {e.status_id: e for e in h if type(e) is events.StatusSent and e.patience is not None}
    handled = {
        (e.status_id, e.query_id): i for i, e in enumerate(h) if type(e) is events.StatusHandled
    }
    for i, e in enumerate(h):
        if type(e) is not events.StatusAnswered or e.status_id not in sent:
            continue
        send = sent[e.status_id]
        for query_id in e.reached:
            j = handled.get((e.status_id, query_id))
            if j is None or j > i:
                continue
            late = hlc.from_seconds(hlc.seconds(send.hlc) + (send.patience or 0.0) + 1.0)
            later = dataclasses.replace(h[j], hlc=late)
            answer = dataclasses.replace(e, hlc=late + 1)
            rest = [x for k, x in enumerate(h) if k not in (i, j)]
            return [*rest, later, answer]
    return None


def begin_beside(h: History) -> History | None:
    """An id's status callback began as the one that arrived before it began."""
    first: dict[tuple[int, str, str], int] = {}
    for i, e in enumerate(h):
        if type(e) is not events.StatusHandled:
            continue
        j = first.setdefault((e.pid, e.registrar, e.query_id), i)
        earlier = h[j]
        if j != i and earlier.arrived < e.arrived:  # type: ignore[union-attr]
            return [*h[:i], dataclasses.replace(e, began=earlier.began), *h[i + 1 :]]  # type: ignore[union-attr]
    return None


def arrive_as_another(h: History) -> History | None:
    """A status callback numbered at the arrival place of the one of its process before it."""
    last: dict[tuple[str, int], int] = {}
    for i, e in enumerate(h):
        if type(e) is events.ChildExited:
            last.pop((e.host, e.pid), None)
        elif type(e) is events.StatusHandled:
            j = last.setdefault((e.host, e.pid), i)
            if j != i:
                return [*h[:i], dataclasses.replace(e, arrived=h[j].arrived), *h[i + 1 :]]  # type: ignore[union-attr]
    return None


def answer_twice(h: History) -> History | None:
    for i, e in enumerate(h):
        if type(e) is events.CallAnswered and not e.retry:
            return [*h[: i + 1], e, *h[i + 1 :]]
    return None


def drop_add(h: History) -> History | None:
    answered = {e.query_id for e in h if type(e) is events.CallAnswered}
    restored = {r[0] for e in h if type(e) is events.CatalogRestored for r in e.consumers}
    for i, e in enumerate(h):
        if type(e) is events.ConsumerAdded and e.query_id in answered - restored:
            return _without(h, i)
    return None


def drop_forget(h: History) -> History | None:
    for i, e in enumerate(h):
        if type(e) is events.QueryForgotten and _stops_later(h, i):
            return _without(h, i)
    return None


def told_lost_while_held(reason: str) -> Callable[[History], History | None]:
    """A consumer forgets, as lost, an id its provider's life holds (and later releases).
    As `provider lost`, only an id its provider added on the consumer's own host: across
    hosts a cut makes a provider lost while it runs on (rule 19), and the history does
    not show the cuts (`reported-lost` excuses it; in `simhosts` the first answered call
    is api's of db, from host a to host b)."""

    def mutate(h: History) -> History | None:
        released = {e.query_id for e in h if type(e) is events.ConsumerReleased}
        added = {(e.registrar, e.query_id): e.host for e in h if type(e) is events.ConsumerAdded}
        for i, e in enumerate(h):
            if type(e) is not events.CallAnswered or e.query_id not in released:
                continue
            if reason == "provider lost" and (
                not e.host or added.get((e.serving_rr, e.query_id)) != e.host
            ):
                continue  # (across hosts, or hosts not known: excused)
            forgot = events.QueryForgotten(
                e.registrar, e.query_id, e.serving_rr, reason, pid=e.pid, host=e.host
            )
            return [*h[: i + 1], _after(e, forgot), *h[i + 1 :]]
        return None

    return mutate


def release_after_reconcile(h: History) -> History | None:
    """An id a restart without a backup lost, never reported `FATAL`: its consumer forgets
    it on its release instead, which left after its reconcile with the restart was
    answered (issue 51: not a release that crossed the restart)."""
    restoring = {e.registrar for e in h if type(e) is events.CatalogRestored}
    for i, e in enumerate(h):
        if (
            type(e) is events.QueryForgotten
            and e.reason == "unknown at reconcile"
            and e.serving_rr not in restoring
        ):
            released = dataclasses.replace(
                e, reason="unload", unload_sent=e.hlc - 1, reconciled=e.hlc - 2
            )
            fatal = {
                j
                for j, d in enumerate(h)
                if type(d) is events.StatusDelivered
                and d.query_id == e.query_id
                and d.status is rr.Status.FATAL
            }
            return [released if j == i else d for j, d in enumerate(h) if j not in fatal]
    return None


def second_server_to_the_end(h: History) -> History | None:
    """Another process serves a provider's name beside its last process, from that
    process's first event to the end of the run, and never yields (rule 22)."""
    shut = {(e.child, e.pid) for e in h if type(e) is events.ChildExited and e.reason == "shutdown"}
    for i, e in enumerate(h):
        name = getattr(e, "registrar", None)
        if (name, e.pid) not in shut or type(e) is events.StatusDelivered:
            continue
        if any(getattr(x, "registrar", None) == name and x.pid == e.pid for x in h[i + 1 :]):
            return [*h[: i + 1], _fresh(e, pid=e.pid + 100_000), *h[i + 1 :]]
    return None


def release_withdrawn_late(h: History) -> History | None:
    """A provider that releases an id its consumer withdrew (`CallWithdrawn`) only long
    after (its `at` moved 5 s on): what issue 51's lost `Abandon` looked like. 5 s after
    the withdrawal or the release, whichever is later: the rule counts from when that
    life of the provider began to hold the id, which under load (a slow restart that
    restores it, an `Add` queued past its call's timeout) can be more than 4 s after the
    withdrawal, and a release 5 s after the withdrawal but just after that is the prompt
    one `withdrawn` excuses (`simslow` under load; `withdrawn_then_restored`). Not an id
    answered after its last withdrawal: `acall_with_retry`'s next attempt at it was, and
    its release is that answer's, which `withdrawn` rightly does not judge (`killheavy`
    under load). Nor a withdrawn retry of an id its consumer held (answered, not forgotten
    since): it stays held, its release is its holder's (`simwithdraw`)."""
    withdrawn: dict[tuple[str, str], float] = {}  # (consumer, id) -> `at`, if not answered since
    held: set[tuple[str, str]] = set()  # (consumer, id) answered and not forgotten since
    for e in h:
        if type(e) is events.CallWithdrawn and (e.registrar, e.query_id) not in held:
            withdrawn[e.registrar, e.query_id] = e.at
        elif type(e) is events.CallAnswered:
            withdrawn.pop((e.registrar, e.query_id), None)
            held.add((e.registrar, e.query_id))
        elif type(e) is events.QueryForgotten:
            held.discard((e.registrar, e.query_id))
    for i, e in enumerate(h):
        if type(e) is events.ConsumerReleased and (e.consumer, e.query_id) in withdrawn:
            late = dataclasses.replace(e, at=max(e.at, withdrawn[e.consumer, e.query_id]) + 5.0)
            return [*h[:i], late, *h[i + 1 :]]
    return None


def release_ended_dependency_late(h: History) -> History | None:
    """A provider that releases an id of a failed dependency call (a `CallFailed` that may
    have executed, of a `parent` load) only long after that load ended (its `LoadFailed`
    or `ResourceUnloaded`; the release's `at` moved 5 s past the later of the two): an id
    kept for a retry no one can make (`simkeptdep`)."""
    failed: dict[tuple[str, str], str] = {}  # (consumer, id) -> parent, if not answered since
    ended: dict[tuple[str, str], float] = {}  # (consumer, id) -> `at` of its load's end
    for e in h:
        key = (getattr(e, "registrar", ""), getattr(e, "query_id", ""))
        if type(e) is events.CallFailed and e.may_have_executed and e.parent:
            failed[key] = e.parent
        elif type(e) in (events.CallAnswered, events.CallWithdrawn):
            failed.pop(key, None)
            ended.pop(key, None)
        elif type(e) in (events.LoadFailed, events.ResourceUnloaded):
            for (consumer, qid), parent in list(failed.items()):
                if consumer == key[0] and parent == e.resource_id:  # type: ignore[attr-defined]
                    ended[consumer, qid] = e.at
                    del failed[consumer, qid]
        elif type(e) is events.ConsumerReleased and (e.consumer, e.query_id) in ended:
            late = max(e.at, ended[e.consumer, e.query_id]) + 5.0
            i = h.index(e)
            return [*h[:i], dataclasses.replace(e, at=late), *h[i + 1 :]]
    return None


def release_failed_call_at_restore(h: History) -> History | None:
    """A restarted provider that releases, at its first reconcile, an id its consumer's
    call failed on as it died (a `CallFailed` that may have executed, put before its
    restore): the retry that may follow would load afresh (rule 17 case 3)."""
    for i, e in enumerate(h):
        if type(e) is not events.CatalogRestored or not e.consumers:
            continue
        qid, rid, consumer = e.consumers[0][:3]
        pids = [x.pid for x in h[:i] if getattr(x, "registrar", None) == consumer]
        if not pids:
            continue
        failed = events.CallFailed(
            consumer, qid, e.registrar, "cam", "RegistrarUnavailableError", "gone", True,
            pid=pids[-1], seq=1, at=e.at, hlc=e.hlc,
        )  # fmt: skip
        released = events.ConsumerReleased(
            e.registrar, rid, qid, consumer, "reconcile", pid=e.pid, seq=1, at=e.at, hlc=e.hlc
        )
        return [*h[:i], failed, e, released, *h[i + 1 :]]
    return None


def stop_keeps_resource(h: History) -> History | None:
    """A registrar's last stop (the end of the run) lists a resource it loaded, as if its
    unload had left its row. Not after a give-up (its stops keep their rows)."""
    if any(type(e) is events.SupervisorGaveUp for e in h):
        return None
    last = {getattr(e, "registrar", None): i for i, e in enumerate(h)}
    for e in h:
        if (
            type(e) is events.ResourceLoaded
            and type(h[last[e.registrar]]) is events.RegistrarStopped
        ):
            at = last[e.registrar]
            stop = h[at]
            row = (e.resource_id, e.server, "loaded", "", "")
            kept = dataclasses.replace(stop, resources=(*stop.resources, row))  # type: ignore[union-attr]
            return [*h[:at], kept, *h[at + 1 :]]
    return None


def unload_before_dependency(h: History) -> History | None:
    """A resource's unload published before its registrar released one of its
    dependencies (rule 7 the other way round)."""
    parents = {
        (e.registrar, e.query_id): e.parent
        for e in h
        if type(e) is events.CallAnswered and e.parent is not None
    }
    for i, e in enumerate(h):
        if type(e) is not events.QueryForgotten or e.reason != "dependency":
            continue
        rid = parents.get((e.registrar, e.query_id))
        for j in range(i + 1, len(h)):
            later = h[j]
            if type(later) is events.ResourceUnloaded and (later.registrar, later.resource_id) == (
                e.registrar,
                rid,
            ):
                return _moved(h, j, i)
    return None


def forget_dependency_while_held(h: History) -> History | None:
    """A dependency forgotten (its `QueryForgotten`) right after its resource got a
    consumer id, not after the last one was released (rule 7 broken the other way)."""
    parents = {}
    for i, e in enumerate(h):
        if type(e) is events.CallAnswered and e.parent is not None:
            parents[(e.registrar, e.query_id)] = (e.parent, i)
        if type(e) is not events.QueryForgotten or e.reason != "dependency":
            continue
        rid, answered = parents.get((e.registrar, e.query_id), ("", len(h)))
        for j in range(answered + 1, i):
            added = h[j]
            if getattr(added, "registrar", None) == e.registrar and (
                added.pid != e.pid or type(added) is events.CatalogRestored
            ):
                break  # (a life of it began since the answer: its dependency is another's)
            if type(added) is events.ConsumerAdded and (added.registrar, added.resource_id) == (
                e.registrar,
                rid,
            ):
                return _moved(h, i, j + 1)
    return None


def release_before_answer(h: History) -> History | None:
    """A provider's reconcile releases an id whose answer its consumer then records: a
    `ConsumerReleased` of reason `"reconcile"` right after its `ConsumerAdded`, stamped
    just before the `CallAnswered` (its consumer's list left the due call out)."""
    adds = {(e.consumer, e.query_id, e.registrar): i for i, e in enumerate(h)
            if type(e) is events.ConsumerAdded}  # fmt: skip
    for e in h:
        if type(e) is not events.CallAnswered or e.retry:
            continue
        i = adds.get((e.registrar, e.query_id, e.serving_rr))
        if i is None or not h[i].hlc < e.hlc:
            continue
        added = h[i]
        released = events.ConsumerReleased(
            added.registrar, added.resource_id, added.query_id, added.consumer, "reconcile",
            pid=added.pid, seq=added.seq, at=added.at, hlc=e.hlc - 1, host=added.host,
        )  # fmt: skip
        return [*h[: i + 1], released, *h[i + 1 :]]
    return None


def restore_loses_record(h: History) -> History | None:
    """A consumer's restore lacks a client record its life before recorded (its
    `CallAnswered`) and did not forget, nor had its provider released it. A run with no
    such restore (the real runs of 2 s) gets one: a restart right after a consumer's first
    answer restores no client row."""
    return _restore_drops_a_row(h) or _restart_after_an_answer(h)


def _restart_after_an_answer(h: History) -> History | None:
    for i, e in enumerate(h):
        if type(e) is events.CallAnswered and not e.retry:
            restored = events.CatalogRestored(  # (its process: a new one is a second server)
                e.registrar, (), (), (), pid=e.pid, at=e.at, hlc=e.hlc + 1, host=e.host
            )
            return [*h[: i + 1], restored, *h[i + 1 :]]
    return None


def _restore_drops_a_row(h: History) -> History | None:
    held: dict[str, set[str]] = defaultdict(set)
    released = {(e.consumer, e.query_id) for e in h if type(e) is events.ConsumerReleased}
    for i, e in enumerate(h):
        if type(e) is events.CallAnswered:
            held[e.registrar].add(e.query_id)
        elif type(e) is events.QueryForgotten:
            held[e.registrar].discard(e.query_id)
        elif type(e) is events.CatalogRestored:
            for row in e.clients:
                if row[0] in held[e.registrar] and (e.registrar, row[0]) not in released:
                    rows = tuple(r for r in e.clients if r is not row)
                    return [*h[:i], dataclasses.replace(e, clients=rows), *h[i + 1 :]]
            held[e.registrar] = {row[0] for row in e.clients}
    return None


def shed_with_time_left(h: History) -> History | None:
    """A load shed with nothing queued ahead and 3 s left of its callers' timeout, right
    after a load of its server whose loads in that process all took under a second, none
    failed before (a `LoadFailed` of a new id). (CI's `simcancel`: a slow or failed load
    before the first quick one leaves nothing needless to plant there.)"""
    longest: dict[tuple[str, str, int], float] = {}
    failed: set[tuple[str, str, int]] = set()
    for i, e in enumerate(h):
        if type(e) is events.LoadFailed:
            failed.add((e.registrar, e.server, e.pid))
        if type(e) is not events.ResourceLoaded:
            continue
        key = (e.registrar, e.server, e.pid)
        longest[key] = max(longest.get(key, 0.0), e.load_s)
        if longest[key] < 1.0 and key not in failed:
            shed = events.LoadFailed(
                e.registrar, e.server, "f1111111-0000", "f2222222-0000", "DeadlineExceededError",
                f"the load of 'x' at '{e.registrar}/{e.server}' was shed before it started: "
                "3.000 s were left of its callers' timeout, and its loads take 9.000 s lately",
                pid=e.pid, seq=e.seq, at=e.at, hlc=e.hlc, host=e.host,
            )  # fmt: skip
            return [*h[: i + 1], shed, *h[i + 1 :]]
    return None


def drop_give_up(h: History) -> History | None:
    """A supervisor's give-up at an exit past its intensity is not published."""
    i = _index(h, events.SupervisorGaveUp)
    return None if i is None else _without(h, i)


def restart_group_out_of_order(h: History) -> History | None:
    """A group's two restarts swapped: its siblings come back out of start order."""
    decided: dict[tuple[str, str], tuple[str, ...]] = {}  # the group of its last decision
    for i, e in enumerate(h):
        if type(e) is events.ChildExited and not e.stopped:
            group = _supervision_rules.group(e.strategy, e.children, e.child)
            decided[e.host, e.supervisor] = group
        if type(e) is not events.ChildRestarted or len(decided.get((e.host, e.supervisor), ())) < 2:
            continue
        for j in range(i + 1, len(h)):
            later = h[j]
            if (getattr(later, "host", ""), getattr(later, "supervisor", None)) != (
                e.host,
                e.supervisor,
            ):
                continue
            if type(later) is events.ChildRestarted:
                return [*h[:i], later, *h[i + 1 : j], e, *h[j + 1 :]]
            break
    return None


def give_up_unescalated(h: History) -> History | None:
    """A nested supervisor's give-up its parent never takes: its exit there is a stop at
    the end of the run (a shutdown) instead."""
    nested = {(e.host, e.supervisor) for e in h if type(e) is events.SupervisorGaveUp}
    for i, e in enumerate(h):
        if type(e) is events.ChildExited and (e.host, e.child) in nested and not e.stopped:
            at = max(x.at for x in h) + 2 * _supervision_rules.ESCALATED_S
            late = dataclasses.replace(e, stopped=True, reason="shutdown", at=at)
            return [*h[:i], *h[i + 1 :], late]
    return None


def leaves_out_a_held_id(
    kind: type, since: type, provider: str
) -> Callable[[History], History | None]:
    """A fetch's answer (`QueriesFetched`: ids its consumer had answered, `CallAnswered`;
    its provider `serving_rr`) or a provider's listing of its server (`ServerQueriesListed`:
    ids that server had added, `ConsumerAdded`; its provider `registrar`) without an id held
    from before it began until after it (no release, no restart of the provider)."""

    def mutate(h: History) -> History | None:
        stamps = {(e.registrar, e.query_id): e.hlc for e in h if type(e) is since}
        for i, e in enumerate(h):
            if type(e) is not kind:
                continue
            for qid in e.query_ids:
                stamp = stamps.get((e.registrar, qid))
                if stamp is None or stamp >= e.started:
                    continue
                if any(_touches(getattr(e, provider), qid, o, stamp, e.hlc) for o in h):
                    continue
                kept = tuple(q for q in e.query_ids if q != qid)
                return [*h[:i], dataclasses.replace(e, query_ids=kept), *h[i + 1 :]]
        return None

    return mutate


def _touches(provider: str, qid: str, event: events.Event, after: int, before: int) -> bool:
    """Whether `event` (stamped between `after` and `before`) let `qid` go at `provider`,
    or began or ended a life there (a restart, a stop, an exit)."""
    if not after < event.hlc < before:
        return False
    if type(event) is events.ConsumerReleased:
        return event.registrar == provider and event.query_id == qid
    if type(event) in (events.CatalogRestored, events.RegistrarStopped, events.InDoubt):
        return event.registrar.partition("@")[0] == provider  # type: ignore[union-attr]
    return type(event) is events.ChildExited and event.child == provider


def lists_an_unknown_id(kind: type) -> Callable[[History], History | None]:
    """A fetch's answer (`QueriesFetched`) or a provider's listing of its server
    (`ServerQueriesListed`) listing an id nobody ever called."""

    def mutate(h: History) -> History | None:
        for i, e in enumerate(h):
            if type(e) is kind:
                ids = (*e.query_ids, "f0000000-0000-4000-8000-000000000000")
                return [*h[:i], dataclasses.replace(e, query_ids=ids), *h[i + 1 :]]
        return None

    return mutate


def drop_outcome(h: History) -> History | None:
    """A call its provider added (`ConsumerAdded`) whose caller, one process and one life
    that stops cleanly after it and never exits, publishes no answer, error or withdrawal
    of it (a caller the checker reads as restarted within `CALL_BOUND_S` is unjudged)."""
    pids: dict[str, set[int]] = defaultdict(set)
    for e in h:
        if (name := getattr(e, "registrar", None)) is not None:
            pids[name].add(e.pid)
    exited = {e.child for e in h if type(e) is events.ChildExited}
    outcomes = (events.CallAnswered, events.CallFailed, events.CallWithdrawn)
    for i, e in enumerate(h):
        if type(e) is not events.ConsumerAdded or len(pids.get(e.consumer, ())) != 1:
            continue
        caller, qid = e.consumer, e.query_id
        stops = [x for x in h[i + 1 :] if type(x) is events.RegistrarStopped]
        if caller in exited or not any(x.registrar == caller for x in stops):
            continue
        dropped = [
            j
            for j, x in enumerate(h)
            if type(x) in outcomes and (x.registrar, x.query_id) == (caller, qid)
        ]
        if not dropped:
            continue
        mutated = _without(h, *dropped)
        _steps, lives = check.walk(numbered(mutated))
        if (caller, 1) not in lives:  # (one life, as the checker reads it without the outcome)
            return mutated
    return None


def end_by_itself(h: History) -> History | None:
    """A child's exit by a kill (the plan's fault) told as its registrar's own crash."""
    for i, e in enumerate(h):
        if type(e) is events.ChildExited and not e.stopped and e.reason.startswith("killed by"):
            return [*h[:i], dataclasses.replace(e, reason="registrar actor died"), *h[i + 1 :]]
    return None


def refuse_under_share(h: History) -> History | None:
    """A server with room that refused a consumer holding none of its loads, none ahead."""
    for i, e in enumerate(h):
        if type(e) is events.ShareRefused:
            return [*h[:i], dataclasses.replace(e, under_way=0, ahead=0), *h[i + 1 :]]
    return None


def admit_past_share(h: History) -> History | None:
    """A load admitted while others waited, of a consumer holding its share already."""
    for i, e in enumerate(h):
        if type(e) is events.ShareAdmitted:
            held = max(e.pending, e.share + sum(e.waiting))
            return [*h[:i], dataclasses.replace(e, under_way=e.share, pending=held), *h[i + 1 :]]
    return None


def release_lost_for_good(h: History) -> History | None:
    """Each id a restart forgot as `provider lost`, its provider lost for good (a `temporary`
    child's crash, its last event) before that process's first event, told as released
    (`dependency`) instead: the restart never told (the mutant tree.py:527)."""
    lost: dict[str, int] = {}  # provider -> the stamp of its crash, if its last event
    for e in h:
        if type(e) is events.ChildExited and e.restart == "temporary" and not e.stopped:
            lost[e.child] = e.hlc
        elif (name := getattr(e, "registrar", None) or getattr(e, "child", None)) is not None:
            lost.pop(name, None)
    first: dict[tuple[str, int], int] = {}  # (registrar, pid) -> the stamp of its first event
    for e in h:
        if (name := getattr(e, "registrar", None)) is not None:
            first.setdefault((name, e.pid), e.hlc)
    told = {
        i
        for i, e in enumerate(h)
        if type(e) is events.QueryForgotten
        and e.reason == "provider lost"
        and lost.get(e.serving_rr, first[e.registrar, e.pid]) < first[e.registrar, e.pid]
    }
    if not told:
        return None
    return [
        dataclasses.replace(e, reason="dependency") if i in told else e for i, e in enumerate(h)
    ]


MUTATIONS: dict[str, tuple[Callable[[History], History | None], str]] = {
    # name: (the mutation, the rule that must catch it)
    "duplicate-unload": (duplicate(events.ResourceUnloaded), "unload-once"),
    "overloaded-told-twice": (duplicate(events.ServerOverloaded), "overload-paced"),
    "refused-under-share": (refuse_under_share, "share-needed"),
    "admitted-past-share": (admit_past_share, "share-kept"),
    "unload-before-release": (unload_before_release, "unload-once"),
    "drop-last-release": (drop_last_release, "unload-once"),
    "duplicate-release": (duplicate(events.ConsumerReleased), "unload-once"),
    "add-after-unload": (add_after_unload, "unload-once"),
    "drop-unload": (drop_unload, "no-leak"),
    "release-names-other-resource": (release_names_other_resource, "release-match"),
    "add-held-id-elsewhere": (add_held_id_elsewhere, "one-resource"),
    "in-doubt-while-held": (in_doubt_while_held, "in-doubt"),
    "load-equal-twice": (load_equal_twice, "dedup"),
    "serve-before-restore": (serve_before_restore, "restore-first"),
    "restore-loses-id": (restore_loses_id, "kept"),
    "duplicate-delivery": (duplicate(events.StatusDelivered), "status-once"),
    "drop-delivery": (drop_delivery, "status-reached"),
    "deliver-at-wrong-hop": (deliver_at_wrong_hop, "status-path"),
    "drop-status-sent": (drop_status_sent, "status-path"),
    "begin-beside": (begin_beside, "status-order"),
    "arrive-as-another": (arrive_as_another, "status-order"),
    "answer-early": (answer_early, "status-answered"),
    "wait-past-patience": (wait_past_patience, "status-patient"),
    "answer-twice": (answer_twice, "answered"),
    "drop-add": (drop_add, "answered"),
    "drop-forget": (drop_forget, "answered"),
    "release-before-answer": (release_before_answer, "answer-released"),
    "restore-loses-record": (restore_loses_record, "record-kept"),
    "shed-with-time-left": (shed_with_time_left, "shed-needed"),
    "unknown-at-reconcile-while-held": (
        told_lost_while_held("unknown at reconcile"),
        "reported-lost",
    ),
    "provider-lost-while-alive": (told_lost_while_held("provider lost"), "reported-lost"),
    "release-unpublished": (release_unpublished, "kept"),
    "release-after-reconcile": (release_after_reconcile, "kept"),
    "provider-keeps-id": (provider_keeps_id, "end"),
    "second-server-to-the-end": (second_server_to_the_end, "one-name"),
    "release-withdrawn-late": (release_withdrawn_late, "withdrawn"),
    "release-ended-dependency-late": (release_ended_dependency_late, "retry-ended"),
    "release-failed-call-at-restore": (release_failed_call_at_restore, "retry-kept"),
    "stop-keeps-resource": (stop_keeps_resource, "left"),
    "unload-before-dependency": (unload_before_dependency, "unload-order"),
    "forget-dependency-while-held": (forget_dependency_while_held, "dependency-held"),
    "drop-in-doubt": (drop_in_doubt, "doubt-reported"),
    "drop-give-up": (drop_give_up, "intensity"),
    "restart-group-out-of-order": (restart_group_out_of_order, "strategy"),
    "give-up-unescalated": (give_up_unescalated, "escalation"),
    "fetch-leaves-out-a-held-id": (
        leaves_out_a_held_id(events.QueriesFetched, events.CallAnswered, "serving_rr"),
        "fetch",
    ),
    "fetch-lists-an-unknown-id": (lists_an_unknown_id(events.QueriesFetched), "fetch"),
    "listing-leaves-out-a-held-id": (
        leaves_out_a_held_id(events.ServerQueriesListed, events.ConsumerAdded, "registrar"),
        "fetch",
    ),
    "listing-lists-an-unknown-id": (lists_an_unknown_id(events.ServerQueriesListed), "fetch"),
    "drop-outcome": (drop_outcome, "outcome"),
    "end-by-itself": (end_by_itself, "life-end"),
    "release-lost-for-good": (release_lost_for_good, "gone-told"),
}


SHORT = {"killheavy": 3.0}
"""Seconds per run of each shipped plan here (2 s for the others): a few kills each."""

ROOT_ONLY = {"leases", "simhosts"}
"""Shipped plans these tests do not run: `leases` and `simhosts` (`[hosts]`) need root,
network namespaces and minutes (tests/experiments/test_hosts.py runs a small plan of
their shape; test_simulate.py runs `simhosts` on the simulation)."""

SIMULATION_ONLY = {
    "simheal",
    "simrest",
    "simprogram",
    "simcommit",
    "simanswer",
    "simpatient",
    "simbackup",
    "simwithdraw",
}
"""Shipped plans of a fault kind only the simulation injects (`split_brain`,
`kill_in_setup`, `kill_program`, `kill_before_commit`, `corrupt_backup`), and `simanswer`,
timed for it (a 20 ms callback within a 30 ms patience; `status-answered` is judged in the
real runs of the others), and `simpatient` (a status every 3 s: none in a 2 s run;
`status-patient` is judged in the real runs of the others), and `simwithdraw`, timed
for it (0.5 s timeouts, which a loaded machine's real run misses for most calls): their
histories are checked in tests/experiments/test_simulate.py."""


@pytest.fixture(scope="module")
def shipped_files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Real runs of every shipped plan (one repeat, shortened): each one's `events.jsonl`
    (kept in pytest's base temporary folder, the last three sessions' kept). Each plan runs
    once: a killed process's numbers that no event took are told (`EventsUnpublished`),
    not lost (4 of 129 real `simways` runs at load 6-30 were `unverifiable` before).
    A mutation needs its shape in some run: `nobackup` gives the give-up (`drop-give-up`,
    `give-up-unescalated`) and the id a restart without a backup lost
    (`release-after-reconcile`) in every run; `crashloop` and `simnostate`, timed kills
    under load, had none in some real runs (CI at 82548e2b, load 40-70 here)."""
    files = {}
    for name in sorted(set(plans.shipped()) - ROOT_ONLY - SIMULATION_ONLY):
        out = tmp_path_factory.mktemp(name)
        run(load_plan(plans.find(name)), out=out, repeat=1, duration=SHORT.get(name, 2.0))
        files[name] = out / "events.jsonl"
    return files


def _heard_from_start(name: str) -> bool:
    """`check`'s `heard_from_start` for shipped plan `name` (its `listen`)."""
    return load_plan(plans.find(name)).listen == "before_start"


@pytest.fixture(scope="module")
def shipped(shipped_files: dict[str, Path]) -> dict[str, dict[int, list[check.Line]]]:
    """The histories of `shipped_files`."""
    return {
        name: check.read_runs(path.read_text().splitlines()) for name, path in shipped_files.items()
    }


@pytest.mark.timeout(900)
def test_the_shipped_plans_real_runs_hold(
    shipped: dict[str, dict[int, list[check.Line]]], shipped_files: dict[str, Path]
) -> None:
    verdicts = {
        (name, number): check.check(history, heard_from_start=_heard_from_start(name))
        for name, runs in shipped.items()
        for number, history in runs.items()
    }
    assert set(plans.shipped()) - ROOT_ONLY - SIMULATION_ONLY == {name for name, _ in verdicts}
    broken = {
        key: found
        for key, v in verdicts.items()
        if v.verdict != "held"
        and (found := tuple(f for f in v.findings if not _known_gap(key[0], f)))
    }
    # (a real run's failure is seldom seen twice: the message names each broken history)
    kept = sorted({str(shipped_files[name]) for name, _ in broken})
    assert {} == broken, f"histories kept: {kept}"


def _known_gap(plan: str, finding: check.Finding) -> bool:
    """A finding of a runtime gap seen in real runs only, open in issue 68 (each its reason):
    in a real `crashloop` run (CI of 2026-11-29, and once under load before), db still held
    ids of the worker when the root's give-up stopped it, the worker lost for good in the
    pool's give-up just before (`end`, widened on 2026-11-28 to consumers lost for good).
    The root's give-up tells db the pool's managers are lost before db's `Stop`
    (`Ending.lost`), yet db released nothing. A likely cause (read, not traced): db's
    `Life.lose` defers the release while the worker's name is still in its process's
    directory (rule 22's namesake check), asking it for a `Reconcile`, and its `Stop` comes
    first. No simulated seed reaches it (1-200, the root at 0 restarts). Every other finding
    still fails."""
    return plan == "crashloop" and finding.rule == "end" and "lost for good" in finding.message


def test_a_status_whose_send_died_with_its_killed_provider_is_on_its_path() -> None:
    """A real `simslow` run (2026-11-25, load 14): db, restarted, listed its queries and
    sent a WARNING that reached client-3's ids at hop 1, and was SIGKILLed; its
    `StatusSent`, the tail of its journal, was not in the file. A life that wrote nothing
    after the deliveries and exited may have lost it: not off the path. One that wrote
    on after them did send it, or nothing did."""
    h = clean()
    killed = [*h[:4], *h[5:7], events.ChildExited("sup", "erm", P, "killed by SIGKILL")]
    found = check.check(numbered(renumbered(killed))).findings
    assert [] == [f for f in found if f.rule == "status-path"]
    went_on = [*h[:4], *h[5:]]
    found = check.check(numbered(renumbered(went_on))).findings
    assert ["status-path", "status-path"] == [f.rule for f in found if f.rule == "status-path"]


@pytest.mark.timeout(300)  # (a whole simdoubt run: 3 s alone, over 60 s at a load of 75)
def test_drop_delivery_leaves_a_status_whose_sender_was_killed_right_after_it_sent_it_on() -> None:
    """`simdoubt` seed 27 (13 before a restart was told only to the manager processes
    that monitor it, 15 before announced restarts): a registrar (api) is
    killed right after a status reaches it at hop 1 (its last line), its climb already on
    its way. That delivery lost reads as one it never sent (`status-reached` excuses it):
    `drop_delivery` takes another."""
    run = simulate.run_seed(load_plan(plans.find("simdoubt")), 27)
    (history,) = check.read_runs(run.history.splitlines()).values()
    h = [event for _, event in history]
    last = {(e.registrar, e.pid): i for i, e in enumerate(h) if hasattr(e, "registrar")}
    climbs = [
        (i, e)
        for i, e in enumerate(h)
        if type(e) is events.StatusDelivered and e.hop == 1 and last[e.registrar, e.pid] == i
    ]
    assert climbs, "seed 27 no longer kills a registrar right after a status reached it"
    mutated = drop_delivery(h)
    assert mutated is not None
    verdict = check.check(numbered(renumbered(mutated)))
    assert "status-reached" in {f.rule for f in verdict.findings if f.kind == "violation"}


def test_provider_lost_while_alive_takes_a_call_its_provider_holds_on_the_callers_host() -> None:
    """`simhosts`: its first answered call is api's (host a) of db (host b); told lost
    across hosts is what a cut shows (`reported-lost` excuses it). The mutation takes the
    first call of a provider on its caller's host: app's of cm, not cm's of erm."""
    h = [
        dataclasses.replace(e, host="b") if getattr(e, "registrar", "") == "erm" else e
        for e in _stamped(with_paths())
    ]
    mutate, rule = MUTATIONS["provider-lost-while-alive"]
    mutated = mutate(h)
    assert mutated is not None
    (forgot,) = (
        e for e in mutated if type(e) is events.QueryForgotten and e.reason == "provider lost"
    )
    assert ("app", "cm") == (forgot.registrar, forgot.serving_rr)
    verdict = check.check(numbered(renumbered(mutated)))
    assert rule in {f.rule for f in verdict.findings if f.kind == "violation"}


def test_release_withdrawn_late_is_late_after_the_life_that_restored_the_id_began() -> None:
    """Issue 51's shape: erm restored Q1 10 s after cm withdrew it and released it at
    the reconcile. Its release moved to 5 s after the withdrawal is still before the
    restore (`withdrawn` rightly excuses it); the mutation moves it 5 s after the release."""
    history = withdrawn_then_restored(released_after=0.01)
    assert "held" == check.check(numbered(history)).verdict
    mutate, rule = MUTATIONS["release-withdrawn-late"]
    mutated = mutate(history)
    assert mutated is not None
    verdict = check.check(numbered(renumbered(mutated)))
    assert rule in {f.rule for f in verdict.findings if f.kind == "violation"}


def test_release_withdrawn_late_takes_no_id_a_retry_answered_again() -> None:
    """A real `killheavy` run (2026-11-28, load 16): client-1's attempt at its id timed out
    (`CallWithdrawn`) while edge restarted, before edge held it; `acall_with_retry`'s next
    attempt at that id was answered, and edge released it at client-1's unload. Answered
    again, the id is held by that answer (`withdrawn` rightly does not judge its release):
    the mutation takes Q2's release, withdrawn and never answered, not Q1's, before it."""
    history = [
        events.CatalogRestored("erm", (), (), (), pid=P, seq=1, at=10.0),
        events.CallWithdrawn("cm", Q1, "erm", "cam", "timeout", pid=C, at=10.1),
        events.ResourceLoaded("erm", "cam", RID, Q1, 0.01, 42, "cam 0", pid=P, seq=2, at=12.0),
        events.ConsumerAdded("erm", RID, Q1, "cm", pid=P, seq=3, at=12.0),
        events.CallAnswered("cm", Q1, "erm", "cam", pid=C, at=12.01),
        events.ConsumerReleased("erm", RID, Q1, "cm", pid=P, seq=4, at=12.2),
        events.ResourceUnloaded("erm", "cam", RID, pid=P, seq=5, at=12.2),
        events.QueryForgotten("cm", Q1, "erm", "unload", pid=C, at=12.21),
        events.ResourceLoaded("erm", "cam", RID2, Q2, 0.01, 42, "cam 0", pid=P, seq=6, at=13.0),
        events.ConsumerAdded("erm", RID2, Q2, "cm", pid=P, seq=7, at=13.0),
        events.CallWithdrawn("cm", Q2, "erm", "cam", "interrupted", pid=C, at=13.001),
        events.ConsumerReleased("erm", RID2, Q2, "cm", "abandoned", pid=P, seq=8, at=13.01),
        events.ResourceUnloaded("erm", "cam", RID2, pid=P, seq=9, at=13.01),
        events.RegistrarStopped("cm", (), (), (), pid=C, at=14.0),
        events.RegistrarStopped("erm", (), (), (), pid=P, seq=10, at=14.0),
    ]
    assert "held" == check.check(numbered(history)).verdict
    mutate, rule = MUTATIONS["release-withdrawn-late"]
    mutated = mutate(history)
    assert mutated is not None
    (late,) = (e for e, was in zip(mutated, history, strict=True) if e != was)
    assert (Q2, pytest.approx(18.01)) == (late.query_id, late.at)  # type: ignore[attr-defined]
    verdict = check.check(numbered(renumbered(mutated)))
    assert rule in {f.rule for f in verdict.findings if f.kind == "violation"}


def test_restore_loses_id_takes_no_row_of_a_consumer_killed_before_the_restore() -> None:
    """`simprogram` (seeds 6, 7, 9, 11): a client, without a backup, killed with the
    program before the restore; its row's loss is excused (`kept`: its release's events
    may be lost with it, nobody holds the id). The mutation takes app's row instead."""
    h = clean()
    restored = events.CatalogRestored(
        "erm",
        ((RID, "cam", "loaded", "42"),),
        ((Q1, RID, "cm"), (Q2, RID, "app")),
        (),
        (1, 2, 0),
        pid=P + 1,
    )
    history = _stamped(
        [
            *h[:3],
            events.ConsumerAdded("erm", RID, Q2, "app", pid=P),
            events.CallAnswered("cm", Q1, "erm", "cam", pid=C),
            events.CallAnswered("app", Q2, "erm", "cam", pid=A),
            restored,
            events.RegistrarStopped("cm", (), (), (), pid=C + 2),  # (cm's next life)
        ]
    )
    mutate, rule = MUTATIONS["restore-loses-id"]
    mutated = mutate(history)
    assert mutated is not None
    (restore,) = (e for e in mutated if type(e) is events.CatalogRestored and e.pid == P + 1)
    assert ((Q1, RID, "cm"),) == restore.consumers
    verdict = check.check(numbered(renumbered(mutated)))
    assert rule in {f.rule for f in verdict.findings if f.kind == "violation"}


def test_shed_with_time_left_plants_after_a_server_whose_loads_there_are_all_known() -> None:
    """CI's `simcancel` (stop 75): a cancelled load of cam before its quick ones leaves
    cam's load time unknown in that process, so a shed planted there is not judged. The
    mutation plants it after lidar's quick load instead."""
    cancelled = events.LoadFailed(
        "erm", "cam", "r0000000-0000", "q0000000-0000", "CancelledError", "cancelled", pid=P
    )
    lidar = events.ResourceLoaded("erm", "lidar", "r3333333-0000", Q2, 0.02, 43, "l", pid=P)
    history = _stamped([clean()[0], cancelled, *clean()[1:-1], lidar, clean()[-1]])
    assert "held" == check.check(numbered(history)).verdict
    mutate, rule = MUTATIONS["shed-with-time-left"]
    mutated = mutate(history)
    assert mutated is not None
    shed = next(e for e in mutated if type(e) is events.LoadFailed and e.query_id.startswith("f2"))
    assert "lidar" == shed.server
    verdict = check.check(numbered(renumbered(mutated)))
    assert rule in {f.rule for f in verdict.findings if f.kind == "violation"}


def test_answer_early_takes_no_callback_that_returned_after_its_id_s_release_on_an_unload() -> None:
    """A real `simdoubt` run (CI, 2026-11-28): db's first answered send reached one id, whose
    callback returned after db released that id on an Unload; `status-answered` excuses it
    (the status may have come on the Unload's answer), so the answer moved before it broke
    nothing. The mutation takes the next callback the rule judges, or none."""
    h = _answered(70, gave_up=(Q2,))  # (Q1's s2 callback returned at 20, line 11)
    i = next(i for i, e in enumerate(h) if type(e) is events.ConsumerReleased and e.query_id == Q1)
    released = [*h[:i], dataclasses.replace(h[i], hlc=10_015), *h[i + 1 :]]  # (before 20)
    _holds(released)
    mutate, rule = MUTATIONS["answer-early"]
    assert mutate(released) is None
    mutated = mutate(h)  # (its release after the callback returned: judged)
    assert mutated is not None
    verdict = check.check(numbered(renumbered(mutated)))
    assert rule in {f.rule for f in verdict.findings if f.kind == "violation"}


SIMULATED_SHAPES = {
    "release-ended-dependency-late": "simkeptdep",
    "release-lost-for-good": "simgone",
}
"""Mutations whose shape a short real run does not always have, each with the plan whose
simulated seed 1 has it every time: a SIGKILL of api inside one of its 50 ms loads with
front's call in flight (2 of 3 real `simkeptdep` runs of 2 s had none, 2026-11-28); a
manager restarted after a provider it held ids at was lost for good (`simgone`'s timing)."""


@pytest.mark.timeout(900)
@pytest.mark.parametrize("mutation", sorted(set(MUTATIONS) - set(SIMULATED_SHAPES)))
def test_each_mutation_of_the_shipped_plans_real_runs_is_caught_by_its_rule(
    shipped: dict[str, dict[int, list[check.Line]]], mutation: str
) -> None:
    mutate, rule = MUTATIONS[mutation]
    caught, missed = [], []
    for name, runs in shipped.items():
        heard = _heard_from_start(name)
        for number, history in runs.items():
            mutated = mutate([event for _, event in history])
            if mutated is None:
                continue  # (nothing of its kind in this run: no status, no restore, ...)
            verdict = check.check(numbered(renumbered(mutated)), heard_from_start=heard)
            rules = {f.rule for f in verdict.findings if f.kind == "violation"}
            (caught if rule in rules else missed).append((name, number, sorted(rules)))
    assert caught, f"{mutation} applies to no run of the shipped plans"
    assert [] == missed


@pytest.mark.parametrize("mutation", sorted(SIMULATED_SHAPES))
def test_each_mutation_real_runs_may_lack_is_caught_on_its_plans_simulated_seed(
    mutation: str,
) -> None:
    mutate, rule = MUTATIONS[mutation]
    run = simulate.run_seed(load_plan(plans.find(SIMULATED_SHAPES[mutation])), 1)
    assert "held" == run.verdict
    (history,) = check.read_runs(run.history.splitlines()).values()
    mutated = mutate([event for _, event in history])
    assert mutated is not None, f"{mutation} applies to no part of the simulated seed"
    verdict = check.check(numbered(renumbered(mutated)))
    assert rule in {f.rule for f in verdict.findings if f.kind == "violation"}


@pytest.mark.parametrize("seed", [37, 147])
def test_a_release_after_reconcile_is_caught_on_simnostate_s_seeds_that_once_hid_it(
    seed: int,
) -> None:
    """Its real runs' shapes (CI, 2026-11-28): the lost id's consumer had a retry of it fail
    as its provider died (37), or was killed long after forgetting it (147); `kept` took
    both for ids their consumer let go of."""
    run = simulate.run_seed(load_plan(plans.find("simnostate")), seed)
    assert "held" == run.verdict
    (history,) = check.read_runs(run.history.splitlines()).values()
    mutate, rule = MUTATIONS["release-after-reconcile"]
    mutated = mutate([event for _, event in history])
    assert mutated is not None
    verdict = check.check(numbered(renumbered(mutated)))
    assert rule in {f.rule for f in verdict.findings if f.kind == "violation"}


SWEEP = pytest.mark.timeout(300)
"""A few seeds take a few CPU seconds; under load several times that."""

MUTATED_ON_THE_SIMULATION = {
    "simanswer", "simbackup", "simcommit", "simheal", "simhosts", "simpatient", "simprogram",
    "simrest", "simwithdraw",
}  # fmt: skip
"""The shipped plans the real runs above leave out that the simulation runs (not `leases`:
it freezes a host's router, which the simulated hosts have none of)."""

MUTATION_SEEDS = (1, 2, 6)
"""Their seeds each mutation is applied to (6: `simprogram` restores a row of a client
killed with the program, which `restore_loses_id` once took)."""


def test_the_plans_left_out_of_the_real_runs_are_mutated_on_the_simulation_if_simulable() -> None:
    simulable = set()
    for name in ROOT_ONLY | SIMULATION_ONLY:
        try:
            simulate.check_simulable(load_plan(plans.find(name)))
        except PlanError:
            continue
        simulable.add(name)
    assert MUTATED_ON_THE_SIMULATION == simulable


@SWEEP
@pytest.mark.parametrize("name", sorted(MUTATED_ON_THE_SIMULATION))
def test_each_mutation_of_a_simulated_plan_left_out_of_the_real_runs_is_caught_by_its_rule(
    name: str,
) -> None:
    """Deterministic: a seed's history is the same each time, so a gap reopened in a rule
    (or a mutation that takes a case its rule excuses) fails this every time."""
    plan = load_plan(plans.find(name))
    caught: set[str] = set()
    missed: list[tuple[int, int, str, list[str]]] = []
    for seed in MUTATION_SEEDS:
        result = simulate.run_seed(plan, seed)
        assert "held" == result.verdict, (seed, result.verdict)
        for number, history in check.read_runs(result.history.splitlines()).items():
            for mutation, (mutate, rule) in sorted(MUTATIONS.items()):
                mutated = mutate([event for _, event in history])
                if mutated is None:
                    continue
                verdict = check.check(numbered(renumbered(mutated)))
                rules = {f.rule for f in verdict.findings if f.kind == "violation"}
                if rule in rules:
                    caught.add(mutation)
                else:
                    missed.append((seed, number, mutation, sorted(rules)))
    assert caught
    assert [] == missed


def test_every_rule_but_the_events_rule_has_a_mutation() -> None:
    # (`events`, a loss, is not a broken rule: the mutations renumber to show none;
    # `kept-unclaimed` needs its consumers' `call_timeout`, which no event carries: judged
    # on the simulation only, its planted history is test_an_id_kept_for_a_retry_that_...;
    # `damaged-backup` the backups a fault damaged, which no event shows: its planted
    # histories are test_a_damaged_backup_...; `timed-out` its consumers' timeouts too:
    # test_a_call_withdrawn_at_a_timeout_before_its_call_timeout_...; `client-stopped` the
    # plan's clients' names: test_a_client_its_tree_did_not_stop_is_a_client_stopped_...;
    # `backup-readable` the backups a run left, which no event shows:
    # test_a_backup_the_run_left_unreadable_...)
    kept_out = {
        "events",
        "kept-unclaimed",
        "damaged-backup",
        "timed-out",
        "client-stopped",
        "backup-readable",
    }
    assert set(check.RULES) - kept_out == {rule for _, rule in MUTATIONS.values()}


def test_check_of_a_simulations_output_points_to_its_seeds_and_replay(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A new user ran `rr-actors check` on an `experiment --simulate` folder (it has
    `seeds.jsonl`, no `events.jsonl`): the error says where the verdicts are."""
    (tmp_path / "seeds.jsonl").write_text('{"seed": 1}\n', encoding="utf-8")

    assert 2 == main(["check", str(tmp_path)])

    err = capsys.readouterr().err
    assert f"no events.jsonl at {tmp_path}: it is a simulation's output; its seeds.jsonl" in err
    assert f"`rr-actors replay {tmp_path} --seed S` re-runs one" in err


def _gone_while_down(*forgotten: str) -> list[events.Event]:
    """sensor (a manager) killed, then feed, a `temporary` provider it held Q1 and Q2 at,
    lost for good while sensor was down; sensor's restart restores both ids, forgets them
    as `forgotten` says, and stops."""
    sensor, feed = 300, 400
    rows = ((Q1, "feed", "resource", ""), (Q2, "feed", "resource", ""))
    return [
        events.CatalogRestored("feed", (), (), (), pid=feed, seq=1),
        events.CatalogRestored("sensor", (), (), rows, pid=sensor, seq=1),
        events.ChildExited("sup", "sensor", sensor, "killed by SIGKILL", restart="permanent"),
        events.ChildExited("sup", "feed", feed, "killed by SIGKILL", restart="temporary"),
        events.CatalogRestored("sensor", (), (), rows, pid=sensor + 1, seq=1),
        *(
            events.QueryForgotten("sensor", qid, "feed", reason, pid=sensor + 1, seq=n)
            for n, (qid, reason) in enumerate(zip((Q1, Q2), forgotten, strict=True), start=2)
        ),
        events.RegistrarStopped("sensor", (), (), (), pid=sensor + 1, seq=4),
    ]


def test_a_restart_never_told_its_provider_was_lost_for_good_is_a_gone_told_violation() -> None:
    """The mutant tree.py:527 (`gone <= name`: feed is not told to sensor, whose name sorts
    after it): sensor's restart releases its ids at feed as its clients let go, and is
    never told `FATAL` (`simgone`)."""
    found = _of_rule(_gone_while_down("dependency", "dependency"), "gone-told")
    assert [("violation", (4, 6, 7))] == [(f.kind, f.lines) for f in found]


@pytest.mark.parametrize(
    "forgotten",
    [
        ("provider lost", "provider lost"),
        ("dependency", "provider lost"),
        ("in doubt", "withdrawn"),
    ],
)
def test_a_restart_told_its_provider_was_lost_holds_gone_told(forgotten: tuple[str, str]) -> None:
    """Told: both forgotten as `provider lost`, or one released before the telling arrived
    (a race); an id settled in doubt at the restore, or withdrawn, is no release."""
    assert [] == _of_rule(_gone_while_down(*forgotten), "gone-told")


def test_a_release_at_a_provider_lost_after_the_life_began_is_not_judged_by_gone_told() -> None:
    """feed lost for good while sensor's restart runs: the death watch tells it as it tells
    every living registrar, which `gone-told` does not judge."""
    history = _gone_while_down("dependency", "dependency")
    exited = history.pop(3)
    history.insert(4, dataclasses.replace(exited, hlc=history[3].hlc + 1))  # (after it began)
    assert [] == _of_rule(history, "gone-told")


def test_a_client_its_tree_did_not_stop_is_a_client_stopped_violation() -> None:
    """The mutant supervisor.py:323 (`Supervisor.stop` stops none of the registrars
    `Supervisor.registrar` started): the client's last life has no `RegistrarStopped`
    (`simstop`); a consumer of no plan (not in `timeouts`) is not judged."""
    h = clean()
    assert isinstance(h[-2], events.RegistrarStopped)
    assert "cm" == h[-2].registrar
    unstopped = numbered([*h[:-2], h[-1]])
    found = check.check(unstopped, timeouts={"cm": 1.0}).findings
    assert [("client-stopped", (7,))] == [(f.rule, f.lines) for f in found]  # (its last event)
    assert "held" == check.check(numbered(h), timeouts={"cm": 1.0}).verdict
    assert "held" == check.check(unstopped).verdict
