"""A wheel of rr_actors runs its shipped plans by name from anywhere (issue 24, item 10).

The wheel is built from a copy of the sources, installed with `--no-deps` into a fresh
virtual environment that sees only the core's and the plan reader's dependencies (pykka,
cloudpickle, msgspec, taken from this interpreter), and run from a directory that is not
the repository, with no `PYTHONPATH`: what a user who ran `pip install rr-actors` has.
"""

from __future__ import annotations

import csv
import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
NEEDED = ("pykka", "cloudpickle", "msgspec")  # the core's and the plan reader's


def sh(*argv: str | Path, cwd: Path, env: dict[str, str]) -> str:
    done = subprocess.run(
        [str(a) for a in argv],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert 0 == done.returncode, f"{argv}:\n{done.stdout}\n{done.stderr}"
    return done.stdout


@pytest.mark.timeout(240)
def test_the_wheel_lists_and_runs_a_shipped_plan_from_anywhere(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    source = tmp_path / "source"
    shutil.copytree(ROOT / "rr_actors", source / "rr_actors", symlinks=False)
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, source / name)
    sh(sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
       "-w", tmp_path / "dist", source, cwd=tmp_path, env=env)  # fmt: skip
    (wheel,) = (tmp_path / "dist").glob("rr_actors-*.whl")

    venv = tmp_path / "venv"
    sh(sys.executable, "-m", "venv", "--without-pip", venv, cwd=tmp_path, env=env)
    python = venv / "bin" / "python"
    sh(sys.executable, "-m", "pip", "--python", python, "install", "-q", "--no-deps", wheel,
       cwd=tmp_path, env=env)  # fmt: skip
    deps = tmp_path / "deps"
    deps.mkdir()
    for name in NEEDED:
        spec = importlib.util.find_spec(name)
        assert spec is not None
        assert spec.submodule_search_locations
        (deps / name).symlink_to(next(iter(spec.submodule_search_locations)))
    site = sh(python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])",
              cwd=tmp_path, env=env).strip()  # fmt: skip
    (Path(site) / "needed-deps.pth").write_text(f"{deps}\n")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()

    where = sh(python, "-c", "import rr_actors; print(rr_actors.__file__)", cwd=elsewhere, env=env)
    listed = sh(venv / "bin" / "rr-actors", "experiment", "--list", cwd=elsewhere, env=env)
    help_text = sh(venv / "bin" / "rr-actors", "experiment", "--help", cwd=elsewhere, env=env)
    license_text = sh(
        python, "-c", "from importlib.metadata import distribution as d; "
        "print(d('rr-actors').read_text('LICENSE'))", cwd=elsewhere, env=env,
    )  # fmt: skip
    sh(venv / "bin" / "rr-actors", "experiment", "first", "--out", "out", "--repeat", "1",
       "--duration", "1", cwd=elsewhere, env=env)  # fmt: skip

    assert where.startswith(str(venv))
    assert {"crashloop", "first", "hang", "resource", "strategies"} <= {
        line.split()[0] for line in listed.splitlines() if line.strip()
    }
    assert "the format: " in " ".join(help_text.split())  # the shipped reference, named
    # The footer names the shipped folder relative to the package (80 columns, no absolute
    # path, issue 44): the reference is there, in the installed wheel.
    assert "rr_actors/experiments/plans/" in listed
    assert "plan-reference.md" in listed
    reference = Path(where.strip()).parent / "experiments" / "plans" / "plan-reference.md"
    assert reference.is_file()
    assert "# Experiment plans" in reference.read_text()
    assert "MIT License" in license_text
    assert "the rr_actors developers" in license_text
    with (elsewhere / "out" / "runs.csv").open(newline="") as rows:
        assert ["one_for_one", "rest_for_one"] == [row["value"] for row in csv.DictReader(rows)]
