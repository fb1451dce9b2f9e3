"""`rr-actors events`: every host's events as JSON lines (`--network`), or files merged (`--merge`).

The live stream runs in a child process (`python -m rr_actors._cli events ...`) against a
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
    command = [sys.executable, "-m", "rr_actors._cli", "events", "--network"]
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
