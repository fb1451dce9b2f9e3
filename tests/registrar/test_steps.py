"""The protocol's replaceable steps are a value passed in (`RegistrarConfig.steps`,
`Supervisor(steps=)`), never a slot of the process: a registrar runs the copy its config
hands it, and a registrar beside it in the same process runs its own (issue 71 item 1)."""

from __future__ import annotations

import uuid

import pytest

import rr_actors as rr
from rr_actors.config import Steps


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
    told: list[str] = []

    def climb(parent: str | None, resources: object, status: rr.Status) -> list[str]:
        told.append("tree")
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
