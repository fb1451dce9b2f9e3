"""`rr-actors experiment` stopped by signals and by a full disk (issue 21: bug 8 and a weakness).

A second Ctrl-C lands while the finished runs are plotted: no traceback. A SIGTERM stops
the experiment as a Ctrl-C does (exit 143) and leaves no `rr-experiment-*` directory in
the temporary directory; so does a SIGHUP (exit 129; issue 29, item 11), and no process.
A full disk under `--out`: one line, exit 1, and files that agree.
"""

from __future__ import annotations

import contextlib
import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

import psutil
import pytest

from tests.support.small_disk import fill, mounted

SERVICE = "rr_actors.experiments.services:service"

PLAN = f"""\
name = "tiny"
duration = {{duration}}

[tree]
max_restarts = 20

[[tree.children]]
name = "db"
setup = "{SERVICE}"

[workload]
clients = 2
rate = 20.0

[[workload.calls]]
manager = "db"
server = "resource"

[[faults]]
kind = "kill_manager"
target = "db"
at = 0.5
"""

CODE = "import sys; from rr_actors.__main__ import main; sys.exit(main(sys.argv[1:]))"


@pytest.fixture
def tmp_path() -> Iterator[Path]:
    """A short temporary directory (pytest's own, under pytest-xdist, is too long).

    The command's run processes start a forkserver whose socket lives under their
    temporary directory, which is under this one: an AF_UNIX path has at most 107 bytes.
    """
    short = Path(tempfile.mkdtemp(prefix="rr-", dir="/tmp"))
    try:
        yield short
    finally:
        shutil.rmtree(short, ignore_errors=True)


def start(tmp_path: Path, out: Path, *extra: str) -> tuple[subprocess.Popen[str], Path]:
    """The command as a program of its own, with its own temporary directory."""
    plan = tmp_path / "plan.toml"
    plan.write_text(PLAN.format(duration=2.0))
    temp = tmp_path / "temp"
    temp.mkdir()
    cli = subprocess.Popen(
        [sys.executable, "-c", CODE, "experiment", str(plan), "--out", str(out), *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1", "TMPDIR": str(temp)},
    )
    return cli, temp


def rows(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with path.open(newline="") as file:
        return list(csv.DictReader(file))


def alive(token_prefix: str) -> list[int]:
    wanted = f"RR_ACTORS_EXPERIMENT={token_prefix}".encode()
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            environ = (entry / "environ").read_bytes().split(b"\0")
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        if state != "Z" and any(item.startswith(wanted) for item in environ):
            found.append(int(entry.name))
    return found


def finish(cli: subprocess.Popen[str]) -> tuple[str, str]:
    try:
        return cli.communicate(timeout=60)
    finally:
        if cli.poll() is None:
            cli.kill()
            cli.communicate()


@pytest.mark.timeout(180)
def test_a_second_ctrl_c_while_the_runs_are_plotted_prints_no_traceback(
    tmp_path: Path, eventually: Callable[..., bool]
) -> None:
    out = tmp_path / "out"
    cli, temp = start(tmp_path, out, "--repeat", "5")
    try:
        assert eventually(lambda: len(rows(out / "runs.csv")) >= 1, timeout=40)
        assert eventually(lambda: len(alive(f"{cli.pid}-")) > 0, timeout=20)
        cli.send_signal(signal.SIGINT)
        assert eventually(lambda: [] == alive(f"{cli.pid}-"), timeout=30)  # it is cleaning up
        while cli.poll() is None:  # Ctrl-C again and again, while it plots and ends
            cli.send_signal(signal.SIGINT)
            with contextlib.suppress(subprocess.TimeoutExpired):
                cli.wait(timeout=0.05)
    finally:
        stdout, stderr = finish(cli)

    assert 130 == cli.returncode, stderr
    assert "Traceback" not in stderr
    assert "interrupted: " in stdout
    assert (out / "recovery.png").exists()
    assert [] == list(temp.glob("rr-experiment-*"))


@pytest.mark.timeout(180)
def test_sigterm_stops_it_like_ctrl_c_and_leaves_no_work_directory(
    tmp_path: Path, eventually: Callable[..., bool]
) -> None:
    out = tmp_path / "out"
    cli, temp = start(tmp_path, out, "--repeat", "5")
    try:
        assert eventually(lambda: len(list(temp.glob("rr-experiment-*"))) == 1, timeout=20)
        assert eventually(lambda: len(alive(f"{cli.pid}-")) > 0, timeout=20)
        cli.send_signal(signal.SIGTERM)
    finally:
        stdout, stderr = finish(cli)

    assert 143 == cli.returncode, stderr
    assert "Traceback" not in stderr
    assert [] == list(temp.glob("rr-experiment-*"))
    assert [] == alive(f"{cli.pid}-")
    assert "interrupted: " in stdout


@pytest.mark.timeout(180)
@pytest.mark.parametrize(
    ("signum", "code"), [(signal.SIGHUP, 129), (signal.SIGTERM, 143)], ids=["SIGHUP", "SIGTERM"]
)
def test_a_hangup_or_sigterm_leaves_no_work_directory_and_no_process(
    tmp_path: Path, eventually: Callable[..., bool], signum: int, code: int
) -> None:
    out = tmp_path / "out"
    cli, temp = start(tmp_path, out, "--repeat", "5")
    try:
        assert eventually(lambda: len(list(temp.glob("rr-experiment-*"))) == 1, timeout=20)
        assert eventually(lambda: len(alive(f"{cli.pid}-")) > 0, timeout=20)
        started = psutil.Process(cli.pid).children(recursive=True)  # the run's processes
        cli.send_signal(signum)
    finally:
        stdout, stderr = finish(cli)
    _, left = psutil.wait_procs(started, timeout=10)

    assert code == cli.returncode, stderr
    assert [] == list(temp.glob("rr-experiment-*"))
    assert ([], []) == (left, alive(f"{cli.pid}-"))
    assert "interrupted: " in stdout


@pytest.mark.timeout(180)
def test_a_full_disk_under_out_is_one_line_exit_1_and_files_that_agree(tmp_path: Path) -> None:
    with mounted(tmp_path / "disk", size="1m") as disk:
        filler = fill(disk)
        os.truncate(filler, filler.stat().st_size - 8192)  # 8 KiB left: less than a run's events
        out = disk / "out"
        cli, temp = start(tmp_path, out, "--repeat", "2")
        stdout, stderr = finish(cli)

        events = (out / "events.jsonl").read_bytes() if (out / "events.jsonl").exists() else b""
        listed = {row["run"] for row in rows(out / "runs.csv")}
        logged = {str(json.loads(line)["run"]) for line in events.splitlines()}
        faulted = {row["run"] for row in rows(out / "faults.csv")}
        leftovers = sorted(p.name for p in out.iterdir() if p.name.endswith((".tmp", ".png")))

    assert 1 == cli.returncode, stderr
    assert 1 == len(stderr.splitlines()), stderr
    assert stderr.startswith(f"rr-actors experiment: cannot write to {out}/ (No space left")
    assert "run 1 was not added; the files hold the 0 run(s) before it" in stderr
    assert events == b"" or events.endswith(b"\n")  # no run's events cut mid-line
    assert listed == logged == faulted == set()
    assert [] == leftovers
    assert [] == list(temp.glob("rr-experiment-*"))
    assert "Traceback" not in stdout + stderr


@pytest.mark.timeout(180)
def test_a_disk_that_fills_up_after_a_run_keeps_that_run_in_every_file(tmp_path: Path) -> None:
    measure = tmp_path / "measure"
    measured, _ = start(tmp_path, measure, "--repeat", "1")
    assert 0 == measured.wait(timeout=60)
    finish(measured)
    one_run = sum(p.stat().st_size for p in measure.iterdir() if not p.name.endswith(".png"))
    (tmp_path / "temp").rename(tmp_path / "measured-temp")
    with mounted(tmp_path / "disk", size="4m") as disk:
        filler = fill(disk)
        room = (one_run * 3 // 2 // 4096 + 1) * 4096  # run 1 fits (same seed), run 2 does not
        os.truncate(filler, max(0, filler.stat().st_size - room))
        out = disk / "out"
        cli, temp = start(tmp_path, out, "--repeat", "2")
        stdout, stderr = finish(cli)

        events = (out / "events.jsonl").read_bytes()
        listed = {row["run"] for row in rows(out / "runs.csv")}
        logged = {str(json.loads(line)["run"]) for line in events.splitlines()}
        faulted = {row["run"] for row in rows(out / "faults.csv")}

    assert 1 == cli.returncode, stdout + stderr
    # One line says what was lost; a plot that no longer fits either (how much room the
    # run left depends on how many events it had, which a loaded machine changes) says so
    # in one line of its own.
    said = stderr.splitlines()
    assert 1 == len([line for line in said if "run 2 was not added" in line]), stderr
    assert "run 2 was not added; the files hold the 1 run(s) before it" in stderr
    assert all(
        "run 2 was not added" in line or line.endswith(".png not drawn: No space left on device")
        for line in said
    ), stderr
    assert events.endswith(b"\n")
    assert listed == logged == faulted == {"1"}
    assert [] == list(temp.glob("rr-experiment-*"))
