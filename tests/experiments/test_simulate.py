"""A plan on the simulation (`rr_actors.experiments.simulate`): its tree, workload and
`kill_manager` faults in virtual time, one seed a run: the checker's verdict, the same
history (hash) for the same seed in this process and in another, a planted bug found and
replayed; what is not simulated yet is a `PlanError` naming it."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from rr_actors.experiments import PlanError, parse_plan, simulate
from rr_actors.experiments.plan import Plan

pytest.importorskip("greenlet")  # (the simulation extra)

ROOT = Path(__file__).resolve().parent.parent.parent

SERVICE = "rr_actors.experiments.services:service"

PLAN = f"""\
name = "simkill"
duration = 3.0

[tree]
max_restarts = 1000
period = 1.0

[[tree.children]]
name = "db"
setup = "{SERVICE}"

[[tree.children]]
name = "api"
setup = "{SERVICE}"
options = {{ uses = ["db"], load_s = 0.002 }}

[workload]
clients = 2
rate = 10.0
hold = 0.2
timeout = 3.0

[[workload.calls]]
manager = "api"
server = "resource"
keys = 3

[[faults]]
kind = "kill_manager"
target = ["api", "db"]
every = {{ min = 0.3, max = 0.8 }}
"""

SWEEP = pytest.mark.timeout(300)
"""A few seeds take a few CPU seconds; under load several times that."""


def simkill() -> Plan:
    return parse_plan(PLAN)


@pytest.fixture(autouse=True)
def _quiet_kills() -> Iterator[None]:
    """The supervisor logs each kill: hundreds of warnings a sweep."""
    logging.disable(logging.WARNING)
    try:
        yield
    finally:
        logging.disable(logging.NOTSET)


def plant_second_load(monkeypatch: pytest.MonkeyPatch) -> None:
    """A planted bug: a provider loads an equal request again instead of sharing it."""
    from rr_actors._catalog.records import ResourceState  # noqa: PLC0415
    from rr_actors._registrar.provider import Provider  # noqa: PLC0415

    matched = Provider.matched

    def buggy(self: Provider, message: Any, key: Any, resource: Any) -> None:
        if resource is not None and resource.state is ResourceState.LOADED:
            resource = None  # (the bug: no dedup hit, a second load)
        matched(self, message, key, resource)

    monkeypatch.setattr(Provider, "matched", buggy)


@SWEEP
def test_a_plan_of_kills_holds_on_every_seed_with_faults_and_calls_made() -> None:
    runs = simulate.simulate(simkill(), range(1, 5))

    assert [1, 2, 3, 4] == [r.seed for r in runs]
    assert ["held"] * 4 == [r.verdict for r in runs], [r.findings for r in runs]
    assert all(r.faults > 0 and r.calls_ok > 0 and r.events > 0 for r in runs)
    assert all(r.virtual_s >= 3.0 for r in runs)
    assert len({r.hash for r in runs}) == 4


@SWEEP
def test_the_history_is_the_runners_events_jsonl_with_fault_lines_in_virtual_time() -> None:
    run = simulate.run_seed(simkill(), 2)

    lines = [json.loads(line) for line in run.history.splitlines()]
    kinds = {line["type"] for line in lines}
    assert {"ChildStarted", "ChildExited", "ChildRestarted", "FaultInjected"} <= kinds
    assert all(line["run"] == 1 and line["seed"] == 2 for line in lines)
    assert simulate.history_hash(run.history) == run.hash
    first = min(line["at"] for line in lines if line["at"] is not None)
    assert 1_767_225_600.0 <= first < 1_767_225_600.0 + 60  # (the virtual wall clock)
    killed = [line for line in lines if line["type"] == "FaultInjected"]
    assert run.faults == len(killed)
    assert all(line["detail"].startswith("SIGKILL pid ") for line in killed)
    assert max(line.get("pid", 0) for line in lines) < 1_000  # simulated pids, not ours


@SWEEP
def test_the_same_seed_gives_the_same_history_here_and_in_another_process() -> None:
    plan = simkill()
    first, again = simulate.run_seed(plan, 7), simulate.run_seed(plan, 7)
    assert first.history == again.history

    script = (
        "import logging, sys; logging.disable(logging.WARNING)\n"
        "from rr_actors.experiments import parse_plan, simulate\n"
        "print(simulate.run_seed(parse_plan(sys.stdin.read()), 7).hash)\n"
    )
    env = {**os.environ, "PYTHONHASHSEED": "0"}
    hashes = [
        subprocess.run(
            [sys.executable, "-c", script],
            input=PLAN,
            env=env,
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
            timeout=240,
        ).stdout.strip()
        for _ in range(2)
    ]
    assert hashes[0] == hashes[1]
    if os.environ.get("PYTHONHASHSEED") == "0":  # (else this process's sets iterate otherwise)
        assert first.hash == hashes[0]


class _Backwards(set):  # type: ignore[type-arg]
    """A set that iterates the other way round: as a set of objects ordered by their
    addresses does in another process, or after another run in this one."""

    def __iter__(self) -> Iterator[Any]:
        return iter(list(super().__iter__())[::-1])


CHAIN = f"""\
name = "chainkill"
duration = 2.0

[tree]
max_restarts = 1000
period = 1.0

[[tree.children]]
name = "db"
setup = "{SERVICE}"

[[tree.children]]
name = "api"
setup = "{SERVICE}"
options = {{ uses = ["db"], load_s = 0.002 }}

[[tree.children]]
name = "edge"
setup = "{SERVICE}"
options = {{ uses = ["api"], load_s = 0.002 }}

[workload]
clients = 4
rate = 25.0
hold = 0.2
timeout = 3.0

[[workload.calls]]
manager = "edge"
server = "resource"
shared = 0.5
keys = 4

[[faults]]
kind = "kill_manager"
target = ["edge", "api", "db"]
every = {{ min = 0.15, max = 0.4 }}
"""
"""The shipped killheavy plan (without its cut) for 2 s: clients wait for restarts often."""


@SWEEP
def test_the_same_seed_gives_the_same_history_whatever_order_a_set_of_callbacks_has(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from rr_actors._supervision.tree import Tree  # noqa: PLC0415

    plan = parse_plan(CHAIN)
    seeds = range(1, 9)  # (without the fix, about 2 in 5 of them give another history)
    first = [simulate.run_seed(plan, seed).history for seed in seeds]
    made = Tree.__init__

    def backwards(self: Tree, *args: Any, **kwargs: Any) -> None:
        made(self, *args, **kwargs)
        self.watchers = _Backwards()  # (the waits woken at each change: in another order)

    monkeypatch.setattr(Tree, "__init__", backwards)
    again = [simulate.run_seed(plan, seed).history for seed in seeds]

    assert [] == [seed for seed, a, b in zip(seeds, first, again, strict=True) if a != b]


@SWEEP
def test_a_planted_second_load_is_violated_and_its_seed_replays_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    plant_second_load(monkeypatch)
    plan = simkill()

    runs = simulate.simulate(plan, range(1, 3))
    violated = [r for r in runs if r.verdict == "violated"]
    assert violated
    assert any("[dedup]" in finding for finding in violated[0].findings)

    again = simulate.run_seed(plan, violated[0].seed)
    assert again.hash == violated[0].hash
    assert "violated" == again.verdict


@pytest.mark.parametrize(
    ("fault", "key", "named"),
    [
        ('kind = "cut_connections"\ntarget = "db"\nat = 1.0', "faults[1].kind", "cut_connections"),
        (
            'kind = "hang_manager"\ntarget = "db"\nat = 1.0\nfor = 0.5',
            "faults[1].kind",
            "hang_manager",
        ),
        ('kind = "load_error"\ntarget = "db"\nat = 1.0', "faults[1].kind", "load_error"),
        (
            'kind = "kill_manager"\ntarget = "db"\nafter = { event = "ChildRestarted" }',
            "faults[1].after",
            "triggered",
        ),
    ],
    ids=["cut_connections", "hang_manager", "load_error", "after"],
)
def test_what_is_not_simulated_yet_is_a_plan_error_naming_it(
    fault: str, key: str, named: str
) -> None:
    plan = parse_plan(f"{PLAN}\n[[faults]]\n{fault}\n")

    with pytest.raises(PlanError) as raised:
        simulate.simulate(plan, range(1))

    assert key == raised.value.key
    assert named in str(raised.value)
    assert "kill_manager" in str(raised.value) or named == "triggered"
