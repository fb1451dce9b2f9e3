"""rr_actors.experiments.check: a clean history holds; one seeded violation of each rule is
found, with the lines that show it; mutations of a real history are found too."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import rr_actors as rr
from rr_actors import events
from rr_actors.__main__ import main
from rr_actors.experiments import check

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
        "held": (restarted, {4, 5}),
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
    ["held", "unload-once", "dedup", "restore-first", "status-once", "status-path", "end"],
)
def test_one_seeded_violation_of_each_rule_is_found_with_its_window(rule: str) -> None:
    history, window = _seeded()[rule]
    verdict = check.check(numbered(history))
    assert "violated" == verdict.verdict
    found = [f for f in verdict.findings if f.rule == rule]
    assert found, verdict.findings
    assert window == set(found[0].lines)


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


def test_a_lost_id_reported_fatal_holds() -> None:
    history, _ = _seeded()["held"]
    answered = events.CallAnswered("cm", Q2, "erm", "cam", pid=C)
    fatal = events.StatusDelivered("cm", Q2, rr.Status.FATAL, 1, 0.0, "s9", pid=C)
    forgotten = events.QueryForgotten("cm", Q2, "erm", "unknown at reconcile", pid=C)
    assert "held" == check.check(numbered([*history, answered, fatal, forgotten])).verdict


def test_an_id_its_consumer_forgot_before_a_restore_lost_it_holds() -> None:
    # the provider committed the release and was killed before it published it
    history, _ = _seeded()["held"]
    answered = events.CallAnswered("cm", Q2, "erm", "cam", pid=C)
    forgotten = events.QueryForgotten("cm", Q2, "erm", "unload", pid=C)
    let_go = [*history[:4], answered, forgotten, *history[4:]]
    assert "held" == check.check(numbered(let_go)).verdict
    late = [*history[:4], answered, *history[4:], forgotten]  # forgotten after: lost
    assert ["held"] == [f.rule for f in check.check(numbered(late)).findings]


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
    verdict = check.check(numbered(with_paths()))
    assert ("held", ()) == (verdict.verdict, verdict.findings)


def _found(history: list[events.Event], rule: str) -> set[int]:
    verdict = check.check(numbered(history))
    assert "violated" == verdict.verdict
    found = [f for f in verdict.findings if f.rule == rule and f.kind == "violation"]
    assert found, verdict.findings
    return set(found[0].lines)


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
    assert "held" == check.check(numbered([*_without(h, 7, 11), listed])).verdict


def test_an_id_forgotten_that_was_not_held_is_found() -> None:
    h = with_paths()
    again = events.QueryForgotten("app", Q2, "cm", "unload", pid=A)
    assert {9} == _found([*h[:8], again, *h[8:]], "answered")


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


def test_rr_actors_check_reads_a_schema_2_file_as_a_schema_3_one(
    real: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A run written before events had `host` and `hlc` (schema 2) checks as it did."""
    old = []
    for text in real:
        line = json.loads(text)
        assert 3 == line.pop("schema")
        del line["host"], line["hlc"]
        old.append(json.dumps({**line, "schema": 2}))
    for name, lines in (("new", real), ("old", old)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "events.jsonl").write_text("\n".join(lines) + "\n")
        assert 0 == main(["check", str(tmp_path / name), "-q"])
        assert "run 0: held" in capsys.readouterr().out
