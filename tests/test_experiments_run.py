"""Experiments for real: runs in fresh processes, every fault kind, the files, seeds, leaks.

One experiment with every fault kind (two runs) is shared by the tests that read its
results and files; the tests of the same seed and of a cut connection run their own.
"""

from __future__ import annotations

import csv
import functools
import json
import os
import sys
import threading
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
import rr_actors.observe
from rr_actors import events
from rr_actors.experiments import ExperimentError, Progress, Results, parse_plan, run
from rr_actors.experiments._instrument import CUT_SIGNAL
from rr_actors.experiments._procs import processes_with
from rr_actors.experiments.runner import build_tree
from rr_actors.testing import pending_work

SERVICE = "rr_actors.experiments.services:service"

EVERY_FAULT = f"""\
name = "every-fault"
duration = 3.4
seed = 21

[tree]
max_restarts = 20

[[tree.children]]
name = "db"
setup = "{SERVICE}"

[[tree.children]]
name = "api"
setup = "{SERVICE}"
options = {{ uses = ["db"] }}
heartbeat = 0.1

[workload]
clients = 2
rate = 20.0
hold = 0.2
timeout = 3.0

[[workload.calls]]
manager = "api"
server = "resource"
shared = 0.3
keys = 2

[[faults]]
kind = "kill_manager"
target = "db"
at = 0.5

[[faults]]
kind = "kill_manager"
target = "api"
after = {{ event = "ChildRestarted", child = "db" }}
delay = 0.2

[[faults]]
kind = "hang_manager"
target = "api"
at = 1.7
for = 1.0

[[faults]]
kind = "load_error"
target = "db"
at = 2.4
loads = 2

[[faults]]
kind = "cut_connections"
target = "db"
at = 2.8
"""


def ours() -> list[int]:
    """Processes of this test process's experiments that are still alive."""
    prefix = f"{os.getpid()}-"
    alive = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            environ = (entry / "environ").read_bytes().split(b"\0")
        except OSError:
            continue
        for item in environ:
            if item.startswith(b"RR_ACTORS_EXPERIMENT=" + prefix.encode()):
                token = item.split(b"=", 1)[1].decode()
                alive.extend(processes_with(token))
    return sorted(set(alive))


@pytest.fixture(scope="module")
def every_fault(tmp_path_factory: pytest.TempPathFactory) -> tuple[Results, Path]:
    out = tmp_path_factory.mktemp("every-fault")
    seen: list[Progress] = []
    results = run(parse_plan(EVERY_FAULT), out=out, repeat=2, progress=seen.append, force=True)
    assert [1, 2] == [p.finished.run for p in seen if p.finished is not None]
    return results, out


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as file:
        return list(csv.DictReader(file))


def lines(out: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (out / "events.jsonl").read_text().splitlines()]


def run_events(out: Path, number: int) -> list[events.Event]:
    """The rr_actors events of one run, read back from events.jsonl."""
    found = []
    for line in lines(out):
        if line["run"] == number and line["type"] not in ("FaultInjected", "FaultSkipped"):
            del line["run"], line["seed"]
            found.append(events.from_dict(line))
    return found


def test_every_run_writes_one_row_of_runs_csv_with_its_seed(
    every_fault: tuple[Results, Path],
) -> None:
    _, out = every_fault
    rows = read_csv(out / "runs.csv")

    assert [("1", "21"), ("2", "22")] == [(r["run"], r["seed"]) for r in rows]
    assert {"every-fault"} == {r["plan"] for r in rows}
    assert {rr.__version__} == {r["version"] for r in rows}
    for column in (
        "calls_ok",
        "calls_failed",
        "calls_retried",
        "unavailable_s_db",
        "unavailable_s_api",
        "restarts",
        "recovery_median_s",
        "recovery_p90_s",
        "leaked_processes",
        "catalog_entries_left",
    ):
        assert column in rows[0]


def test_every_line_of_events_jsonl_has_its_run_and_seed_and_reads_back(
    every_fault: tuple[Results, Path],
) -> None:
    results, out = every_fault
    recorded = lines(out)

    assert {(1, 21), (2, 22)} == {(line["run"], line["seed"]) for line in recorded}
    assert [run.events for run in results.runs] == [
        len(run_events(out, 1)),
        len(run_events(out, 2)),
    ]


def test_every_scheduled_fault_is_in_faults_csv_and_events_jsonl(
    every_fault: tuple[Results, Path],
) -> None:
    results, out = every_fault
    rows = read_csv(out / "faults.csv")
    injected = [line for line in lines(out) if line["type"] in ("FaultInjected", "FaultSkipped")]

    assert 2 * 5 == len(rows) == len(injected)
    assert sorted(r["kind"] for r in rows) == sorted(f.kind for _, f in results.faults())


def test_every_fault_kind_fires_on_time_in_every_run(every_fault: tuple[Results, Path]) -> None:
    results, _ = every_fault

    for run_result in results.runs:
        kinds = {f.kind: f for f in run_result.faults}
        assert [] == [f.detail for f in run_result.faults if f.skipped]
        assert {
            "kill_manager",
            "hang_manager",
            "load_error",
            "cut_connections",
        } == set(kinds)
        for fault in run_result.faults:
            assert fault.late_s is not None
            assert 0 <= fault.late_s < 0.05, fault


def test_a_killed_manager_exits_by_sigkill_and_is_restarted(
    every_fault: tuple[Results, Path],
) -> None:
    results, out = every_fault
    for number, run_result in enumerate(results.runs, start=1):
        seen = run_events(out, number)
        t0 = run_result.started_at
        kill = next(f for f in run_result.faults if f.kind == "kill_manager" and f.target == "db")
        assert kill.injected_s is not None

        exits = [e for e in seen if isinstance(e, events.ChildExited) and e.child == "db"]
        assert "killed by SIGKILL" in exits[0].reason
        assert exits[0].at - t0 >= kill.injected_s
        assert run_result.restart_times["db"]
        assert kill.recovery_s is not None


def test_a_fault_triggered_by_an_event_fires_its_delay_after_that_event(
    every_fault: tuple[Results, Path],
) -> None:
    results, _ = every_fault
    for run_result in results.runs:
        triggered = next(f for f in run_result.faults if f.fault == 1)
        db_back = run_result.restart_times["db"][0]

        assert triggered.scheduled_s is not None
        assert 0.2 == pytest.approx(triggered.scheduled_s - db_back, abs=1e-3)


def test_a_hung_manager_is_found_by_its_heartbeat_killed_and_restarted(
    every_fault: tuple[Results, Path],
) -> None:
    results, out = every_fault
    for number, run_result in enumerate(results.runs, start=1):
        hang = next(f for f in run_result.faults if f.kind == "hang_manager")
        assert hang.injected_s is not None
        exits = [
            e
            for e in run_events(out, number)
            if isinstance(e, events.ChildExited)
            and e.child == "api"
            and e.at - run_result.started_at > hang.injected_s
        ]

        assert exits[0].reason.startswith("hung: no heartbeat answer")
        assert hang.recovery_s is not None
        assert hang.recovery_s < 1.0  # found and restarted before the hang would have ended


def test_a_load_error_makes_loads_raise_and_calls_fail(every_fault: tuple[Results, Path]) -> None:
    results, out = every_fault
    for number, run_result in enumerate(results.runs, start=1):
        failed = [
            e
            for e in run_events(out, number)
            if isinstance(e, events.LoadFailed) and e.error_type == "InjectedLoadError"
        ]

        assert 2 == len(failed)
        assert {"db"} == {e.registrar for e in failed}
        assert 2 <= sum(1 for c in run_result.calls if c.error == "ResourceLoadError")


def test_the_runs_leave_no_process_behind(every_fault: tuple[Results, Path]) -> None:
    results, _ = every_fault

    assert [0, 0] == [r.leaked_processes for r in results.runs]
    assert [] == ours()


def test_the_plots_are_drawn(every_fault: tuple[Results, Path]) -> None:
    _, out = every_fault

    for name in ("recovery.png", "timeline.png"):
        assert (out / name).read_bytes().startswith(b"\x89PNG")


RANDOM_KILLS = f"""\
duration = 2.0

[tree]
max_restarts = 20

[[tree.children]]
name = "a"
setup = "{SERVICE}"

[[tree.children]]
name = "b"
setup = "{SERVICE}"

[[faults]]
kind = "kill_manager"
target = ["a", "b"]
every = {{ min = 0.3, max = 0.6 }}
"""


def test_the_same_seed_gives_the_same_fault_schedule_in_two_runs() -> None:
    plan = parse_plan(RANDOM_KILLS)

    def schedule(seed: int) -> list[tuple[Any, ...]]:
        (only,) = run(plan, seed=seed).runs
        return [(f.fault, f.n, f.kind, f.target, f.scheduled_s) for f in only.faults]

    first, second = schedule(4), schedule(4)

    assert first == second
    assert 3 <= len(first)
    assert first != schedule(5)


def test_a_cut_fails_the_call_in_flight_at_once_and_the_next_call_gets_through(
    eventually: Callable[..., bool], process_helpers: object
) -> None:
    plan = parse_plan(
        f"""\
        duration = 1.0
        [tree]
        [[tree.children]]
        name = "slow"
        setup = "{SERVICE}"
        options = {{ load_s = 1.5 }}
        """.replace("        ", "")
    )
    sup = build_tree(plan, None)
    with sup:
        app = sup.registrar(rr.RegistrarConfig("app", call_timeout=20.0))
        outcome: list[Any] = []

        def call() -> None:
            try:
                outcome.append(app.call("slow", "resource", "in flight"))
            except rr.RrError as exc:
                outcome.append(exc)

        caller = threading.Thread(target=call)
        caller.start()
        waiting = functools.partial(_waiting_loads, sup, "slow")
        assert eventually(lambda: waiting() > 0, timeout=10)

        pid = sup.child("slow").pid
        assert pid is not None
        os.kill(pid, CUT_SIGNAL)
        caller.join(1.0)  # well before the load's 1.5 s

        assert not caller.is_alive()
        assert isinstance(outcome[0], rr.RegistrarUnavailableError)
        assert "slow" == app.call("slow", "resource", "after the cut").response["server"][:4]
        assert 0 == sup.child("slow").restarts  # it kept running: only its connections went


def _waiting_loads(sup: rr.Supervisor, name: str) -> int:
    counter = sup.run_in(name, lambda registrar: pending_work(registrar).waiting_loads)
    return sum(counter.values())


def test_with_observe_each_run_serves_its_observer_page_while_it_runs() -> None:
    pages: list[tuple[int, str, str]] = []

    def look(number: int, url: str) -> None:  # in this process, while the run goes on
        with urllib.request.urlopen(url, timeout=10) as response:  # noqa: S310 - our page
            pages.append((number, url, response.read().decode()))

    results = run(parse_plan(RANDOM_KILLS), repeat=2, duration=0.5, observe=True, on_observe=look)

    assert [1, 2] == [number for number, _, _ in pages]
    assert all(url.startswith("http://127.0.0.1:") for _, url, _ in pages)
    assert all("<title>rr_actors observer</title>" in html for _, _, html in pages)
    assert 2 == len(results.runs)


def test_observe_without_the_observe_extra_is_refused_before_anything_starts(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setitem(sys.modules, "rr_actors.observe._server", None)  # as if not installed
    monkeypatch.delattr(rr.observe, "_server", raising=False)

    with pytest.raises(rr.ConfigError, match=r"pip install 'rr-actors\[observe\]'"):
        run(parse_plan(RANDOM_KILLS), observe=True)


def test_an_output_directory_that_is_not_empty_is_refused_unless_forced(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("mine")

    with pytest.raises(rr.ConfigError, match="exists and is not empty"):
        run(parse_plan(RANDOM_KILLS), out=tmp_path)

    assert ["notes.txt"] == [p.name for p in tmp_path.iterdir()]


MANAGERS_NEXT_TO_THE_PLAN = """\
def counter_setup(registrar, *, greeting):
    registrar.register_server("hello", load=lambda r: f"{greeting} {r}", unload=lambda q, r: None)


def broken_setup(registrar):
    raise RuntimeError("no camera on this bench")


def request(key, context):
    return f"{key} from client {context.client}"
"""

OWN_PLAN = """\
duration = 0.5

[tree]
[[tree.children]]
name = "mine"
setup = "bench_managers:SETUP"
OPTIONS

[workload]
clients = 1
rate = 20.0
[[workload.calls]]
manager = "mine"
server = "hello"
factory = "bench_managers:request"
"""


def test_a_plan_names_managers_and_factories_in_a_module_next_to_it(tmp_path: Path) -> None:
    (tmp_path / "bench_managers.py").write_text(MANAGERS_NEXT_TO_THE_PLAN)
    plan = tmp_path / "plan.toml"
    plan.write_text(
        OWN_PLAN.replace("SETUP", "counter_setup").replace(
            "OPTIONS", 'options = { greeting = "hi" }'
        )
    )

    (result,) = run(plan).runs

    assert result.calls_ok > 0
    assert 0 == result.calls_failed


def test_a_manager_that_cannot_start_fails_the_experiment_with_its_error(
    tmp_path: Path,
) -> None:
    (tmp_path / "bench_managers.py").write_text(MANAGERS_NEXT_TO_THE_PLAN)
    plan = tmp_path / "plan.toml"
    plan.write_text(OWN_PLAN.replace("SETUP", "broken_setup").replace("OPTIONS", ""))

    with pytest.raises(ExperimentError, match="no camera on this bench"):
        run(plan, out=tmp_path / "out")

    assert [] == ours()
