"""What the demo's tests share: `rr-actors demo` interrupted as a terminal's Ctrl-C would
(SIGINT to its whole process group, on a pseudo-terminal), and the network namespaces a
two-host demo may leave behind."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import psutil

from rr_actors_lab.mission import FAULTS, FaultResult, MissionReport, UnplannedRestart
from tests.support import selecting

ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")
LINE = re.compile(r"^interrupted at \d+\.\d s: unloading\.\.\. everything unloaded$")
STORY = re.compile(r"^\[\s*\d+\.\d+ s\] ")  # a line of the story ("[  0.77 s] driving ...")
PROMPT = "press Enter to inject it"  # --step's prompt, redrawn as the terminal's lines settle


def one_line_after_the_story(after: str) -> bool:
    """Whether the output after the SIGINT is the one line, after at most story lines.

    A story line the demo was printing as the signal came (its printer thread does not
    wait for the prompt), or the rest of the prompt's line, may still land first on a
    loaded machine.
    """
    *story, last = after.splitlines() or [""]
    return bool(LINE.match(last)) and all(
        STORY.match(line) or line.startswith(PROMPT) for line in story
    )


def interrupt_demo(tmp_path: Path, when: bytes, *options: str) -> tuple[int, str, str, list]:
    """Run the demo on a pty, SIGINT its process group once `when` shows; wait for its end.

    Returns:
        The exit code, the output before the SIGINT, the output after it, and the
        processes of the demo's tree when it was sent.
    """
    master, slave = os.openpty()
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES", "NO_COLOR")}
    demo = subprocess.Popen(
        [sys.executable, "-m", "rr_actors_lab", "demo", "--fast", *options],
        cwd=tmp_path,
        stdin=slave,
        stdout=slave,
        stderr=slave,
        env={**env, "TERM": "xterm-256color"},
        start_new_session=True,  # its own process group, as a terminal's foreground job
    )
    os.close(slave)
    before = after = b""
    tree: list[psutil.Process] = []
    deadline = time.monotonic() + 90
    try:
        while time.monotonic() < deadline:
            readable, _, _ = selecting.select([master], [], [], 1.0)
            if readable:
                try:
                    chunk = os.read(master, 65536)
                except OSError:  # the demo ended: its side of the terminal closed
                    break
                if not chunk:
                    break
                if tree:
                    after += chunk
                else:
                    before += chunk
            if not tree and when in before:
                tree = psutil.Process(demo.pid).children(recursive=True)
                os.killpg(demo.pid, signal.SIGINT)  # what Ctrl-C in its terminal does
        code = demo.wait(30)
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait(10)
        os.close(master)
    return code, clean(before), clean(after), tree


def clean(output: bytes) -> str:
    """The text a reader sees: no colours, no redrawn progress lines, no blank lines."""
    text = ANSI.sub("", output.decode(errors="replace"))
    lines = (line.rsplit("\r", 1)[-1].strip() for line in text.replace("\r\n", "\n").split("\n"))
    return "\n".join(line for line in lines if line and "━" not in line)


def assert_nothing_left(tmp_path: Path, tree: list[psutil.Process]) -> None:
    """Every process of the demo's tree ends (bounded), and no program of the mission lives."""
    assert tree  # the managers were running
    _, alive = psutil.wait_procs(tree, timeout=20)  # the forkserver ends after the demo
    assert [] == alive
    for record in (tmp_path / "rr-actors-demo" / "bus" / "pids").glob("*.json"):
        pid = json.loads(record.read_text())["pid"]
        assert not psutil.pid_exists(pid) or psutil.Process(pid).status() == "zombie"


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


def report_with_everything() -> MissionReport:
    """A report of a long mission: all five faults and an unplanned restart of each manager."""
    faults = tuple(
        FaultResult(f, "x" * 40, 100.0 + i, 12.345, 123.456, 99.999) for i, f in enumerate(FAULTS)
    )
    restarts = tuple(UnplannedRestart(m, 200.0, 4_194_304) for m in ("erm", "cm", "rm"))
    return MissionReport(
        mission_time_s=1234.5,
        distance_m=160.0,
        nominal_time_s=320.0,
        faults=faults,
        leaked_processes=0,
        catalog_entries_left=0,
        catalog_entries_by_registrar={},
        trace=(),
        stops=(),
        unplanned_restarts=restarts,
    )


def console_spans(text: str) -> list[dict[str, Any]]:
    """The spans OpenTelemetry's console exporter printed in `text` (one JSON object each;
    other lines, the story's, skipped)."""
    decoder = json.JSONDecoder()
    spans, at = [], text.find("{")
    while at >= 0:
        try:
            span, end = decoder.raw_decode(text, at)
        except ValueError:
            end = at + 1
        else:
            if isinstance(span, dict) and "context" in span:
                spans.append(span)
        at = text.find("{", end)
    return spans


STEPS = ("load robot", "load lidar1", "drive", "unload")
"""The mission's steps, each a trace of its own (`mission step <step>`) with `--trace`."""


def assert_one_trace_per_step(stdout: str) -> list[dict[str, Any]]:
    """The spans of `demo --faults F4 --trace` (console exporter): each mission step one
    trace, every parent exported, `restart cm` linked to both incarnations; the spans."""
    spans = console_spans(stdout)
    by_id = {span["context"]["span_id"]: span for span in spans}
    assert {"SpanKind.CLIENT", "SpanKind.SERVER", "SpanKind.INTERNAL"} <= {
        span["kind"] for span in spans
    }
    orphans = [s["name"] for s in spans if s["parent_id"] and s["parent_id"] not in by_id]
    assert [] == orphans  # (an unload's dependency releases: their CLIENT spans too)
    steps = {s["name"]: s["context"]["trace_id"] for s in spans if not s["parent_id"]}
    assert {f"mission step {name}" for name in STEPS} <= set(steps)
    roots = {trace: name for name, trace in steps.items()}
    assert len(roots) == len(steps)  # one root a trace: each step a trace of its own
    # (F4 kills cm while the robot stands: its restart is a trace of its own, linked)
    assert {"restart cm"} == set(roots.values()) - {f"mission step {n}" for n in STEPS}
    for span in spans:  # every call, load and unload is in the trace of its step
        if span["name"] != "restart cm":
            assert roots[span["context"]["trace_id"]].startswith("mission step"), span["name"]
    unloaded = [s for s in spans if s["context"]["trace_id"] == steps["mission step unload"]]
    assert {"rm/robot", "cm/lidar", "erm/program", "robot.unload", "program.unload"} <= {
        s["name"] for s in unloaded
    }
    (restart,) = [s for s in spans if s["name"] == "restart cm"]
    linked = {
        link["attributes"]["rr_actors.incarnation"]: by_id[link["context"]["span_id"]]["name"]
        for link in restart["links"]
    }
    assert {"old": "cm/lidar", "new": "cm/lidar"} == linked
    return spans
