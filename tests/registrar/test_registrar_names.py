"""Registrar names become file names (`<name>.db`, `<name>.sock`): the ones a shell or a
directory listing reads as something else are refused (issue 21)."""

from __future__ import annotations

from pathlib import Path

import pytest

import rr_actors as rr


@pytest.mark.parametrize("name", [".", "..", "-rf", ".hidden", "-", "--help"])
def test_a_name_starting_with_a_dot_or_a_dash_is_refused_naming_the_field(name: str) -> None:
    with pytest.raises(rr.ConfigError, match=r"^name must .*not starting with '\.' or '-'"):
        rr.RegistrarConfig(name)


@pytest.mark.parametrize("name", ["..", "-rf"])
def test_a_supervisor_with_such_a_name_writes_no_file(name: str, tmp_path: Path) -> None:
    with pytest.raises(rr.ConfigError, match="name"):
        rr.Supervisor([rr.ManagerSpec(name, lambda _r: None)], state_dir=tmp_path)
    assert [] == list(tmp_path.iterdir())


@pytest.mark.parametrize("name", ["erm", "a.b", "cam-1", "_private", "0"])
def test_a_name_with_dots_and_dashes_inside_is_accepted(name: str) -> None:
    assert name == rr.RegistrarConfig(name).name
