"""The ERM re-adopt example: pid AND creation time, so pid reuse cannot fool it."""

from __future__ import annotations

import importlib.util
import os
import re
import signal
import subprocess
import sys
from pathlib import Path
from types import ModuleType

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "readopt_processes.py"


def load_example() -> ModuleType:
    spec = importlib.util.spec_from_file_location("readopt_processes", EXAMPLE)
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_running_process_is_recognised_by_pid_and_start_time() -> None:
    example = load_example()

    assert example.same_process(os.getpid(), example.process_start_time(os.getpid()))


def test_a_live_pid_with_another_start_time_is_not_our_process() -> None:
    example = load_example()
    start = example.process_start_time(os.getpid())

    assert not example.same_process(os.getpid(), start + 1)


def test_a_pid_that_no_longer_runs_is_not_our_process() -> None:
    example = load_example()
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    start = example.process_start_time(child.pid)
    child.wait(10.0)

    assert not example.same_process(child.pid, start)


WAITS = [sys.executable, "-c", "import sys; sys.stdin.read()"]  # runs until stdin closes


def test_a_process_with_another_start_time_gets_no_signal() -> None:
    example = load_example()
    with subprocess.Popen(WAITS, stdin=subprocess.PIPE) as child:
        try:
            start = example.process_start_time(child.pid)
            sent = example.signal_process(child.pid, start + 1, signal.SIGTERM)
            assert (False, None) == (sent, child.poll())
        finally:
            child.kill()


def test_our_process_is_signalled_through_its_pidfd() -> None:
    example = load_example()
    with subprocess.Popen(WAITS, stdin=subprocess.PIPE) as child:
        try:
            start = example.process_start_time(child.pid)
            sent = example.signal_process(child.pid, start, signal.SIGTERM)
            assert (True, -signal.SIGTERM) == (sent, child.wait(10.0))
        finally:
            child.kill()


def test_the_restarted_erm_re_adopts_the_process_that_still_runs_and_unloads_it() -> None:
    result = subprocess.run(
        [sys.executable, str(EXAMPLE)], capture_output=True, text=True, timeout=60, check=False
    )

    assert 0 == result.returncode, result.stderr
    # The one line on standard error is the supervisor's WARNING of the SIGKILL the example
    # makes (rr_actors' WARNINGs reach stderr, with their level and logger, when no logging
    # is configured).
    assert re.fullmatch(
        r"WARNING rr_actors: supervisor supervisor-\d+: child erm-\w+ exited: killed by SIGKILL\n",
        result.stderr,
    ), result.stderr
    pid = result.stdout.split("ERM started process ")[1].split()[0]
    assert f"ERM re-adopted process {pid} (pid and start time match)" in result.stdout
    assert f"running after restart: [{pid}]" in result.stdout
    assert "status for the process that ended: ['FATAL: process ended while the ERM was down']" in (
        result.stdout
    )
    assert f"process {pid} stopped by unload after the restart: True" in result.stdout
