"""The `rr-actors` command itself (its subcommands have their own test modules)."""

from __future__ import annotations

import importlib.metadata
import subprocess
import sys
import sysconfig
from pathlib import Path

import rr_actors


def rr_actors_command(*argv: str) -> subprocess.CompletedProcess[str]:
    """The installed `rr-actors` console script, next to this interpreter."""
    script = Path(sysconfig.get_path("scripts")) / "rr-actors"
    return subprocess.run(
        [str(script), *argv], capture_output=True, text=True, timeout=30, check=False
    )


def test_version_prints_the_installed_version() -> None:
    result = rr_actors_command("--version")

    assert (0, "") == (result.returncode, result.stderr)
    assert f"rr-actors {importlib.metadata.version('rr-actors')}\n" == result.stdout


def test_the_package_version_is_the_distribution_version() -> None:
    assert importlib.metadata.version("rr-actors") == rr_actors.__version__


def test_help_lists_every_subcommand_and_the_version_option() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "rr_actors", "--help"],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )

    assert 0 == result.returncode
    for word in ("demo", "inspect", "--version"):
        assert word in result.stdout


def test_without_a_command_it_prints_the_help_and_exits_2() -> None:
    result = rr_actors_command()

    assert (2, "") == (result.returncode, result.stderr)
    assert result.stdout.startswith("usage: rr-actors [-h] [--version] COMMAND ...\n")
    listed = {line.split()[0] for line in result.stdout.splitlines() if line.startswith("    ")}
    assert {"demo", "inspect", "observe", "graph", "experiment"} <= listed
