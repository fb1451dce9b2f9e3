"""Configuration as frozen, validated data (`rr_actors.config`): backoff, manager specs, and
the one walk over a spec tree (`config.walk`) and what is read through it."""

from __future__ import annotations

from typing import Any

import pytest

import rr_actors as rr
from rr_actors.config import Backoff, ManagerSpec, managers, tree_names, walk

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
