"""Every example runs to completion as its own program (the smoke test STYLE.md asks for)."""

from __future__ import annotations

import ast
import importlib.util
import re
import subprocess
import sys
import threading
import tomllib
from pathlib import Path

import pytest

from tests.support.python import python

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
EXTRAS = tomllib.loads((EXAMPLES.parent / "pyproject.toml").read_text())["project"][
    "optional-dependencies"
]


def run_example(name: str) -> subprocess.CompletedProcess[str]:
    """Run `examples/<name>` with this interpreter; fail the test after 45 s."""
    return python(str(EXAMPLES / name), timeout=45)


def test_quickstart_loads_hears_a_status_unloads_and_exits_cleanly() -> None:
    result = run_example("quickstart.py")

    assert (0, "") == (result.returncode, result.stderr)
    assert "response: 'hello, world'; shared: True" in result.stdout
    assert "heard WARNING: battery low" in result.stdout
    assert 1 == result.stdout.count("unloaded 'hello, world'")


FILTERED_CAMERA_RUNS = 6
"""How often the filtered camera story runs: its lines come from several threads."""

STORY_LINE = re.compile(r"\[[ \w-]{8}\] \S.*")
"""One line of the filtered camera story: an 8-column tag, a space, the text."""

TAG = re.compile(r"\[[ \w-]{8}\] ")


@pytest.fixture(scope="module")
def filtered_camera_runs() -> list[subprocess.CompletedProcess[str]]:
    """`examples/filtered_camera.py`, run `FILTERED_CAMERA_RUNS` times."""
    return [run_example("filtered_camera.py") for _ in range(FILTERED_CAMERA_RUNS)]


def test_filtered_camera_is_loaded_once_for_two_actions(
    filtered_camera_runs: list[subprocess.CompletedProcess[str]],
) -> None:
    result = filtered_camera_runs[0]

    assert (0, "") == (result.returncode, result.stderr)
    assert "filtered_camera loaded 1 time(s) for 2 consumers" in result.stdout
    assert "both actions share one camera and one filter process: True" in result.stdout


def test_filtered_camera_failure_reaches_both_actions_then_everything_stops(
    filtered_camera_runs: list[subprocess.CompletedProcess[str]],
) -> None:
    for result in filtered_camera_runs:
        out = result.stdout

        assert 0 == result.returncode
        assert "[      cm] filtered_camera hears FATAL from erm/camera" in out
        assert "[action-1] heard FATAL" in out
        assert "[action-2] heard FATAL" in out
        assert 1 == out.count("stopped camera pid")
        assert 1 == out.count("stopped filter pid")
        for name in ("action-1", "action-2", "cm", "erm"):
            assert f"stopped registrar {name}" in out
        assert out.rstrip().endswith("done")


def test_filtered_camera_prints_every_line_whole_in_every_run(
    filtered_camera_runs: list[subprocess.CompletedProcess[str]],
) -> None:
    glued = [
        line
        for result in filtered_camera_runs
        for line in result.stdout.splitlines()
        if not STORY_LINE.fullmatch(line) or len(TAG.findall(line)) != 1
    ]

    assert [] == glued


def test_filtered_camera_say_writes_whole_lines_from_many_threads(
    capfd: pytest.CaptureFixture[str],
) -> None:
    spec = importlib.util.spec_from_file_location(
        "filtered_camera", EXAMPLES / "filtered_camera.py"
    )
    assert spec is not None
    assert spec.loader is not None
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # switch threads as often as possible: races show at once
    try:
        threads = [
            threading.Thread(target=lambda n=n: [example.say(f"t{n}", str(i)) for i in range(300)])
            for n in range(8)
        ]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(10)
    finally:
        sys.setswitchinterval(interval)
    lines = capfd.readouterr().out.splitlines()

    assert 8 * 300 == len(lines)
    assert [] == [line for line in lines if not re.fullmatch(r"\[ {6}t\d\] \d+", line)]


def test_the_asyncio_service_shares_a_camera_streams_its_frames_and_unloads_it() -> None:
    # A real Starlette app on uvicorn, a real socket, httpx as the client: the example
    # plays the client against itself (POST twice, stream server-sent events and leave
    # the stream, DELETE). The stream's watch is closed once the client left: a bare
    # `async for` over `watch()` left it open (1), the query's status callback for good.
    result = run_example("asyncio_service.py")

    assert (0, "") == (result.returncode, result.stderr)
    assert [
        "opened rtsp://robot/front twice: ids differ: True",
        "heard 2 frames: True",
        "event streams open once the client left: 0",
        "closing it again: 404",
        "service stopped: the tree and its registrars with it",
    ] == [line for line in result.stdout.splitlines() if not line.startswith("closed ")]
    assert 2 == sum(line.endswith(": 204") for line in result.stdout.splitlines())


def _needs(example: Path) -> set[str]:
    """The distributions an example imports at its top level, beyond the standard library
    and rr_actors (an import inside a function is optional: the example says so)."""
    top = ast.parse(example.read_text()).body
    names = {a.name for n in top if isinstance(n, ast.Import) for a in n.names}
    names |= {n.module for n in top if isinstance(n, ast.ImportFrom) and n.module and not n.level}
    ours = {"rr_actors", "rr_actors_lab"}  # the runtime and the lab: one distribution
    roots = {name.split(".")[0] for name in names} - {*sys.stdlib_module_names, *ours}
    return {root.replace("_", "-") for root in roots - {"__future__"}}


@pytest.mark.parametrize("example", sorted(EXAMPLES.glob("*.py")), ids=lambda p: p.name)
def test_an_example_that_needs_more_than_rr_actors_names_the_extra_that_installs_it(
    example: Path,
) -> None:
    """A new user reads the example's docstring: `pip install -e ".[X]"` in it, and X
    installs every package the example imports."""
    needs = _needs(example)
    if not needs:
        return
    docstring = ast.get_docstring(ast.parse(example.read_text())) or ""
    named = re.search(r'pip install -e "\.\[(?P<extra>[\w-]+)\]"', docstring)
    assert named is not None, f"{example.name} imports {sorted(needs)}: name the extra"
    installed = {re.split(r"[<>=\[ ]", r)[0] for r in EXTRAS.get(named.group("extra"), [])}
    assert set() == needs - installed, f"{example.name}: {named.group('extra')} misses these"
