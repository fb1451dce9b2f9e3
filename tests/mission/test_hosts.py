"""`rr-actors demo --hosts 2`: the mission on two hosts (network namespaces), F6, cleanup.

The demo runs as a command, as a user runs it: it makes two namespaces joined by a veth,
the certificates, the station's process inside one and the robot's inside the other,
and deletes all of it at the end. The end-to-end test and the Ctrl-C test need root (CI
runs as root); the no-root test gives the check another user id.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from rr_actors.mission.run import main
from tests.mission.test_cli_interrupt import interrupt_demo, one_line_after_the_story

ROOT = Path(__file__).resolve().parents[2]

needs_root = pytest.mark.skipif(
    os.geteuid() != 0 or shutil.which("ip") is None,
    reason="needs root and iproute2's ip: two network namespaces",
)


def _running(pid: int) -> bool:
    try:
        return bool(psutil.Process(pid).status() != psutil.STATUS_ZOMBIE)
    except psutil.NoSuchProcess:
        return False


def ours(within: float = 10.0) -> list[str]:
    """`_ended()`, waited on for at most `within` seconds until it is empty: a demo whose
    pid ended may still be deleting its namespaces (another process of it does that)."""
    deadline = time.monotonic() + within
    left = _ended()
    while left and time.monotonic() < deadline:
        time.sleep(0.1)  # allowed: polling `ip netns list`, no event says a namespace went
        left = _ended()
    return left


def _ended() -> list[str]:
    """The demo namespaces on this machine (`rrdemo-<pid>-...`) whose demo has ended.

    A demo deletes its namespaces before it exits; those of a demo still running (another
    test's, beside this one under pytest-xdist) are not counted: left ones are a leak.
    """
    done = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, check=True)  # noqa: S607
    names = [line.split()[0] for line in done.stdout.splitlines() if line.strip()]
    left = []
    for name in names:
        parts = name.split("-")
        if parts[0] != "rrdemo" or len(parts) < 3 or not parts[1].isdigit():
            continue
        if not _running(int(parts[1])):
            left.append(name)
    return left


def demo(*options: str, cwd: Path, timeout: float = 150) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, "-m", "rr_actors", "demo", *options],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        check=False,
    )


@needs_root
@pytest.mark.timeout(200)
def test_the_two_host_demo_cuts_the_link_recovers_every_fault_and_leaves_nothing(
    tmp_path: Path,
) -> None:
    before = set(ours())

    done = demo("--hosts", "2", "--fast", "--out", "out", cwd=tmp_path)

    assert 0 == done.returncode, done.stdout + done.stderr
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert ["F1", "F2", "F3", "F4", "F5", "F6"] == [f["id"] for f in report["faults"]]
    injected = [f["injected_at_s"] for f in report["faults"]]
    assert sorted(injected) == injected  # in that order
    assert all(f["recovered_after_s"] is not None for f in report["faults"])
    hosts = [f["host"] for f in report["faults"]]
    assert ["robot", "robot", "robot", "station", "robot", "both"] == hosts
    cut = report["faults"][-1]["details"]
    # (whether a call is made while the link is down depends on the timing: none may be)
    failed, slowest = cut["calls_failed_during_cut"], cut["slowest_failed_call_s"]
    assert failed == 0 or slowest < 8.0  # a call in flight fails by the lease (3 s), no hang
    assert cut["station_saw_cut_after_s"] is not None
    assert cut["robot_saw_cut_after_s"] is not None
    assert ["erm", "rm"] == report["hosts"]["robot"]["managers"]
    assert ["cm"] == report["hosts"]["station"]["managers"]
    assert "robot_stopped_at_cut_s" in report["hosts"]["robot"]
    assert 0 == report["leaked_processes"]
    assert 0 == report["catalog_entries_left"]
    story = done.stdout
    assert "robot: the station is gone" in story
    assert "F6 recovered" in story
    assert "F6 both" in story  # the timeline names the hosts
    after = story.split("F6 recovered", 1)[1].split("goal reached", 1)[0]
    late = [line for line in " ".join(after.split()).split("[") if "hears FATAL" in line]
    assert all("(late: the mission let go of that query" in line for line in late), after
    assert "state:  out/state (rr-actors inspect out/state/robot/erm.db)" in story  # (relative)
    assert all(len(line) <= 80 for line in story.splitlines()), story
    # F6's loss is the story's to tell: cm's WARNING (a station manager process) goes to
    # the run's log with the mission's own, not to the terminal
    assert "" == done.stderr
    log = (tmp_path / "out" / "rr-actors.log").read_text()
    assert "registrar cm: erm is gone and nobody will restart it" in log
    assert before == set(ours())  # its namespaces (and the veth in them) are gone
    for record in (tmp_path / "out" / "bus" / "pids").glob("*.json"):
        pid = json.loads(record.read_text())["pid"]
        assert not psutil.pid_exists(pid) or psutil.Process(pid).status() == "zombie"


def test_without_root_the_two_host_demo_says_what_to_run_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # (as `nobody` the interpreter cannot read this machine's site-packages: the check
    # is given another user id instead)
    monkeypatch.setattr(os, "geteuid", lambda: 1000)

    code = main(["--hosts", "2", "--fast", "--out", str(tmp_path / "o")])

    out, err = capsys.readouterr()
    assert 2 == code
    assert "" == out
    assert [
        "rr-actors demo: --hosts 2 needs root (it makes two network namespaces): run "
        "`sudo rr-actors demo --hosts 2`, or `rr-actors demo` for the mission on one host"
    ] == err.splitlines()


@needs_root
@pytest.mark.usefixtures("process_helpers")
@pytest.mark.timeout(200)
def test_ctrl_c_on_two_hosts_prints_one_line_exits_130_and_deletes_the_namespaces(
    tmp_path: Path,
) -> None:
    before = set(ours())

    code, shown, after, tree = interrupt_demo(tmp_path, b"driving", "--hosts", "2")

    assert "driving" in shown
    assert 130 == code, after
    assert one_line_after_the_story(after), after
    assert "Traceback" not in after
    _, alive = psutil.wait_procs(tree, timeout=20)
    assert [] == alive
    assert before == set(ours())
