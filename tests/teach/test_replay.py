"""A simulated seed replayed step by step (`rr_actors_lab.teach.replay`): what each step shows
is what the run's events say (the tree, the catalogs, what is in flight, the story), and
the observer's page in a real chromium (Playwright) plays, pauses, steps, steps back and
scrubs to an event; live, a manager's kill and cut run the seed again with that fault.
The screenshot goes to `docs/img/` with `RR_DOCS_SCREENSHOTS=1`."""

from __future__ import annotations

import json
import os
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from rr_actors import events
from rr_actors.errors import ConfigError
from rr_actors_lab.teach import grade, kit, replay
from tests.support.observing import headless_chromium, request

DOCS_IMG = Path(__file__).resolve().parents[2] / "docs" / "img"

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def camera() -> Iterator[replay.Replay]:
    """Seed 1 of the camera exercise's starter (kills of `actions`; a broken rule)."""
    with tempfile.TemporaryDirectory() as tmp:
        _chosen, folder = kit.start("camera", Path(tmp) / "cam")
        plan, run = grade.seed_run(folder, 1)
        yield replay.Replay(plan, run)


def step_of(shown: replay.Replay, kind: type[Any], first: int = 1, **fields: Any) -> int:
    """The first step (from `first`) whose event is a `kind` with these fields."""
    for n, step in enumerate(shown.steps, 1):
        e = step.event
        if (
            n >= first
            and isinstance(e, kind)
            and all(getattr(e, k) == v for k, v in fields.items())
        ):
            return n
    raise AssertionError(f"no {kind.__name__} {fields} from step {first}")


def child(sections: dict[str, Any], name: str) -> dict[str, Any]:
    found: dict[str, Any] = next(c for c in sections["tree"]["children"] if c["name"] == name)
    return found


def test_each_step_shows_what_the_events_say(camera: replay.Replay) -> None:
    loaded = step_of(camera, events.ResourceLoaded, registrar="camera")
    resource = camera.steps[loaded - 1].event
    assert isinstance(resource, events.ResourceLoaded)
    before, at = camera.sections(loaded - 1), camera.sections(loaded)
    assert [] == before["catalog/camera"]["catalog"]["resources"]
    assert [resource.resource_id] == [r["id"] for r in at["catalog/camera"]["catalog"]["resources"]]
    added = step_of(camera, events.ConsumerAdded, loaded, resource_id=resource.resource_id)
    consumers = camera.sections(added)["catalog/camera"]["catalog"]["resources"][0]["consumers"]
    assert {"actions"} == {c["origin"] for c in consumers}
    started = step_of(camera, events.ChildStarted, child="actions")
    assert ("starting", None) == tuple(
        map(child(camera.sections(started - 1), "actions").get, ("state", "pid"))
    )
    assert "running" == child(camera.sections(started), "actions")["state"]
    # the kill: a fault's step, then the exit (restarting), then the restart (a new pid)
    kill = next(n for n, s in enumerate(camera.steps, 1) if s.line.who == "fault")
    exited = step_of(camera, events.ChildExited, kill, child="actions")
    restarted = step_of(camera, events.ChildRestarted, exited, child="actions")
    down = child(camera.sections(exited), "actions")
    assert ("restarting", 0) == (down["state"], down["restarts"])
    assert "SIGKILL" in down["last_exit"]
    assert "restarting" == camera.sections(exited)["catalog/actions"]["state"]
    up = child(camera.sections(restarted), "actions")
    assert ("running", 1) == (up["state"], up["restarts"])
    assert up["pid"] != down["pid"]
    story = camera.sections(kill)["replay"]
    assert (kill, len(camera)) == (story["step"], story["steps"])
    current = next(row for row in story["story"] if row["step"] == kill)
    assert ("fault", camera.steps[kill - 1].line.text) == (current["who"], current["text"])
    assert current["text"].startswith("kill_manager actions")


def test_a_call_is_in_flight_from_its_start_to_its_answer(camera: replay.Replay) -> None:
    calls = [
        (n, s.event)
        for n, s in enumerate(camera.steps, 1)
        if isinstance(s.event, events.CallAnswered) and s.event.started > 0
    ]
    # a call begun at or before the step before its answer: in flight there, not at its answer
    n, call = next((n, e) for n, e in calls if n > 1 and camera.steps[n - 2].at >= e.started)
    flying = {row["id"] for row in camera.sections(n - 1)["replay"]["in_flight"]}
    assert call.query_id in flying
    assert call.query_id not in {row["id"] for row in camera.sections(n)["replay"]["in_flight"]}
    # and before it began, it is not
    begun = next((m for m in range(1, n) if camera.steps[m - 1].at >= call.started), n)
    if begun > 1 and camera.steps[begun - 2].at < call.started:
        earlier = camera.sections(begun - 1)["replay"]["in_flight"]
        assert call.query_id not in {row["id"] for row in earlier}


def test_a_step_from_a_checkpoint_is_the_step_folded_from_the_start(
    camera: replay.Replay,
) -> None:
    folded = camera.state_at(0)
    assert len(camera) > 2 * replay.CHECKPOINT  # (checkpoints beyond the first are used)
    for n, step in enumerate(camera.steps, 1):
        replay._fold(folded, step.event)
        assert json.dumps(folded, sort_keys=True) == json.dumps(camera.state_at(n), sort_keys=True)


def test_a_step_outside_the_run_is_clamped_and_a_bad_one_refused(camera: replay.Replay) -> None:
    assert {"ok": True, "step": len(camera), "steps": len(camera)} == camera.control(
        {"step": 10**6}
    )
    assert 1 == camera.control({"step": -3})["step"]
    with pytest.raises(ConfigError, match="whole number"):
        camera.control({"step": "4"})


# -- the page, in a real browser ----------------------------------------------------------


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """A headless chromium for this module's tests (its own fresh profile)."""
    with headless_chromium() as context:
        yield context


def shows(page: Any, step: int) -> None:
    page.wait_for_selector(f'#replay-panel[data-step="{step}"]', timeout=10_000)


def story_line(page: Any) -> str:
    text: str = page.locator("#replay-story li.current").inner_text()
    return text


def test_a_step_asked_while_a_kill_reruns_the_seed_waits_for_the_rerun(tmp_path: Path) -> None:
    """Review of the replay: the page's requests run on the server's threads, and a
    kill's rerun (seconds) replaced the steps while a scrub read them. A step asked
    meanwhile now waits for the rerun and shows the new run's step."""
    _chosen, folder = kit.start("camera", tmp_path / "cam")
    plan, run = grade.seed_run(folder, 1)
    rerun = grade.rerun(folder, 1)
    inside, go = threading.Event(), threading.Event()

    def held(new_plan: Any) -> Any:
        inside.set()
        assert go.wait(60)
        return rerun(new_plan)

    shown = replay.Replay(plan, run, rerun=held)
    shown.show(10)
    answers: dict[str, Any] = {}
    kill = threading.Thread(
        target=lambda: answers.update(kill=shown.control({"fault": "kill", "target": "camera"}))
    )
    kill.start()
    assert inside.wait(60)
    stepped = threading.Event()

    def step() -> None:
        answers["step"] = shown.control({"step": 5})
        stepped.set()

    scrub = threading.Thread(target=step)
    scrub.start()
    assert not stepped.wait(0.5)  # (it waits for the rerun: the steps are being replaced)
    go.set()
    kill.join(60)
    scrub.join(60)
    assert answers["step"] == {"ok": True, "step": 5, "steps": len(shown)}
    assert answers["kill"]["steps"] == len(shown)


@pytest.mark.parametrize("kind", ["kill", "cut"])
def test_a_kill_or_cut_of_a_manager_on_another_host_fires_in_the_rerun(
    kind: str, tmp_path: Path
) -> None:
    """Issue 56: with `[hosts]` a manager fault hit only the first host's managers; a
    kill or cut of `db` (host c of the cut exercise) did not fire."""
    _chosen, folder = kit.start("cut", tmp_path / "cut")
    plan, run = grade.seed_run(folder, 1)
    assert plan.host_of("db") not in (None, plan.hosts.names[0] if plan.hosts else None)
    shown = replay.Replay(plan, run, rerun=grade.rerun(folder, 1))
    shown.show(step_of(shown, events.CallAnswered))

    told = shown.control({"fault": kind, "target": "db"})["message"]

    fault = replay.BRANCHES[kind]
    assert "it did not fire" not in told
    assert f"{fault} db: " in shown.steps[shown.shown - 1].line.plain()
    pid = {"kill": "SIGKILL pid ", "cut": "cut pid "}[kind]
    assert pid in shown.steps[shown.shown - 1].line.plain()


def test_the_page_plays_pauses_steps_and_scrubs(
    camera: replay.Replay, browser: Any, tmp_path: Path
) -> None:
    page = browser.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    observer, shown = replay.open_replay(camera.plan, camera.run)
    try:
        page.goto(observer.url)
        shows(page, 1)  # opened at its first step
        assert f"step 1 of {len(shown)}" in page.locator("#replay-where").inner_text()
        assert story_line(page).endswith(shown.steps[0].line.text)
        assert "replay" == page.locator("#connection").inner_text()
        for n in (2, 3, 4):
            page.click("#replay-step")
            shows(page, n)
        page.click("#replay-back")
        shows(page, 3)
        assert story_line(page).endswith(shown.steps[2].line.text)
        # scrub to the kill: the slider, then the exit's line in the story
        kill = next(n for n, s in enumerate(shown.steps, 1) if s.line.who == "fault")
        exited = step_of(shown, events.ChildExited, kill, child="actions")
        page.locator("#replay-scrub").evaluate(
            "(e, n) => { e.value = n; e.dispatchEvent(new Event('input')); }", kill
        )
        shows(page, kill)
        assert "kill_manager actions" in story_line(page)
        page.click(f'#replay-story li[data-step="{exited}"]')
        shows(page, exited)
        actions = page.locator('.node[data-child="actions"]')
        assert "restarting" == actions.get_attribute("data-state")
        assert "SIGKILL" in actions.locator('[data-field="last-exit"]').inner_text()
        card = page.locator('#catalogs [data-registrar="actions"]')
        assert "process manager · restarting" in card.locator("h3 small").inner_text()
        rows = shown.sections(exited)["catalog/camera"]["catalog"]["resources"]
        for row in rows:  # the camera's catalog, as the events left it
            page.wait_for_selector(
                f'#catalogs [data-registrar="camera"] [data-resource="{row["id"]}"]'
            )
        # play: it goes on by itself; pause: it stops, and a step goes one on from there
        page.click("#replay-play")
        page.wait_for_function(
            "(n) => Number(document.querySelector('#replay-panel').dataset.step) >= n",
            arg=exited + 2,
            timeout=10_000,
        )
        page.click("#replay-play")
        assert "" == page.locator("#replay-panel").get_attribute("data-playing")
        asked = int(page.locator("#replay-panel").get_attribute("data-asked") or 0)
        shows(page, asked)
        page.click("#replay-step")
        shows(page, asked + 1)
        assert asked + 1 == shown.shown
        status, _, body = request(
            observer.url,
            "/api/control",
            method="POST",
            body=b'{"step": "x"}',
            headers={"Content-Type": "application/json"},
        )
        assert (400, False) == (status, json.loads(body)["ok"])
    finally:
        observer.close()
        page.close()
    assert [] == errors


def test_a_live_replay_kills_and_cuts_after_the_step_shown(browser: Any, tmp_path: Path) -> None:
    _chosen, folder = kit.start("camera", tmp_path / "cam")
    plan, run = grade.seed_run(folder, 1)
    page = browser.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    observer, shown = replay.open_replay(
        plan, run, rerun=grade.rerun(folder, 1), judge=replay.exercise_verdict(folder)
    )
    try:
        page.goto(observer.url)
        shows(page, 1)
        loaded = step_of(shown, events.ResourceLoaded, registrar="actions")
        before = [s.line.plain() for s in shown.steps[:loaded]]
        page.locator("#replay-scrub").evaluate(
            "(e, n) => { e.value = n; e.dispatchEvent(new Event('input')); }", loaded
        )
        shows(page, loaded)
        page.click('.node[data-child="camera"] [data-fault="kill"]')
        page.click("#confirm-ok")
        page.wait_for_selector("#notice:not([hidden])", timeout=30_000)
        assert "kill_manager camera after step" in page.locator("#notice").inner_text()
        killed = shown.shown  # the fault's own step, in the run made again
        shows(page, killed)
        assert "kill_manager camera: SIGKILL" in story_line(page)
        assert before == [s.line.plain() for s in shown.steps[:loaded]]  # the same before it
        assert ["kill_manager"] == [f.kind for f in shown.plan.faults][-1:]
        exited = step_of(shown, events.ChildExited, killed, child="camera")
        page.locator("#replay-scrub").evaluate(
            "(e, n) => { e.value = n; e.dispatchEvent(new Event('input')); }", exited
        )
        shows(page, exited)
        assert 0 == page.locator('[data-fault="fatal"]').count()  # (no FATAL: not a fault here)
        assert "restarting" == page.locator('.node[data-child="camera"]').get_attribute(
            "data-state"
        )
        assert "FAILED" == page.locator("#replay-outcome").inner_text()  # (the run made again)
        where = DOCS_IMG if os.environ.get("RR_DOCS_SCREENSHOTS") == "1" else tmp_path
        page.screenshot(path=str(where / "teach-replay.png"), full_page=True)
        # a cut, then: the same way, its connections closed in the run made again
        page.evaluate("() => { document.querySelector('#notice').hidden = true; }")
        page.click('.node[data-child="actions"] [data-fault="cut"]')
        page.click("#confirm-ok")
        page.wait_for_selector("#notice:not([hidden])", timeout=30_000)
        assert "cut_connections actions after step" in page.locator("#notice").inner_text()
        shows(page, shown.shown)
        assert "cut_connections actions: cut pid" in story_line(page)
        assert ["kill_manager", "cut_connections"] == [f.kind for f in shown.plan.faults][-2:]
    finally:
        observer.close()
        page.close()
    assert [] == errors


def test_a_failed_seeds_page_shows_failed_the_rule_and_its_first_violating_step(
    browser: Any, tmp_path: Path
) -> None:
    """Issue 70 item 3: the page said "checker: held" on the seed the check failed (the
    exercise's own rule, `[dependency]`, and FAILED appeared nowhere)."""
    _chosen, folder = kit.start("camera", tmp_path / "cam")
    plan, run = grade.seed_run(folder, 1)
    failure = grade.check_folder(folder, seed=1, shrink_budget=0).failure
    assert failure is not None
    assert failure.first_event is not None
    assert "held" == run.verdict  # (the checker alone finds nothing: the kit's rule broke)
    line = int(failure.first_event.split(":")[0].lstrip("#"))
    page = browser.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    observer, shown = replay.open_replay(
        plan, run, rerun=grade.rerun(folder, 1), judge=replay.exercise_verdict(folder)
    )
    try:
        page.goto(observer.url)
        shows(page, 1)
        assert "FAILED" == page.locator("#replay-outcome").inner_text()
        assert f"[{failure.rule}]" == page.locator("#replay-rule").inner_text()
        assert failure.message in page.locator("#replay-message").inner_text()
        assert f"the rule: {failure.words}" == page.locator("#replay-words").inner_text()
        assert "checker: held" not in page.locator("#replay-panel").inner_text()
        violating = next(n for n, s in enumerate(shown.steps, 1) if s.line.line == line)
        button = page.locator("#replay-violation")
        assert f"first violating step: {violating}" == button.inner_text()
        button.click()
        shows(page, violating)
        current = page.locator("#replay-story li.current")
        assert "violating" in (current.get_attribute("class") or "")
        assert f"#{line} " in current.inner_text()
        assert failure.first_event.split(": ", 1)[1] in current.inner_text()
    finally:
        observer.close()
        page.close()
    assert [] == errors


def test_a_seed_that_holds_every_rule_shows_passed_and_no_violating_step(tmp_path: Path) -> None:
    _chosen, folder = kit.start("camera", tmp_path / "cam")
    for file, text in kit.solution_files(kit.exercise("camera")).items():
        (folder / file).write_text(text, encoding="utf-8")
    plan, run = grade.seed_run(folder, 1)

    shown = replay.Replay(plan, run, judge=replay.exercise_verdict(folder))

    check = shown.sections(1)["replay"]["check"]
    assert ("passed", "", None) == (check["outcome"], check["rule"], check["step"])
    assert not any(row["violating"] for row in shown.sections(1)["replay"]["story"])


def test_without_an_exercise_the_page_shows_the_checkers_first_violation(tmp_path: Path) -> None:
    _chosen, folder = kit.start("climb", tmp_path / "climb")
    plan, run = grade.seed_run(folder, 1)  # (the starter's climb stops at FATAL: violated)
    assert "violated" == run.verdict

    shown = replay.Replay(plan, run)

    check = shown.sections(1)["replay"]["check"]
    assert ("FAILED", "status-reached") == (check["outcome"], check["rule"])
    assert check["step"] is not None
    assert shown.steps[check["step"] - 1].line.marked  # (a step the checker points at)
