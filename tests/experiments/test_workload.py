"""The workload (`rr_actors_lab.experiments.workload`) when a client cannot build a request: the
run fails, naming the cause; awaited and cancelled calls; fetches."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import pytest

from rr_actors_lab.experiments import ExperimentError, load_plan, run

PLAN = """\
name = "bad-factory"
duration = 120.0  # longer than pytest-timeout: the run must end when the client fails

[tree]
[[tree.children]]
name = "api"
setup = "rr_actors_lab.experiments.services:service"
isolation = "thread"

[workload]
clients = 2
rate = 20.0

[[workload.calls]]
manager = "api"
server = "resource"
factory = "bad_factory:request"
"""


def test_a_factory_that_raises_fails_the_run_at_once_with_its_error(tmp_path: Path) -> None:
    (tmp_path / "bad_factory.py").write_text(
        textwrap.dedent(
            """\
            def request(key, context):
                raise ValueError("boom")
            """
        )
    )
    (tmp_path / "plan.toml").write_text(PLAN)

    with pytest.raises(ExperimentError) as caught:
        run(load_plan(tmp_path / "plan.toml"))

    assert "run 1 failed (exit code 1)" in str(caught.value)
    assert (
        "ConfigError: workload.calls[0]: factory 'bad_factory:request' raised "
        "ValueError('boom') for key "
    ) in str(caught.value)


AWAITED = """\
name = "awaited"
duration = 1.0

[tree]
[[tree.children]]
name = "api"
setup = "rr_actors_lab.experiments.services:service"
options = { load_s = 0.002 }

[workload]
clients = 1
rate = 5.0
hold = 0.05
awaited = 40
cancel = 0.5
cancel_within = 0.004

[[workload.calls]]
manager = "api"
server = "resource"
shared = 1.0
keys = 4
"""

GATED = """\
name = "awaited"
duration = 3.0  # (room for the second batch, the first gated one, on a loaded machine)

[tree]
[[tree.children]]
name = "api"
setup = "gate:gated"
isolation = "thread"  # (in the run's process: it hears its client's events)

[workload]
clients = 1
rate = 5.0
arrivals = "fixed"
hold = 0.05
awaited = 40
cancel = 0.5
cancel_within = 0.004

[[workload.calls]]
manager = "api"
server = "resource"
factory = "gate:request"
shared = 1.0
keys = 4
"""

GATE = """\
import itertools
import threading

from rr_actors import events

_made = itertools.count()


def request(key, context):
    # Gated from the second batch of 40 on: the first one's cancels may come while the
    # client's actor starts (before its call is sent); later calls are sent at once.
    return (key, next(_made) >= 40)


def gated(registrar):
    # A gated load answers only once a cancelled call was withdrawn: the calls of its
    # batch are all in flight when cancelled, whatever the machine's load (rule 17 broken:
    # its bound, longer than the calls' timeout).
    withdrawn = threading.Event()

    def heard(event):
        if isinstance(event, events.CallWithdrawn) and event.reason == "interrupted":
            withdrawn.set()

    events.everything().subscribe(heard)

    def load(request):
        key, gate = request
        if gate:
            withdrawn.wait(10.0)
        return key

    registrar.register_server("resource", load=load, unload=lambda _request, _response: None)
"""


def test_awaited_calls_a_share_of_which_are_cancelled_leave_nothing_held(tmp_path: Path) -> None:
    (tmp_path / "gate.py").write_text(GATE)
    (tmp_path / "plan.toml").write_text(GATED)

    results = run(load_plan(tmp_path / "plan.toml"), out=tmp_path / "out")

    [row] = results.rows()
    lines = (tmp_path / "out" / "events.jsonl").read_text().splitlines()
    withdrawn = [line for line in lines if '"type": "CallWithdrawn"' in line]
    assert withdrawn  # (cancelled before their answers: the awaiting tasks were cancelled)
    assert all('"reason": "interrupted"' in line for line in withdrawn)
    assert (0, 0, "held") == (row["calls_failed"], row["catalog_entries_left"], row["verdict"])
    assert row["calls_ok"] > 0


FETCHING = AWAITED.replace(
    "rate = 5.0\nhold = 0.05\nawaited = 40\ncancel = 0.5\ncancel_within = 0.004\n",
    "rate = 20.0\nhold = 0.05\nfetch_every = 2\n",
)


def test_a_workload_that_fetches_publishes_what_each_fetch_listed_and_holds(
    tmp_path: Path,
) -> None:
    (tmp_path / "plan.toml").write_text(FETCHING)

    results = run(load_plan(tmp_path / "plan.toml"), out=tmp_path / "out")

    [row] = results.rows()
    lines = (tmp_path / "out" / "events.jsonl").read_text().splitlines()
    fetched = [json.loads(line) for line in lines if '"type": "QueriesFetched"' in line]
    answered = {json.loads(line)["query_id"] for line in lines if '"type": "CallAnswered"' in line}
    # one fetch after every 2 calls, each of client-0 at api/resource, listing its own ids
    assert "fetch_every = 2" in FETCHING
    assert (row["calls_ok"] + row["calls_failed"]) // 2 == len(fetched) > 0
    assert {("client-0", "api", "resource")} == {
        (f["registrar"], f["serving_rr"], f["server"]) for f in fetched
    }
    assert all(f["started"] < f["hlc"] for f in fetched)
    assert {q for f in fetched for q in f["query_ids"]} <= answered
    assert any(f["query_ids"] for f in fetched)
    assert (0, "held") == (row["calls_failed"], row["verdict"])


AGAIN = AWAITED.replace(
    "rate = 5.0\nhold = 0.05\nawaited = 40\ncancel = 0.5\ncancel_within = 0.004\n",
    'rate = 10.0\narrivals = "fixed"\nhold = 0.2\n',
).replace("keys = 4\n", "keys = 4\nagain = 1.0\n")


def test_a_workload_that_calls_again_calls_each_held_id_again_and_holds(tmp_path: Path) -> None:
    # `again = 1.0`: every answered call is called again with its id while it is held; the
    # provider, which holds it, answers that retry as one (rule 2), and it is released once
    (tmp_path / "plan.toml").write_text(AGAIN)

    results = run(load_plan(tmp_path / "plan.toml"), out=tmp_path / "out")

    [row] = results.rows()
    lines = (tmp_path / "out" / "events.jsonl").read_text().splitlines()
    answered = [json.loads(line) for line in lines if '"type": "CallAnswered"' in line]
    first = {a["query_id"] for a in answered if not a["retry"]}
    again = {a["query_id"] for a in answered if a["retry"]}
    added = [line for line in lines if '"type": "ConsumerAdded"' in line]
    assert "again = 1.0" in AGAIN
    assert first
    assert again <= first
    assert len(first - again) <= 3  # (not the few due after the last call: hold / gap + 1)
    assert len(first) == len(added)  # (a retry of a held id adds nothing)
    assert (0, 0, "held") == (row["calls_failed"], row["catalog_entries_left"], row["verdict"])
    assert len(first) + len(again) == row["calls_ok"]
