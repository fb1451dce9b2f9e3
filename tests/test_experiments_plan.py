"""Experiment plans: what a valid plan becomes, and every bad input as a PlanError with its line."""

from __future__ import annotations

import pickle
import textwrap
from pathlib import Path

import pytest

import rr_actors as rr
from rr_actors.experiments import PlanError, load_plan, parse_plan
from rr_actors.experiments._lines import key_lines

EXAMPLES = Path(__file__).resolve().parent.parent / "examples" / "experiments"

SERVICE = "rr_actors.experiments.services:service"

BASE = f"""\
name = "t"
duration = 2.0

[tree]
strategy = "one_for_one"

[[tree.children]]
name = "db"
setup = "{SERVICE}"

[[tree.children]]
name = "api"
setup = "{SERVICE}"
options = {{ uses = ["db"] }}

[workload]
clients = 1

[[workload.calls]]
manager = "api"
server = "resource"
"""


def plan_error(text: str) -> PlanError:
    with pytest.raises(PlanError) as caught:
        parse_plan(textwrap.dedent(text), source="plan.toml")
    return caught.value


def test_a_valid_plan_becomes_its_tree_workload_and_faults() -> None:
    plan = parse_plan(
        BASE + '[[faults]]\nkind = "kill_manager"\ntarget = ["db", "api"]\nevery = 0.5\n'
    )

    assert ["db", "api"] == [m.name for m in plan.managers()]
    assert {"uses": ["db"]} == plan.manager("api").options
    assert "process" == plan.manager("db").isolation
    assert ("db", "api") == plan.faults[0].targets
    assert 0.5 == plan.faults[0].every
    assert ((None, plan),) == plan.variants


def test_every_shipped_plan_is_valid() -> None:
    plans = sorted(EXAMPLES.glob("*.toml"))

    assert 4 <= len(plans)
    for path in plans:
        assert path.stem == load_plan(path).name


def test_a_plan_pickles_for_its_run_processes() -> None:
    plan = load_plan(EXAMPLES / "strategies.toml")

    assert plan == pickle.loads(pickle.dumps(plan))


def test_an_unknown_key_names_the_key_and_its_line() -> None:
    error = plan_error(BASE.replace('strategy = "one_for_one"', 'stratgey = "one_for_one"'))

    assert (5, "tree.stratgey") == (error.line, error.key)
    assert str(error).startswith("plan.toml:5: tree.stratgey: unknown key; known here:")


def test_an_unknown_key_of_a_child_names_the_child_by_index() -> None:
    error = plan_error(BASE.replace('name = "api"', 'name = "api"\nisolaton = "thread"'))

    assert (13, "tree.children[1].isolaton") == (error.line, error.key)


def test_a_setup_that_does_not_import_is_refused_with_the_module_named() -> None:
    error = plan_error(BASE.replace(f'setup = "{SERVICE}"', 'setup = "no.such.module:setup"', 1))

    assert (9, "tree.children[0].setup") == (error.line, error.key)
    assert "'no.such.module:setup' does not import: No module named 'no'" in str(error)


def test_a_setup_without_that_attribute_is_refused() -> None:
    error = plan_error(BASE.replace(SERVICE, "rr_actors.experiments.services:nothing", 1))

    assert "has no attribute 'nothing'" in error.problem


def test_an_option_the_setup_does_not_take_is_refused_at_the_options_line() -> None:
    error = plan_error(BASE.replace('uses = ["db"]', 'usse = ["db"]'))

    assert (14, "tree.children[1].options") == (error.line, error.key)
    assert "unexpected keyword argument 'usse'" in error.problem


def test_a_fault_naming_a_manager_not_in_the_tree_is_refused() -> None:
    error = plan_error(BASE + '\n[[faults]]\nkind = "kill_manager"\ntarget = "cache"\nat = 1.0\n')

    assert (25, "faults[0].target") == (error.line, error.key)
    assert "no manager 'cache' in the tree (managers: db, api)" in error.problem


def test_a_fault_naming_an_unknown_manager_in_a_list_points_at_that_element() -> None:
    error = plan_error(
        BASE + '[[faults]]\nkind = "kill_manager"\ntarget = [\n  "db",\n  "x",\n]\nat = 1\n'
    )

    assert (26, "faults[0].target[1]") == (error.line, error.key)


def test_a_negative_time_is_refused() -> None:
    error = plan_error(BASE + '[[faults]]\nkind = "kill_manager"\ntarget = "db"\nat = -1.0\n')

    assert (25, "faults[0].at") == (error.line, error.key)
    assert "must be seconds >= 0, got -1.0" == error.problem


def test_a_negative_duration_is_refused() -> None:
    error = plan_error(BASE.replace("duration = 2.0", "duration = -2.0"))

    assert (2, "duration") == (error.line, error.key)


def test_a_fault_after_the_end_of_the_run_is_refused() -> None:
    error = plan_error(BASE + '[[faults]]\nkind = "kill_manager"\ntarget = "db"\nat = [1.0, 2.0]\n')

    assert "faults[0].at[1]" == error.key
    assert "2.0 s is not before the end of the run (2 s)" == error.problem


def test_a_hang_of_a_thread_manager_is_refused() -> None:
    text = BASE.replace('name = "db"', 'name = "db"\nisolation = "thread"')
    error = plan_error(text + '[[faults]]\nkind = "hang_manager"\ntarget = "db"\nat = 1\nfor = 1\n')

    assert "faults[0].target" == error.key
    assert "hang_manager needs a process manager; 'db' has isolation 'thread'" == error.problem


def test_a_fault_without_a_time_says_how_to_give_one() -> None:
    error = plan_error(BASE + '[[faults]]\nkind = "kill_manager"\ntarget = "db"\n')

    assert (22, "faults[0]") == (error.line, error.key)
    assert "say when: give one of 'at', 'every' or 'after'" == error.problem


def test_a_trigger_on_an_unknown_event_is_refused() -> None:
    text = '[[faults]]\nkind = "kill_manager"\ntarget = "db"\nafter = { event = "Restarted" }\n'
    error = plan_error(BASE + text)

    assert "faults[0].after.event" == error.key
    assert error.problem.startswith("unknown event 'Restarted'; events: ChildExited,")


def test_a_trigger_on_a_field_the_event_does_not_have_is_refused() -> None:
    text = (
        '[[faults]]\nkind = "kill_manager"\ntarget = "db"\n'
        'after = { event = "ChildRestarted", name = "db" }\n'
    )
    error = plan_error(BASE + text)

    assert "faults[0].after.name" == error.key


def test_a_workload_call_to_an_unknown_manager_is_refused() -> None:
    error = plan_error(BASE.replace('manager = "api"', 'manager = "apj"'))

    assert (20, "workload.calls[0].manager") == (error.line, error.key)


def test_a_request_template_with_an_unknown_placeholder_is_refused() -> None:
    error = plan_error(BASE + 'request = { name = "x-{keys}" }\n')

    assert "workload.calls[0].request.name" == error.key
    assert error.problem.startswith("unknown placeholder {keys}")


def test_a_name_used_twice_in_the_tree_is_refused() -> None:
    error = plan_error(BASE.replace('name = "api"', 'name = "db"'))

    assert (12, "tree.children[1].name") == (error.line, error.key)


def test_text_that_is_not_toml_names_its_line() -> None:
    error = plan_error(BASE.replace("clients = 1", "clients = = 1"))

    assert 17 == error.line
    assert "is not valid TOML" in error.problem


def test_a_plan_file_that_does_not_exist_is_a_plan_error(tmp_path: Path) -> None:
    with pytest.raises(PlanError, match="cannot be read"):
        load_plan(tmp_path / "missing.toml")


def test_a_plan_error_is_a_config_error_and_pickles() -> None:
    error = plan_error(BASE.replace("duration = 2.0", "duration = 0"))

    assert isinstance(error, rr.ConfigError)
    assert str(error) == str(pickle.loads(pickle.dumps(error)))


def test_compare_makes_one_plan_per_value() -> None:
    plan = parse_plan(
        BASE + '[compare]\nsetting = "tree.strategy"\nvalues = ["one_for_one", "one_for_all"]\n'
    )

    assert ["one_for_one", "one_for_all"] == [v for v, _ in plan.variants]
    assert ["one_for_one", "one_for_all"] == [p.tree.strategy for _, p in plan.variants]
    assert "tree.strategy" == plan.setting_label()


def test_compare_reaches_a_child_by_its_name() -> None:
    plan = parse_plan(
        BASE + '[compare]\nsetting = "tree.children.api.heartbeat"\nvalues = [false, 0.1]\n'
    )

    assert [None, 0.1] == [p.manager("api").heartbeat for _, p in plan.variants]
    assert [0.25, 0.25] == [p.manager("db").heartbeat for _, p in plan.variants]


def test_a_compared_value_that_is_invalid_points_at_the_value() -> None:
    error = plan_error(
        BASE + '[compare]\nsetting = "tree.strategy"\nvalues = ["one_for_one", "all_for_one"]\n'
    )

    assert "compare.values[1]" == error.key
    assert error.problem.startswith("with tree.strategy = 'all_for_one': tree.strategy: must be")


def test_a_compared_setting_that_does_not_exist_is_refused() -> None:
    error = plan_error(
        BASE + '[compare]\nsetting = "tree.children.cache.heartbeat"\nvalues = [1]\n'
    )

    assert "compare.setting" == error.key
    assert "no element named 'cache'" in error.problem


def test_overrides_apply_to_every_compared_value() -> None:
    plan = parse_plan(
        BASE + '[compare]\nsetting = "tree.strategy"\nvalues = ["one_for_one", "one_for_all"]\n'
    )

    changed = plan.with_changes(repeat=5, seed=9, duration=1.0)

    assert (5, 9, 1.0) == (changed.repeat, changed.seed, changed.duration)
    assert [(5, 9, 1.0)] * 2 == [(p.repeat, p.seed, p.duration) for _, p in changed.variants]


def test_the_key_scanner_finds_tables_arrays_of_tables_and_inline_keys() -> None:
    text = textwrap.dedent(
        """\
        name = "x"  # a comment
        description = \"\"\"
        [not a table]
        \"\"\"
        [tree]
        backoff = { initial = 0.1, max = 1.0 }
        [[tree.children]]
        name = "a"
        [[tree.children]]
        name = "b"
        [[tree.children.children]]
        name = "c"
        [[faults]]
        at = [
          1.0,
          2.0,
        ]
        """
    )

    lines = key_lines(text)

    assert 1 == lines[("name",)]
    assert 6 == lines[("tree", "backoff", "max")]
    assert 10 == lines[("tree", "children", 1, "name")]
    assert 12 == lines[("tree", "children", 1, "children", 0, "name")]
    assert 16 == lines[("faults", 0, "at", 1)]
    assert ("not a table",) not in lines
