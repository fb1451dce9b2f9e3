"""`rr-actors events`: every host's events as JSON lines (`--network`), or files merged (`--merge`).

The live stream runs in a child process (`python -m rr_actors events ...`) against a
`ZenohNetwork` of this process on loopback (plain TCP, `--plain`): it prints what this
process's registrar does, one `events.to_dict` line per event, and ends after `--count`.
"""

from __future__ import annotations

import io
import json
import socket
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

import rr_actors as rr
from rr_actors import events
from rr_actors.__main__ import main
from rr_actors._core import hlc
from tests.support.terminal import on_a_terminal

BOUND = 30.0


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def test_merge_prints_the_files_events_ordered_by_hlc(tmp_path: Path) -> None:
    robot = [
        events.ConsumerAdded("erm", "r1", "q1", "app", at=105.0, pid=2, host="robot", hlc=10),
        events.ResourceLoaded("erm", "cam", "r1", "q1", 0.1, at=104.0, pid=2, host="robot", hlc=9),
    ]
    operator = [
        events.CallAnswered("app", "q1", "erm", "cam", at=100.0, pid=1, host="operator", hlc=11)
    ]
    (tmp_path / "robot.jsonl").write_text(
        "".join(json.dumps(events.to_dict(e)) + "\n" for e in robot)
    )
    (tmp_path / "operator.jsonl").write_text(
        "".join(json.dumps(events.to_dict(e)) + "\n" for e in operator)
    )
    out = io.StringIO()

    code = main(
        ["events", "--merge", str(tmp_path / "operator.jsonl"), str(tmp_path / "robot.jsonl")], out
    )

    assert 0 == code
    printed = [events.from_dict(json.loads(line)) for line in out.getvalue().splitlines()]
    assert [robot[1], robot[0], operator[0]] == printed  # by hlc, not by file nor by `at`


def test_merge_names_the_file_and_line_of_what_is_not_an_event(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"type": "Exploded", "schema": 3}\n')
    assert 1 == main(["events", "--merge", str(bad)], io.StringIO())
    assert f"{bad} line 1" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "named"),
    [
        ([], "--network"),
        (["--network", "tls/10.0.0.1:7447"], "--system"),
        (["--network", "tls/10.0.0.1:7447", "--system", "lab"], "--certs"),
        (
            ["--network", "tcp/10.0.0.1:7447", "--system", "lab", "--plain", "--member", "x"],
            "--plain",
        ),
    ],
)
def test_without_what_joins_the_system_it_says_what_is_missing(
    argv: list[str], named: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert 1 == main(["events", *argv], io.StringIO())
    assert named in capsys.readouterr().err


def test_the_live_stream_prints_what_a_registrar_of_the_system_does() -> None:
    port = _free_port()
    system = f"cli-{uuid.uuid4().hex[:8]}"
    net = rr.ZenohNetwork(system=system, listen=[f"tcp/127.0.0.1:{port}"], tls=None)
    erm = rr.ResourceRegistrar.start(rr.RegistrarConfig(name="erm"), network=net)
    erm.register_server("camera", load=lambda request: request, unload=lambda *_: None)
    command = [sys.executable, "-m", "rr_actors", "events", "--network"]
    command += [f"tcp/127.0.0.1:{port}", "--system", system, "--plain", "--count", "3"]
    child = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        probe = 0
        while True:  # (its subscription reaches this process a little after it starts)
            probe += 1
            erm.unload(erm.call("erm", "camera", {"probe": probe}).id)
            try:
                out, err = child.communicate(timeout=0.2)
                break
            except subprocess.TimeoutExpired:
                assert probe < BOUND / 0.2, "rr-actors events printed nothing"
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
        erm.stop()
        net.close()
    assert 0 == child.returncode, err
    printed = [json.loads(line) for line in out.splitlines()]
    assert 3 == len(printed)
    assert {"erm"} == {line["registrar"] for line in printed}
    assert [line["hlc"] for line in printed] == sorted(line["hlc"] for line in printed)
    assert all(line["schema"] == events.lines.SCHEMA for line in printed)


# -- an experiment's events.jsonl --------------------------------------------------------------

PLAN = """\
name = "merged"
duration = 1.0
repeat = 2
seed = 7

[tree]
strategy = "one_for_one"

[[tree.children]]
name = "db"
setup = "rr_actors.experiments.services:service"

[workload]
clients = 1
rate = 10.0
hold = 0.2

[[workload.calls]]
manager = "db"
server = "resource"

[[faults]]
kind = "kill_manager"
target = "db"
at = [0.5]
"""


def _rr_actors(*argv: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(  # noqa: PLW1510 - the exit code is what is checked
        [sys.executable, "-m", "rr_actors", *argv],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.mark.timeout(180)
def test_merge_reads_an_experiments_events_file_with_its_runs_and_faults(tmp_path: Path) -> None:
    """An experiment adds `run` and `seed` to each event and writes a line per fault: the
    file merges as it is (it was refused: `unknown fields ['run', 'seed']`, exit 1;
    issue 44). Every line comes out once, unchanged, the events in `hlc` order and each
    fault at its `at`, among the events of its run."""
    (tmp_path / "plan.toml").write_text(PLAN)
    ran = _rr_actors("experiment", "plan.toml", "--out", "out", cwd=tmp_path)
    assert 0 == ran.returncode, ran.stderr
    written = (tmp_path / "out" / "events.jsonl").read_text().splitlines()
    station = events.ConsumerAdded("erm", "r1", "q1", "app", at=1.0, pid=9, host="station")
    (tmp_path / "station.jsonl").write_text(json.dumps(events.to_dict(station)) + "\n")

    merged = _rr_actors("events", "--merge", "out/events.jsonl", "station.jsonl", cwd=tmp_path)

    assert (0, "") == (merged.returncode, merged.stderr)
    lines = merged.stdout.splitlines()
    assert sorted([*written, json.dumps(events.to_dict(station))]) == sorted(lines)
    printed = [json.loads(line) for line in lines]
    faults = [line for line in printed if line["type"] == "FaultInjected"]
    assert [(1, 7), (2, 8)] == [(fault["run"], fault["seed"]) for fault in faults]
    stamps = [hlc.from_seconds(p["at"]) if "hlc" not in p else p["hlc"] for p in printed]
    assert stamps == sorted(stamps)
    assert {(1, 7), (2, 8)} == {(p["run"], p["seed"]) for p in printed if "run" in p}
    assert 1 == sum("run" not in p for p in printed)  # the station's event


REFUSED = {
    # name: (the line, what the refusal says)
    "a field of neither": (
        json.dumps(
            {**events.to_dict(events.ResourceLoaded("erm", "cam", "r1", "q1", 0.1)), "x": 1}
        ),
        "out/events.jsonl line 1: ResourceLoaded: unknown fields ['x']",
    ),
    "an event without some of its fields": (
        json.dumps({"type": "ResourceLoaded", "query_id": "q1", "load_s": 0.1, "schema": 3}),
        "out/events.jsonl line 1: ResourceLoaded: missing fields ['registrar', 'server', "
        "'resource_id', 'digest', 'label', 'at', 'pid', 'seq', 'host', 'hlc']",
    ),
    "not JSON": (
        '{"type": ResourceLoaded}',
        "out/events.jsonl line 1: not JSON (column 10: Expecting value)",
    ),
    "a run that is no number": (
        json.dumps({**events.to_dict(events.ChildStarted("root", "db", 4)), "run": "one"}),
        "out/events.jsonl line 1: run must be an int >= 0, got 'one'",
    ),
}


@pytest.mark.parametrize("refused", sorted(REFUSED))
def test_what_merge_refuses_is_one_line_in_a_pipe_and_fits_80_columns_on_a_terminal(
    tmp_path: Path, refused: str
) -> None:
    """One line naming the file, the line and the problem (exit 1); on an 80-column
    terminal that line wraps at words (`out/events.jsonl line 1: ...` and the problem
    take more than 80 columns with the prefix `rr-actors events: `)."""
    line, says = REFUSED[refused]
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "events.jsonl").write_text(line + "\n")
    argv = ["events", "--merge", "out/events.jsonl"]

    piped = _rr_actors(*argv, cwd=tmp_path)
    code, shown = on_a_terminal(
        [sys.executable, "-m", "rr_actors", *argv], columns=80, timeout=60, cwd=tmp_path
    )

    assert (1, 1) == (piped.returncode, code)
    assert [f"rr-actors events: {says}"] == piped.stderr.splitlines()
    wide = [f"[{len(row)}] {row}" for row in shown.splitlines() if len(row) > 80]
    assert [] == wide, "lines over 80 columns:\n" + "\n".join(wide)
    assert " ".join(f"rr-actors events: {says}".split()) == " ".join(shown.split())
