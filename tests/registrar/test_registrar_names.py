"""Registrar names become file names (`<name>.db`, `<name>.sock`): the ones a shell or a
directory listing reads as something else are refused (issue 21)."""

from __future__ import annotations

from pathlib import Path

import pytest

import rr_actors as rr
from rr_actors.config import NAME_MAX


@pytest.mark.parametrize("name", [".", "..", "-rf", ".hidden", "-", "--help"])
def test_a_name_starting_with_a_dot_or_a_dash_is_refused_naming_the_field(name: str) -> None:
    with pytest.raises(
        rr.ConfigError, match=r"^name .* is not a registrar name: .*not starting with '\.' or '-'"
    ):
        rr.RegistrarConfig(name)


@pytest.mark.parametrize("name", ["..", "-rf"])
def test_a_supervisor_with_such_a_name_writes_no_file(name: str, tmp_path: Path) -> None:
    with pytest.raises(rr.ConfigError, match="name"):
        rr.Supervisor([rr.ManagerSpec(name, lambda _r: None)], state_dir=tmp_path)
    assert [] == list(tmp_path.iterdir())


@pytest.mark.parametrize("name", ["erm", "a.b", "cam-1", "_private", "0"])
def test_a_name_with_dots_and_dashes_inside_is_accepted(name: str) -> None:
    assert name == rr.RegistrarConfig(name).name


# -- one bound: NAME_MAX (64), a certificate's common name, for every name taken --------------

LONGEST, TOO_LONG = "n" * 64, "n" * 65

TAKERS = {
    "RegistrarConfig": rr.RegistrarConfig,
    "ManagerSpec": rr.ManagerSpec,
    "SupervisorSpec": lambda name: rr.SupervisorSpec(name, ()),
}


def test_the_bound_is_64_characters() -> None:
    assert 64 == NAME_MAX


@pytest.mark.parametrize("take", TAKERS.values(), ids=TAKERS.keys())
def test_a_name_of_64_characters_is_accepted(take) -> None:
    assert LONGEST == take(LONGEST).name


@pytest.mark.parametrize(("what", "take"), TAKERS.items(), ids=TAKERS.keys())
def test_a_name_of_65_characters_is_a_config_error_naming_the_field_and_the_bound(
    what: str, take
) -> None:
    kind = {"RegistrarConfig": "registrar", "ManagerSpec": "manager"}.get(what, "supervisor")
    with pytest.raises(rr.ConfigError) as caught:
        take(TOO_LONG)

    assert (
        f"name {TOO_LONG!r} is 65 characters long: a {kind} name has at most 64 (NAME_MAX, "
        f"the longest common name a certificate holds)"
    ) == str(caught.value)


def test_registrar_start_with_a_name_of_65_characters_is_a_config_error_and_starts_nothing() -> (
    None
):
    with pytest.raises(rr.ConfigError, match=r"^name 'n{65}' is 65 characters long"):
        rr.ResourceRegistrar.start(TOO_LONG)


def test_a_supervisor_serves_managers_and_registrars_of_64_character_names(
    tmp_path: Path, process_helpers: object
) -> None:
    # the process manager's socket, lock and backup are named after it: all fit
    # (`process_helpers` starts the forkserver before the leak check looks)
    manager, registrar = "m" * 64, "r" * 64
    spec = rr.ManagerSpec(manager, _camera, isolation="process")
    with rr.Supervisor([spec], state_dir=tmp_path) as sup:
        app = sup.registrar(registrar)
        assert {"device": 0} == app.call(manager, "camera", {"device": 0}).response
        with pytest.raises(rr.ConfigError, match=r"^name 'n{65}' is 65 characters long"):
            sup.registrar(TOO_LONG)


def _camera(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("camera", load=lambda request: request, unload=lambda *_: None)
