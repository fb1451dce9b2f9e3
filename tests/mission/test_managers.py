"""The mission's managers (`rr_actors_lab.mission.managers`): what the erm adopts after a
restart."""

from __future__ import annotations

import os
import uuid
from pathlib import Path

import rr_actors as rr
from rr_actors_lab.mission.managers import ProcessTable
from rr_actors_lab.mission.programs import start_time
from tests.support.demos import console_spans
from tests.support.python import python


def test_the_erm_does_not_adopt_a_process_whose_pid_was_reused(tmp_path: Path) -> None:
    with rr.ResourceRegistrar.start(f"erm-{uuid.uuid4().hex[:8]}") as registrar:
        table = ProcessTable(registrar)
        me = os.getpid()
        created = start_time(me)
        assert created is not None
        impostor = rr.Query(
            "q1",
            "program",
            registrar.name,
            "cm",
            {"name": "lidar1", "bus": str(tmp_path)},
            {"name": "lidar1", "pid": me, "start_time": created + 1},
        )

        dead = table.adopt([impostor])

    assert [impostor] == dead


def test_rms_driver_restart_is_in_the_trace_of_the_status_callbacks_run(tmp_path: Path) -> None:
    # F2 kills the motor driver: erm sends FATAL, rm's callback restarts it on a thread of
    # its own, whose calls (release the dead driver, load a new one) are in the callback's trace
    env = {**os.environ, "OTEL_TRACES_EXPORTER": "console"}
    argv = ["--fast", "--faults", "F2", "--distance", "2", "--quiet", "--trace"]
    done = python(
        "-m", "rr_actors_lab", "demo", *argv, "--out", str(tmp_path), timeout=300, env=env
    )

    assert 0 == done.returncode, done.stderr[-2000:]
    spans = console_spans(done.stdout)
    by_id = {span["context"]["span_id"]: span for span in spans}
    assert [] == [s["name"] for s in spans if s["parent_id"] and s["parent_id"] not in by_id]
    runs = [s for s in spans if s["name"] == "status FATAL callback"]
    restarts = [
        [s for s in spans if s["context"]["trace_id"] == run["context"]["trace_id"]] for run in runs
    ]
    [restart] = [
        trace
        for run, trace in zip(runs, restarts, strict=True)
        if run["attributes"]["rr_actors.registrar"] == "rm" and len(trace) > 1
    ]
    calls = [s for s in restart if s["kind"] == "SpanKind.CLIENT"]
    assert {"erm/program"} == {s["name"] for s in calls}
    assert {"answered", "unload"} == {s["attributes"]["rr_actors.outcome"] for s in calls}
    [run] = [s for s in restart if s["name"] == "status FATAL callback"]
    assert run["parent_id"] is None  # the root of a trace of its own
    [link] = run["links"]  # to the hop that brought the FATAL to rm
    [hop] = [s for s in spans if s["context"]["span_id"] == link["context"]["span_id"]]
    assert ("SpanKind.CONSUMER", "rm") == (hop["kind"], hop["attributes"]["rr_actors.registrar"])
