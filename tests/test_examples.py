"""Every example runs to completion as its own program (the smoke test STYLE.md asks for)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def run_example(name: str) -> subprocess.CompletedProcess[str]:
    """Run `examples/<name>` with this interpreter; fail the test after 45 s."""
    return subprocess.run(
        [sys.executable, str(EXAMPLES / name)],
        capture_output=True,
        text=True,
        timeout=45,
        check=False,
    )


def test_quickstart_loads_hears_a_status_unloads_and_exits_cleanly() -> None:
    result = run_example("quickstart.py")

    assert (0, "") == (result.returncode, result.stderr)
    assert "response: 'hello, world'; shared: True" in result.stdout
    assert "heard WARNING: battery low" in result.stdout
    assert 1 == result.stdout.count("unloaded 'hello, world'")


def test_filtered_camera_is_loaded_once_for_two_actions() -> None:
    result = run_example("filtered_camera.py")

    assert (0, "") == (result.returncode, result.stderr)
    assert "filtered_camera loaded 1 time(s) for 2 consumers" in result.stdout
    assert "both actions share one camera and one filter process: True" in result.stdout


def test_filtered_camera_failure_reaches_both_actions_then_everything_stops() -> None:
    result = run_example("filtered_camera.py")
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


ROOT = EXAMPLES.parent


def test_readme_quickstart_is_examples_quickstart() -> None:
    readme = (ROOT / "README.md").read_text()
    block = readme.split("```python\n", 1)[1].split("```\n", 1)[0]

    assert (EXAMPLES / "quickstart.py").read_text() == block


def test_readme_starts_with_the_demo_and_the_test_command_that_ci_runs() -> None:
    lines = (ROOT / "README.md").read_text().splitlines()
    test_command = lines[2].split("&&", 1)[1].strip()

    assert ["```bash", "```"] == [lines[0], lines[3]]
    assert 'pip install -e ".[demo]" && rr-actors demo' == lines[1]
    assert lines[2].startswith('pip install -e ".[dev]" && ')
    assert f"\n{test_command} || status=$?\n" in (ROOT / ".ci" / "run").read_text()
