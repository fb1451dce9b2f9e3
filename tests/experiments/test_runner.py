"""One run (`rr_actors_lab.experiments.runner.execute`) traced with OpenTelemetry: its run
process, a real tree of manager processes, a real SIGKILL, the spans printed by the SDK's
console exporter as `OTEL_TRACES_EXPORTER=console` says."""

from __future__ import annotations

import os
import textwrap
from pathlib import Path

from tests.support.demos import console_spans
from tests.support.python import python

PLAN = """\
duration = 3.0
seed = 1
[tree]
strategy = "one_for_one"
max_restarts = 5
[[tree.children]]
name = "db"
setup = "rr_actors_lab.experiments.services:service"
[[tree.children]]
name = "api"
setup = "rr_actors_lab.experiments.services:service"
options = { uses = ["db"], load_s = 0.005 }
[workload]
clients = 1
rate = 10.0
hold = 0.2
[[workload.calls]]
manager = "api"
server = "resource"
[[faults]]
kind = "kill_manager"
target = "db"
at = 1.5
"""

RUN = textwrap.dedent(
    """\
    import sys
    from pathlib import Path

    from rr_actors_lab.experiments import parse_plan, runner

    plan = parse_plan(sys.argv[1])
    spec = runner.RunSpec(plan, "", None, run=1, repeat=1, seed=1, trace=True)
    result = runner.execute(spec, Path(sys.argv[2]))
    print("calls answered:", sum(1 for c in result.calls if c.ok), file=sys.stderr)
    """
)


def test_a_traced_run_exports_one_trace_per_step_its_calls_under_it(tmp_path: Path) -> None:
    env = {**os.environ, "OTEL_TRACES_EXPORTER": "console", "OTEL_SERVICE_NAME": "the run"}
    done = python("-c", RUN, PLAN, str(tmp_path / "run"), timeout=300, env=env)

    assert 0 == done.returncode, done.stderr[-3000:]
    spans = console_spans(done.stdout)
    by_id = {span["context"]["span_id"]: span for span in spans}
    orphans = [s["name"] for s in spans if s["parent_id"] and s["parent_id"] not in by_id]
    assert [] == orphans

    def root(span: dict[str, object]) -> dict[str, object]:
        while span["parent_id"]:
            span = by_id[span["parent_id"]]
        return span

    steps = [s for s in spans if s["attributes"].get("rr_actors.step")]
    assert {"call", "unload"} <= {s["attributes"]["rr_actors.step"] for s in steps}
    assert all(s["parent_id"] is None for s in steps)  # each step the root of its trace
    assert len(steps) == len({s["context"]["trace_id"] for s in steps})  # a trace each
    # every call and unload a client made is under its step (the loads api made of db too)
    clients = [
        s
        for s in spans
        if s["kind"] == "SpanKind.CLIENT" and s["attributes"]["rr_actors.registrar"] == "client-0"
    ]
    assert clients
    for client in clients:
        step = root(client)
        assert "rr_actors.step" in step["attributes"], client["name"]
        assert step["name"].endswith(" api/resource")
    nested = [s for s in spans if s["kind"] == "SpanKind.SERVER" and s["name"] == "db/resource"]
    assert any("rr_actors.step" in root(s)["attributes"] for s in nested)
    [fault] = [s for s in spans if s["name"] == "fault kill_manager db"]
    assert (None, "kill_manager", "db") == (
        fault["parent_id"],
        fault["attributes"]["rr_actors.fault"],
        fault["attributes"]["rr_actors.target"],
    )
    assert all("the run" == s["resource"]["attributes"]["service.name"] for s in spans)
