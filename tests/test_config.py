"""Configuration as frozen, validated data (`rr_actors.config`): backoff, manager specs, and
the one walk over a spec tree (`config.walk`) and what is read through it."""

from __future__ import annotations

import functools
import uuid
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.config import (
    NAME_MAX,
    Backoff,
    ManagerSpec,
    Steps,
    check_strs,
    is_loopback,
    managers,
    tree_names,
    walk,
)

# -- the walk over a spec tree ---------------------------------------------------------------


def noop(_: rr.ResourceRegistrar) -> None:
    """A setup that registers nothing."""


def nested() -> rr.SupervisorSpec:
    """root: a, inner (b, deep (c)), d."""
    deep = rr.SupervisorSpec("deep", (rr.ManagerSpec("c", noop, isolation="process"),))
    inner = rr.SupervisorSpec("inner", (rr.ManagerSpec("b", noop), deep))
    return rr.SupervisorSpec("root", (rr.ManagerSpec("a", noop), inner, rr.ManagerSpec("d", noop)))


def test_walk_yields_every_child_depth_first_with_the_supervisors_above_it() -> None:
    walked = [(child.name, [s.name for s in path]) for child, path in walk(nested())]

    assert [
        ("a", ["root"]),
        ("inner", ["root"]),
        ("b", ["root", "inner"]),
        ("deep", ["root", "inner"]),
        ("c", ["root", "inner", "deep"]),
        ("d", ["root"]),
    ] == walked


def test_names_managers_and_processes_are_read_through_the_walk() -> None:
    spec = nested()

    assert ["a", "inner", "b", "deep", "c", "d"] == tree_names(spec)
    assert ["a", "b", "c", "d"] == [m.name for m in managers(spec)]
    threads_only = rr.SupervisorSpec("t", (rr.ManagerSpec("a", noop),))
    assert (True, False) == (spec.has_processes(), threads_only.has_processes())


# -- Backoff --------------------------------------------------------------------------------


def test_backoff_without_an_initial_delay_restarts_at_once() -> None:
    assert [0.0, 0.0, 0.0] == [Backoff().delay(n) for n in (1, 2, 5)]


def test_backoff_grows_by_its_factor_per_restart_in_the_window() -> None:
    backoff = Backoff(initial=0.1, factor=2.0, max=10.0, jitter=0.0)

    assert [0.1, 0.2, 0.4, 0.8] == [round(backoff.delay(n), 9) for n in (1, 2, 3, 4)]


def test_backoff_never_waits_longer_than_its_max() -> None:
    backoff = Backoff(initial=1.0, factor=10.0, max=3.0, jitter=0.5)

    assert 3.0 == backoff.delay(50, random=lambda: 0.999999)


def test_backoff_jitter_spreads_the_delay_both_ways() -> None:
    backoff = Backoff(initial=1.0, factor=2.0, max=10.0, jitter=0.2)

    assert (0.8, 1.2) == (
        backoff.delay(1, random=lambda: 0.0),
        backoff.delay(1, random=lambda: 1.0),
    )


@pytest.mark.parametrize(
    ("field", "value"),
    [("initial", -1.0), ("factor", 0.5), ("max", -2.0), ("jitter", 1.5), ("jitter", True)],
)
def test_invalid_backoff_raises_config_error_naming_the_field(field: str, value: Any) -> None:
    with pytest.raises(rr.ConfigError, match=f"Backoff.{field}"):
        Backoff(**{field: value})


# -- specs ----------------------------------------------------------------------------------


def test_manager_spec_config_must_carry_the_managers_name() -> None:
    with pytest.raises(rr.ConfigError, match=r"config\.name"):
        ManagerSpec("erm", config=rr.RegistrarConfig(name="other"))


@pytest.mark.parametrize(
    ("field", "value"),
    [("isolation", "fiber"), ("restart", "sometimes"), ("shutdown", 0), ("heartbeat", -1.0)],
)
def test_invalid_manager_spec_raises_config_error_naming_the_field(field: str, value: Any) -> None:
    with pytest.raises(rr.ConfigError, match=field):
        ManagerSpec("erm", **{field: value})


# -- names -------------------------------------------------------------------------------------

LONGEST, TOO_LONG = "n" * 64, "n" * 65

TAKERS = {
    "RegistrarConfig": rr.RegistrarConfig,
    "ManagerSpec": rr.ManagerSpec,
    "SupervisorSpec": lambda name: rr.SupervisorSpec(name, ()),
}


def _camera(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("camera", load=lambda request: request, unload=lambda *_: None)


class TestNames:
    """Names (registrar, system, member): at most 64 characters, checked in one place; none
    starting with a dot or a dash (they become file names)."""

    @pytest.mark.parametrize("name", [".", "..", "-rf", ".hidden", "-", "--help"])
    def test_a_name_starting_with_a_dot_or_a_dash_is_refused_naming_the_field(
        self, name: str
    ) -> None:
        with pytest.raises(
            rr.ConfigError,
            match=r"^name .* is not a registrar name: .*not starting with '\.' or '-'",
        ):
            rr.RegistrarConfig(name)

    @pytest.mark.parametrize("name", ["..", "-rf"])
    def test_a_supervisor_with_such_a_name_writes_no_file(self, name: str, tmp_path: Path) -> None:
        with pytest.raises(rr.ConfigError, match="name"):
            rr.Supervisor([rr.ManagerSpec(name, lambda _r: None)], state_dir=tmp_path)
        assert [] == list(tmp_path.iterdir())

    @pytest.mark.parametrize("name", ["erm", "a.b", "cam-1", "_private", "0"])
    def test_a_name_with_dots_and_dashes_inside_is_accepted(self, name: str) -> None:
        assert name == rr.RegistrarConfig(name).name

    def test_the_bound_is_64_characters(self) -> None:
        assert 64 == NAME_MAX

    @pytest.mark.parametrize("take", TAKERS.values(), ids=TAKERS.keys())
    def test_a_name_of_64_characters_is_accepted(self, take) -> None:
        assert LONGEST == take(LONGEST).name

    @pytest.mark.parametrize(("what", "take"), TAKERS.items(), ids=TAKERS.keys())
    def test_a_name_of_65_characters_is_a_config_error_naming_the_field_and_the_bound(
        self, what: str, take
    ) -> None:
        kind = {"RegistrarConfig": "registrar", "ManagerSpec": "manager"}.get(what, "supervisor")
        with pytest.raises(rr.ConfigError) as caught:
            take(TOO_LONG)

        assert (
            f"name {TOO_LONG!r} is 65 characters long: a {kind} name has at most 64 (NAME_MAX, "
            f"the longest common name a certificate holds)"
        ) == str(caught.value)

    def test_registrar_start_with_a_name_of_65_characters_is_a_config_error_and_starts_nothing(
        self,
    ) -> None:
        with pytest.raises(rr.ConfigError, match=r"^name 'n{65}' is 65 characters long"):
            rr.ResourceRegistrar.start(TOO_LONG)

    def test_a_supervisor_serves_managers_and_registrars_of_64_character_names(
        self, tmp_path: Path, process_helpers: object
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

    def test_a_call_s_target_that_is_not_a_str_is_refused_naming_the_field(self, uid: str) -> None:
        """The other end's names (`target_rr`, `server`) are checked only to be strs, where a
        call starts and where `call_with_retry` does (`check_strs`): their form is theirs."""
        check_strs(target_rr="api", server="cam.v1/x")
        with pytest.raises(rr.ConfigError, match=r"^server must be a name \(a str\), got 7$"):
            check_strs(target_rr="api", server=7)
        with rr.Supervisor([rr.ManagerSpec(f"api-{uid}", noop)]) as sup:
            app = sup.registrar(f"app-{uid}")
            for call in (app.call, functools.partial(sup.call_with_retry, app)):
                with pytest.raises(rr.ConfigError, match=r"^target_rr must be a name"):
                    call(b"api", "camera", {})


@pytest.mark.parametrize(
    ("host", "loopback"),
    [
        ("localhost", True),
        ("127.0.0.1", True),
        ("127.3.2.1", True),
        ("::1", True),
        ("0.0.0.0", False),  # noqa: S104 - every address, so reachable from elsewhere
        ("10.0.0.1", False),
        ("::", False),
        ("localhost.example.com", False),  # a DNS name may resolve anywhere
        ("", False),
    ],
)
def test_a_host_is_loopback_only_when_it_names_this_machine_alone(
    host: str, loopback: bool
) -> None:
    assert loopback == is_loopback(host)


def test_a_mistyped_field_of_a_saved_config_is_answered_with_the_closest_field() -> None:
    data = {**rr.RegistrarConfig().to_dict(), "call_timout": 3.0}

    with pytest.raises(rr.ConfigError) as caught:
        rr.RegistrarConfig.from_dict(data)

    assert str(caught.value).startswith(
        "unknown RegistrarConfig fields: ['call_timout']; did you mean 'call_timeout'? (known: "
    )


# -- the protocol's replaceable steps: a value passed in (issue 71 item 1) ------------------


def _named(prefix: str) -> str:
    return f"{prefix}-{uuid.uuid4().hex[:8]}"


def test_a_step_handed_in_through_config_is_used_by_that_registrar_and_not_by_another() -> None:
    never_shared = Steps(shares=lambda stored, request, loading, failed: False)
    loads: dict[str, list[object]] = {"mine": [], "other": []}
    mine = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=_named("mine"), steps=never_shared))
    other = rr.ResourceRegistrar.start(_named("other"))
    app = rr.ResourceRegistrar.start(_named("app"))
    with app, mine, other:
        for name, registrar in (("mine", mine), ("other", other)):
            registrar.register_server(
                "leaf",
                load=lambda request, name=name: loads[name].append(request) or request,
                unload=lambda request, response: None,
            )
        for registrar in (mine, other):
            app.call(registrar.name, "leaf", "x")
            app.call(registrar.name, "leaf", "x")  # equal: shared unless the step says not

    assert {"mine": ["x", "x"], "other": ["x"]} == loads


def test_a_supervisors_steps_reach_the_registrars_it_makes_unless_their_config_names_its_own() -> (
    None
):
    def climb(parent: str | None, resources: object, status: rr.Status) -> list[str]:
        return []

    tree_steps = Steps(climb=climb)
    own = Steps(unloads=lambda left: not left)
    with rr.Supervisor([], steps=tree_steps) as sup:
        plain = sup.registrar(_named("plain"))
        named = sup.registrar(rr.RegistrarConfig(name=_named("named")))
        kept = sup.registrar(rr.RegistrarConfig(name=_named("kept"), steps=own))

        assert (plain.config.steps, named.config.steps, kept.config.steps) == (
            tree_steps,
            tree_steps,
            own,
        )


def test_steps_that_are_not_functions_are_refused_naming_the_field() -> None:
    with pytest.raises(rr.ConfigError, match=r"^steps\.climb must be a function or None, got 3$"):
        Steps(climb=3)  # type: ignore[arg-type]
    with pytest.raises(rr.ConfigError, match=r"^steps must be an rr_actors\.config\.Steps"):
        rr.RegistrarConfig(steps={"climb": None})  # type: ignore[arg-type]
    with pytest.raises(rr.ConfigError, match=r"^steps must be an rr_actors\.config\.Steps"):
        rr.Supervisor([], steps=object())  # type: ignore[arg-type]


def test_a_configs_steps_are_not_data_and_its_dict_round_trips_without_them() -> None:
    config = rr.RegistrarConfig(name="x", steps=Steps(in_doubt=lambda state: False))

    data = config.to_dict()

    assert "steps" not in data
    assert rr.RegistrarConfig.from_dict(data) == rr.RegistrarConfig(name="x")
