"""rr_actors.experiments.check: a clean history holds; one seeded violation of each rule is
found, with the lines that show it; mutations of a real history are found too."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import rr_actors as rr
from rr_actors import events
from rr_actors._cli import main
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
        "end": ([*h[:8], h[14]], {4, 9}),  # Q2 never released; its consumer stopped
    }


@pytest.mark.parametrize(
    "rule", ["held", "unload-once", "dedup", "restore-first", "status-once", "end"]
)
def test_one_seeded_violation_of_each_rule_is_found_with_its_window(rule: str) -> None:
    history, window = _seeded()[rule]
    verdict = check.check(numbered(history))
    assert "violated" == verdict.verdict
    found = [f for f in verdict.findings if f.rule == rule]
    assert found, verdict.findings
    assert window == set(found[0].lines)


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
    fatal = events.StatusDelivered("cm", Q2, rr.Status.FATAL, 1, 0.0, "s9", pid=C)
    assert "held" == check.check(numbered([*history, fatal])).verdict


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
