"""The `rr-actors` command itself (its subcommands have their own test modules)."""

from __future__ import annotations

import importlib.metadata
import re
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

import rr_actors
from tests.support.terminal import drawn, on_a_terminal

PACKAGE = Path(rr_actors.__file__).resolve().parent


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


# -- 80 columns (issue 44, item 2) ----------------------------------------------------------

TERMINAL_COMMANDS = {
    "help": ["--help"],
    "experiment --help": ["experiment", "--help"],
    "experiment --list": ["experiment", "--list"],
    "demo": ["demo", "--fast", "--out", "{out}"],
    "demo --observe": ["demo", "--fast", "--observe", "--linger", "0.1", "--out", "{out}"],
    "experiment": ["experiment", "first", "--repeat", "1", "--out", "{out}"],
}
CUT = re.compile(r"\w~(\s|$)|…")
"""What a name cut short looks like: `one_for~`, `manag…`."""


@pytest.mark.timeout(150)
@pytest.mark.parametrize("name", list(TERMINAL_COMMANDS))
def test_on_an_80_column_terminal_every_line_fits_and_no_name_is_cut(
    name: str, tmp_path: Path
) -> None:
    argv = [a.format(out=tmp_path / "out") for a in TERMINAL_COMMANDS[name]]

    code, text = on_a_terminal(
        [sys.executable, "-m", "rr_actors", *argv], columns=80, timeout=120, cwd=tmp_path
    )

    pieces = drawn(text)
    assert 0 == code, text
    assert [] == [p for p in pieces if len(p) > 80], text
    assert [] == [p for p in pieces if CUT.search(p)], text
    assert str(tmp_path) not in text  # (paths as typed: relative to the working directory)
    assert str(PACKAGE) not in text  # (nor where rr_actors is installed)
    if name == "experiment":
        runs = [m[1] for p in pieces if (m := re.match(r"run \d+/\d+ (\S+) seed \d+: ", p))]
        assert {"one_for_one", "rest_for_one"} == set(runs), text
    if name == "demo --observe":
        urls = re.findall(r"http://127\.0\.0\.1:\d+/\S*", text)
        assert 2 <= len(urls), text
        assert {urls[0]} == set(urls), text  # whole at the start and at the end


@pytest.mark.timeout(150)
def test_on_an_80_column_terminal_the_certs_lines_fit_and_the_next_command_is_whole(
    tmp_path: Path,
) -> None:
    """`certs init` then `certs issue`, as the securing how-to runs them: each says what
    to do next within 80 columns (their lines were 107 and 186 columns)."""
    said = []
    for argv in (
        ["certs", "init", "certs", "--system", "lab"],
        ["certs", "issue", "certs", "robot", "--address", "10.0.0.2", "--address", "robot.local"],
    ):
        code, text = on_a_terminal(
            [sys.executable, "-m", "rr_actors", *argv], columns=80, timeout=120, cwd=tmp_path
        )
        assert 0 == code, text
        said.append(text)

    pieces = drawn("".join(said))
    assert [] == [p for p in pieces if len(p) > 80], said
    assert "    rr-actors certs issue certs NAME --address ADDR" in pieces, said
    assert any(p.endswith("rr.ZenohTLS(members=[...])") for p in pieces), said  # (whole)
