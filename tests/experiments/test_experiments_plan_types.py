"""The plan reader on msgspec: what the types refuse, worded with the key, line, value, choices."""

from __future__ import annotations

import pytest

from rr_actors.experiments import PlanError, parse_plan

BASE = """\
name = "t"
duration = 2.0

[tree]

[[tree.children]]
name = "db"
setup = "rr_actors.experiments.services:service"

[workload]
clients = 1

[[workload.calls]]
manager = "db"
server = "resource"
"""
KILL_DB = '[[faults]]\nkind = "kill_manager"\ntarget = "db"\n'


def plan_error(text: str) -> PlanError:
    with pytest.raises(PlanError) as caught:
        parse_plan(text, source="plan.toml")
    return caught.value


def test_a_nested_supervisor_names_the_keys_a_supervisor_takes() -> None:
    pool = '[[tree.children]]\nname = "pool"\nheartbeat = 1.0\n\n[[tree.children.children]]\n'
    text = BASE.replace('[[tree.children]]\nname = "db"', pool + 'name = "db"')
    error = plan_error(text)

    assert (8, "tree.children[0].heartbeat") == (error.line, error.key)
    assert (
        "unknown key; known here: backoff, children, max_restarts, name, period, restart, "
        + ("strategy")
        == error.problem
    )


def test_a_trigger_field_the_event_does_not_have_names_the_fields_it_has() -> None:
    error = plan_error(BASE + KILL_DB + 'after = { event = "ChildRestarted", nme = "db" }\n')

    assert (19, "faults[0].after.nme") == (error.line, error.key)
    assert error.problem.startswith("unknown key; known here: child, host, nth, pid,")


def test_an_unknown_backoff_key_is_refused_with_the_keys_it_takes() -> None:
    error = plan_error(BASE.replace("[tree]", "[tree]\nbackoff = { inital = 0.5 }"))

    assert (5, "tree.backoff.inital") == (error.line, error.key)
    assert "unknown key; known here: factor, initial, jitter, max" == error.problem


def test_a_random_interval_whose_max_is_below_its_min_is_refused() -> None:
    error = plan_error(BASE + KILL_DB + "every = { min = 2.0, max = 1.0 }\n")

    assert (19, "faults[0].every") == (error.line, error.key)
    assert error.problem.startswith("max (1 s) must not be less than min (2 s), got {")


def test_a_top_supervisor_with_a_restart_type_is_refused() -> None:
    error = plan_error(BASE.replace("[tree]", '[tree]\nrestart = "transient"'))

    assert (5, "tree.restart") == (error.line, error.key)
    assert (
        "unknown key; known here: backoff, children, max_restarts, name, period, state, "
        + ("strategy")
        == error.problem
    )


def test_the_spellings_of_toml_become_the_plan_s_values() -> None:
    text = BASE.replace("clients = 1", 'clients = 1\nrate = "max"')
    text = text.replace('name = "db"', 'name = "db"\nheartbeat = false')

    plan = parse_plan(text + KILL_DB + "every = { min = 0.5, max = 1.0 }\n")

    assert (None, None) == (plan.workload.rate, plan.manager("db").heartbeat)
    assert ((0.5, 1.0), ("db",)) == (plan.faults[0].every, plan.faults[0].targets)


def test_a_message_too_long_names_its_limit() -> None:
    text = '[[faults]]\nkind = "load_error"\ntarget = "db"\nat = 1.0\nmessage = "' + "x" * 10_001
    error = plan_error(BASE + text + '"\n')

    assert (20, "faults[0].message") == (error.line, error.key)
    assert error.problem.startswith("must be a string of length <= 10000, got 'xxx")
