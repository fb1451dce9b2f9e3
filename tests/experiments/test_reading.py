"""Reading a plan (`rr_actors_lab.experiments.reading`): what a valid plan becomes, every bad
input as a PlanError with its line, and the line of a key in a TOML text."""

from __future__ import annotations

import io
import os
import pickle
import textwrap
from pathlib import Path

import pytest

import rr_actors as rr
from rr_actors_lab.__main__ import main
from rr_actors_lab.experiments import PlanError, load_plan, parse_plan, reading
from rr_actors_lab.experiments.reading import key_lines

EXAMPLES = Path(__file__).resolve().parents[2] / "rr_actors_lab" / "experiments" / "plans"

SERVICE = "rr_actors_lab.experiments.services:service"

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


def test_a_tree_stopped_in_parallel_is_read_and_any_other_stop_is_refused_in_a_line() -> None:
    parallel = BASE.replace(
        'strategy = "one_for_one"', 'strategy = "one_for_one"\nstop = "parallel"'
    )
    assert ("reverse", "parallel") == (parse_plan(BASE).stop, parse_plan(parallel).stop)
    error = plan_error(parallel.replace('"parallel"', '"sideways"'))
    assert "tree.stop" in str(error)
    assert 'must be "reverse" or "parallel"' in str(error)
    assert 1 == len(str(error).splitlines())


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
    assert str(error).startswith(
        "plan.toml:5: tree.stratgey: unknown key; did you mean 'strategy'? known here:"
    )


@pytest.mark.parametrize(
    ("wrong", "key", "says"),
    [
        (("duration = 2.0", "duraton = 2.0"), "duraton", "unknown key; did you mean 'duration'? "),
        (("clients = 1", "client = 1"), "workload.client", "did you mean 'clients'? known here"),
        (
            (
                "[workload]",
                '[[faults]]\nkind = "kill_manger"\ntarget = "db"\nat = 1.0\n\n[workload]',
            ),
            "faults[0].kind",
            "got 'kill_manger'; did you mean 'kill_manager'?",
        ),
        (
            ('manager = "api"', 'manager = "apj"'),
            "workload.calls[0].manager",
            "no manager 'apj' in the tree; did you mean 'api'? (managers: db, api)",
        ),
    ],
    ids=["top key", "table key", "fault kind", "manager"],
)
def test_a_mistyped_name_is_answered_with_the_closest_known_one(
    wrong: tuple[str, str], key: str, says: str
) -> None:
    error = plan_error(BASE.replace(*wrong))

    assert key == error.key
    assert says in error.problem


def test_a_name_far_from_every_known_one_gets_no_guess() -> None:
    error = plan_error(BASE.replace('manager = "api"', 'manager = "cache"'))

    assert "did you mean" not in error.problem


def fault(*keys: str, kind: str = "kill_manager", target: str | None = '"db"') -> str:
    """BASE with one `[[faults]]` table: its kind, its target (none if `None`), these keys."""
    aimed = "" if target is None else f"target = {target}\n"
    return BASE + f'[[faults]]\nkind = "{kind}"\n{aimed}' + "".join(f"{k}\n" for k in keys)


REFUSED = {
    # what the plan names: setups, options, managers, names, placeholders
    "a setup that does not import is refused with the module named": (
        BASE.replace(f'setup = "{SERVICE}"', 'setup = "no.such.module:setup"', 1),
        (9, "tree.children[0].setup"),
        "'no.such.module:setup' does not import: No module named 'no'",
    ),
    "a setup without that attribute is refused": (
        BASE.replace(SERVICE, "rr_actors_lab.experiments.services:nothing", 1),
        (9, "tree.children[0].setup"),
        f"'{SERVICE[:-8]}:nothing': {SERVICE[:-8]} has no attribute 'nothing'",
    ),
    "an option the setup does not take is refused at the options line": (
        BASE.replace('uses = ["db"]', 'usse = ["db"]'),
        (14, "tree.children[1].options"),
        f"{SERVICE} cannot be called with these: got an unexpected keyword argument 'usse'",
    ),
    "a fault naming a manager not in the tree is refused": (
        fault("at = 1.0", target='"cache"'),
        (24, "faults[0].target"),
        "no manager 'cache' in the tree (managers: db, api)",
    ),
    "a fault naming an unknown manager in a list points at that element": (
        fault("at = 1", target='[\n  "db",\n  "x",\n]'),
        (26, "faults[0].target[1]"),
        "no manager 'x' in the tree (managers: db, api)",
    ),
    "a workload call to an unknown manager is refused": (
        BASE.replace('manager = "api"', 'manager = "apj"'),
        (20, "workload.calls[0].manager"),
        "no manager 'apj' in the tree; did you mean 'api'? (managers: db, api)",
    ),
    "a name used twice in the tree is refused": (
        BASE.replace('name = "api"', 'name = "db"'),
        (12, "tree.children[1].name"),
        "the name 'db' is used twice in the tree",
    ),
    "a request template with an unknown placeholder is refused": (
        BASE + 'request = { name = "x-{keys}" }\n',
        (22, "workload.calls[0].request.name"),
        "unknown placeholder {keys}; known: {client}, {key}, {pid}, {run_dir}",
    ),
    "a cancel without awaited calls is refused as doing nothing": (
        BASE.replace("clients = 1", "clients = 1\ncancel = 0.5"),
        (18, "workload.cancel"),
        "cancels only awaited calls: give 'awaited' (how many a client awaits at once)",
    ),
    # when a fault fires
    "a negative time is refused": (
        fault("at = -1.0"),
        (25, "faults[0].at"),
        "must be seconds >= 0, got -1.0",
    ),
    "a negative duration is refused": (
        BASE.replace("duration = 2.0", "duration = -2.0"),
        (2, "duration"),
        "must be a positive number of seconds, got -2.0",
    ),
    "a fault after the end of the run is refused": (
        fault("at = [1.0, 2.0]"),
        (25, "faults[0].at[1]"),
        "2.0 s is not before the end of the run (2 s)",
    ),
    "a fault without a time says how to give one": (
        fault(),
        (22, "faults[0]"),
        "say when: give one of 'at', 'every' or 'after'",
    ),
    "a hang of a thread manager is refused": (
        fault("at = 1", "for = 1", kind="hang_manager").replace(
            'name = "db"', 'name = "db"\nisolation = "thread"'
        ),
        (25, "faults[0].target"),
        "hang_manager needs a process manager; 'db' has isolation 'thread'",
    ),
    "kill resource in a tree of thread managers is refused": (
        fault("at = 1", kind="kill_resource", target=None).replace(
            'setup = "', 'isolation = "thread"\nsetup = "'
        ),
        (24, "faults[0]"),
        "kill_resource kills resource processes of process managers; every manager of this"
        " tree has isolation 'thread'",
    ),
    "a load error with for and loads is refused": (
        fault("at = 1", "for = 0.5", "loads = 3", kind="load_error"),
        (27, "faults[0].loads"),
        "give either 'for' (seconds) or 'loads' (a number), not both",
    ),
    "a trigger on a field the event does not have is refused": (
        fault('after = { event = "ChildRestarted", name = "db" }'),
        (25, "faults[0].after.name"),
        "unknown key; known here: child, host, nth, pid, restart_s, supervisor",
    ),
    "a trigger on a child not in the tree is refused": (
        fault('after = { event = "ChildRestarted", child = "nosuch" }'),
        (25, "faults[0].after.child"),
        "'nosuch' names nothing in this run (it may be: api, db)",
    ),
    "a trigger value of the wrong type is refused": (
        fault('after = { event = "ChildRestarted", child = 3 }'),
        (25, "faults[0].after.child"),
        "must be a string, got 3",
    ),
    "a trigger on an unknown status is refused": (
        fault('after = { event = "StatusSent", status = "fatal" }'),
        (25, "faults[0].after.status"),
        "must be one of 'OK', 'UPDATE', 'WARNING', 'ERROR', 'FATAL', got 'fatal'",
    ),
    # limits: times and counts that would hang or crash a run (review items 1 and 2)
    "an interval below a millisecond is refused": (
        fault("every = 1e-6"),
        (25, "faults[0].every"),
        "must be at least 0.001 s, got 1e-06",
    ),
    "a random interval below a millisecond is refused": (
        fault("every = { min = 1e-6, max = 1.0 }"),
        (25, "faults[0].every.min"),
        "must be at least 0.001 s, got 1e-06",
    ),
    "a fault that would inject too often is refused": (
        fault("every = 0.001").replace("duration = 2.0", "duration = 1000.0"),
        (25, "faults[0].every"),
        "would inject up to 1000000 times in a run (at most 100000 per fault): give a longer"
        " interval, a 'count' or a 'stop'",
    ),
    "a rate so low that its gaps overflow is refused": (
        BASE.replace("clients = 1", "clients = 1\nrate = 1e-300"),
        (18, "workload.rate"),
        'must be calls per second (at least 1e-06, at most 1e+06) or "max", got 1e-300',
    ),
    "a trigger delay past the end of the run is refused": (
        fault('after = { event = "ChildRestarted" }', "delay = 2.0"),
        (26, "faults[0].delay"),
        "2 s is not before the end of the run (2 s): it never fires",
    ),
    # bad types give a PlanError, not a traceback (review item 8)
    "a table as a fault target is refused": (
        fault("at = 1", target="{a=1}"),
        (24, "faults[0].target"),
        "must be a manager's name, got {'a': 1}",
    ),
    "a nested list as a fault target is refused": (
        fault("at = 1", target='[["db"]]'),
        (24, "faults[0].target[0]"),
        "must be a manager's name, got ['db']",
    ),
    "a list as the manager of a call is refused": (
        BASE.replace('manager = "api"', 'manager = ["api"]'),
        (20, "workload.calls[0].manager"),
        "must be a manager's name, got ['api']",
    ),
    # inputs that would do nothing (review item 9)
    "an empty list of times is refused": (
        fault("at = []"),
        (25, "faults[0].at"),
        "must be a non-empty array, got []",
    ),
    "an every that starts after the end is refused": (
        fault("every = 0.5", "start = 2.0"),
        (26, "faults[0].start"),
        "2 s is not before the end of the run (2 s)",
    ),
    "an every whose first interval ends after the run is refused": (
        fault("every = 0.5", "start = 1.6"),
        (25, "faults[0].every"),
        "the first injection (1.6 + 0.5 s) would not come before the end of the run (2 s)",
    ),
    "a stop after the end is refused": (
        fault("every = 0.5", "stop = 3.0"),
        (26, "faults[0].stop"),
        "3 s is after the end of the run (2 s); leave it out to inject until the end",
    ),
    # compare settings that would be ignored or mis-grouped (review item 7)
    "a compared value given twice is refused": (
        BASE + '[compare]\nsetting = "tree.strategy"\n'
        'values = ["one_for_one", "one_for_all", "one_for_one"]\n',
        (24, "compare.values[2]"),
        "'one_for_one' is given twice: each value runs once",
    ),
    "a compared setting that does not exist is refused": (
        BASE + '[compare]\nsetting = "tree.children.cache.heartbeat"\nvalues = [1]\n',
        (23, "compare.setting"),
        "'tree.children.cache.heartbeat': no element named 'cache'",
    ),
}
"""Each bad plan: its text, the line and key its `PlanError` names, and its whole problem."""


@pytest.mark.parametrize(("text", "where", "problem"), REFUSED.values(), ids=REFUSED.keys())
def test_a_bad_plan_is_refused_naming_its_line_its_key_and_the_whole_problem(
    text: str, where: tuple[int, str], problem: str
) -> None:
    error = plan_error(text)

    assert (where, problem) == ((error.line, error.key), error.problem)


def test_a_missing_plan_file_whose_name_is_close_to_a_shipped_plan_names_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)

    with pytest.raises(PlanError) as caught:
        load_plan("frist")

    assert "frist: cannot be read (" in str(caught.value)
    assert "; did you mean 'first'? (a shipped plan: plans.find() finds it)" in str(caught.value)


def test_a_trigger_on_an_unknown_event_is_refused() -> None:
    text = '[[faults]]\nkind = "kill_manager"\ntarget = "db"\nafter = { event = "Restarted" }\n'
    error = plan_error(BASE + text)

    assert (25, "faults[0].after.event") == (error.line, error.key)
    assert error.problem.startswith("must be one of 'ChildStarted', 'ChildExited',")
    assert error.problem.endswith(", got 'Restarted'; did you mean 'ChildRestarted'?")


def test_awaited_calls_cancelled_within_a_delay_become_the_workloads_values() -> None:
    workload = parse_plan(
        BASE.replace(
            "clients = 1", "clients = 1\nawaited = 100\ncancel = 0.7\ncancel_within = 0.008"
        )
    ).workload

    assert (100, 0.7, 0.008) == (workload.awaited, workload.cancel, workload.cancel_within)


def test_a_slow_status_callback_becomes_the_workloads_values_and_a_negative_wait_is_refused() -> (
    None
):
    workload = parse_plan(
        BASE.replace("clients = 1", "clients = 2\nstatus_wait = 0.2\nslow_clients = 2")
    ).workload
    error = plan_error(BASE.replace("clients = 1", "clients = 1\nstatus_wait = -0.1"))

    assert (0.2, 2) == (workload.status_wait, workload.slow_clients)
    assert (0.0, 1) == (
        parse_plan(BASE).workload.status_wait,
        parse_plan(BASE).workload.slow_clients,
    )
    assert (18, "workload.status_wait") == (error.line, error.key)


def test_text_that_is_not_toml_names_its_line() -> None:
    error = plan_error(BASE.replace("clients = 1", "clients = = 1"))

    assert 17 == error.line
    assert "is not valid TOML" in error.problem


def test_a_plan_file_that_does_not_exist_is_a_plan_error(tmp_path: Path) -> None:
    with pytest.raises(PlanError, match="cannot be read"):
        load_plan(tmp_path / "missing.toml")


def test_a_plan_file_that_is_a_pipe_or_too_big_is_refused_unread(tmp_path: Path) -> None:
    """Issue 68 item 3: a FIFO was read until someone wrote to it, a 200 MB file parsed."""
    fifo, big = tmp_path / "fifo.toml", tmp_path / "big.toml"
    os.mkfifo(fifo)
    with big.open("wb") as file:
        file.truncate(200 * 1024 * 1024)  # (sparse)

    with pytest.raises(PlanError) as pipe:
        load_plan(fifo)
    with pytest.raises(PlanError) as bigger:
        load_plan(big)

    assert f"{fifo}: not a regular file (a pipe): refused" == str(pipe.value)
    assert f"{big}: bigger than {reading.PLAN_LIMIT} bytes: not a plan" == str(bigger.value)


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


def test_overrides_apply_to_every_compared_value() -> None:
    plan = parse_plan(
        BASE + '[compare]\nsetting = "tree.strategy"\nvalues = ["one_for_one", "one_for_all"]\n'
    )

    changed = plan.with_changes(repeat=5, seed=9, duration=1.0)

    assert (5, 9, 1.0) == (changed.repeat, changed.seed, changed.duration)
    assert [(5, 9, 1.0)] * 2 == [(p.repeat, p.seed, p.duration) for _, p in changed.variants]


# -- limits: times and counts that would hang or crash a run (review items 1 and 2) ----------

KILL_DB = '[[faults]]\nkind = "kill_manager"\ntarget = "db"\n'


def test_a_count_keeps_a_short_interval_within_the_limit() -> None:
    text = BASE.replace("duration = 2.0", "duration = 1000.0")

    plan = parse_plan(text + KILL_DB + "every = 0.001\ncount = 10\n")

    assert 10 == plan.faults[0].count


@pytest.mark.parametrize(
    ("text", "line", "key"),
    [
        (BASE.replace("duration = 2.0", "duration = 1e300"), 2, "duration"),
        (BASE.replace("clients = 1", "clients = 1\nhold = 1e300"), 18, "workload.hold"),
        (BASE.replace("clients = 1", "clients = 1\ntimeout = 1e10"), 18, "workload.timeout"),
        (
            BASE.replace('name = "db"', 'name = "db"\nheartbeat = 1e10'),
            9,
            "tree.children[0].heartbeat",
        ),
        (
            BASE + KILL_DB.replace("kill_manager", "hang_manager") + "at = 1\nfor = 1e10\n",
            26,
            "faults[0].for",
        ),
        (BASE.replace("[tree]", "[tree]\nbackoff = { max = 1e300 }"), 5, "tree.backoff.max"),
    ],
)
def test_seconds_above_a_million_are_refused(text: str, line: int, key: str) -> None:
    error = plan_error(text)

    assert (line, key) == (error.line, error.key)
    assert error.problem.startswith("must be at most 1e+06 s")


def test_a_longer_duration_override_that_would_inject_too_often_is_refused() -> None:
    plan = parse_plan(BASE + KILL_DB + "every = 0.001\n")

    with pytest.raises(rr.ConfigError, match=r"faults\[0\] would inject more than 100000"):
        plan.with_changes(duration=1000.0)


def test_a_duration_override_above_a_million_seconds_is_refused() -> None:
    plan = parse_plan(BASE)

    with pytest.raises(rr.ConfigError, match="up to 1e"):
        plan.with_changes(duration=1e300)


# -- bad types give a PlanError, not a traceback (review item 8) -------------------------------


def test_a_setup_module_that_exits_on_import_is_a_plan_error(tmp_path: Path) -> None:
    (tmp_path / "exits_on_import.py").write_text("import sys\nsys.exit(3)\n")
    plan_file = tmp_path / "plan.toml"
    plan_file.write_text(BASE.replace(SERVICE, "exits_on_import:setup", 1))

    with pytest.raises(PlanError) as caught:
        load_plan(plan_file)

    assert (9, "tree.children[0].setup") == (caught.value.line, caught.value.key)
    assert "raised SystemExit(3)" in caught.value.problem


# -- templates that would fail in a client (review item 3) -------------------------------------


@pytest.mark.parametrize("template", ["{client:zz}", "{key!x}", "{key!r}", "{key:{client}}"])
def test_a_placeholder_with_a_conversion_or_format_is_refused(template: str) -> None:
    error = plan_error(BASE + f'request = {{ name = "{template}" }}\n')

    assert (22, "workload.calls[0].request.name") == (error.line, error.key)
    assert "a placeholder is only a name" in error.problem


def test_a_trigger_on_a_status_matches_the_status_itself() -> None:
    text = KILL_DB + 'after = { event = "StatusSent", registrar = "api", status = "FATAL" }\n'

    plan = parse_plan(BASE + text)

    assert {"registrar": "api", "status": rr.Status.FATAL} == plan.faults[0].after.match


# -- compare settings that would be ignored or mis-grouped (review item 7) ---------------------


@pytest.mark.parametrize("setting", ["seed", "repeat", "name", "description", "compare.values"])
def test_a_setting_the_experiment_reads_from_the_top_plan_cannot_be_compared(
    setting: str,
) -> None:
    error = plan_error(BASE + f'[compare]\nsetting = "{setting}"\nvalues = [1, 2]\n')

    assert (23, "compare.setting") == (error.line, error.key)
    assert error.problem.startswith(f"{setting!r} cannot be compared")


def test_equal_values_of_other_types_are_different_compared_values() -> None:
    text = '[compare]\nsetting = "tree.children.db.heartbeat"\nvalues = [1, 1.0, false]\n'

    plan = parse_plan(BASE + text)

    assert 3 == len(plan.variants)


NESTED = {
    "arrays": "a = " + "[" * 5000 + "]" * 5000 + "\n",
    "inline tables": "[tree]\nb = " + "{c = " * 5000 + "1" + "}" * 5000 + "\n",
}


class TestNestedTooDeep:
    """A plan nested deeper than Python's TOML reader recurses is a `PlanError`, not a traceback.

    `tomllib` recurses once per nested array or inline table; a plan file of a few kilobytes
    (`a = [[[[...]]]]`) used to end `rr-actors experiment` in a `RecursionError`.
    """

    @pytest.mark.parametrize("text", NESTED.values(), ids=NESTED.keys())
    def test_a_plan_nested_too_deeply_is_a_plan_error_naming_the_file(self, text: str) -> None:
        with pytest.raises(PlanError, match="nested too deeply"):
            parse_plan(text, source="deep.toml")

    def test_rr_actors_experiment_on_it_is_one_line_and_exit_code_2(
        self, tmp_path: Path, capsys: pytest.CaptureFixture[str]
    ) -> None:
        plan = tmp_path / "deep.toml"
        plan.write_text(NESTED["arrays"])

        assert 2 == main(["experiment", str(plan), "--out", str(tmp_path / "out")], io.StringIO())

        err = capsys.readouterr().err
        assert f"rr-actors experiment: {plan}: is not a plan: nested too deeply to read\n" == err
        assert not (tmp_path / "out").exists()


def test_an_integer_too_long_to_read_is_a_plan_error_naming_the_file() -> None:
    with pytest.raises(
        PlanError, match=r"^long\.toml: is not a plan: a number of over 4300 digits$"
    ):
        parse_plan("duration = " + "9" * 5000 + "\n", source="long.toml")


RULES_BASE = """\
name = "t"
description = '''
a text of
[several] lines
'''
duration = 2.0

[tree]

[[tree.children]]
name = "db"
setup = "rr_actors_lab.experiments.services:service"

[[faults]]
kind = "kill_manager"
target = "db"
at = 1.0
"""


def rules_plan_error(text: str) -> PlanError:
    with pytest.raises(PlanError) as caught:
        parse_plan(text, source="plan.toml")
    return caught.value


class TestRules:
    """The plan reader's generic decode and its rules: messages that name what is allowed."""

    def test_a_fault_key_of_another_kind_names_the_kinds_it_goes_with(self) -> None:
        error = rules_plan_error(RULES_BASE + "for = 1.0\n")

        assert (18, "faults[0].for") == (error.line, error.key)
        only = "'hang_manager' or 'load_error' or 'cut' or 'partition' or 'freeze'"
        only += (  # (the simulation's)
            " or 'partition_serving' or 'duplicate_delivery' or 'split_brain' or 'deaf_manager'"
        )
        assert f"does not go with kind 'kill_manager' (only {only})" == error.problem

    def test_a_backup_damage_goes_with_corrupt_backup_only_and_names_its_ways(self) -> None:
        error = rules_plan_error(RULES_BASE + 'how = "flip"\n')

        assert (18, "faults[0].how") == (error.line, error.key)
        assert "does not go with kind 'kill_manager' (only 'corrupt_backup')" == error.problem
        corrupt = RULES_BASE.replace('"kill_manager"', '"corrupt_backup"')
        error = rules_plan_error(corrupt + 'how = "shred"\n')
        assert (18, "faults[0].how") == (error.line, error.key)
        assert error.problem.startswith("must be one of 'delete', 'digests', 'flip'"), error
        assert "truncate" == parse_plan(corrupt + 'how = "truncate"\n').faults[0].how

    def test_a_trigger_status_of_the_wrong_type_names_the_statuses(self) -> None:
        error = rules_plan_error(
            RULES_BASE.replace("at = 1.0", 'after = { event = "StatusSent", status = 3 }')
        )

        assert (17, "faults[0].after.status") == (error.line, error.key)
        assert error.problem.startswith(
            "must be one of 'OK', 'UPDATE', 'WARNING', 'ERROR', 'FATAL'"
        )

    def test_a_key_after_a_multi_line_string_has_its_own_line(self) -> None:
        error = rules_plan_error(RULES_BASE.replace("duration = 2.0", "duration = -2.0"))

        assert (6, "duration") == (error.line, error.key)
        assert 2 == key_lines(RULES_BASE)[("description",)]

    def test_a_name_is_unique_in_the_whole_tree_the_top_supervisor_included(self) -> None:
        text = RULES_BASE.replace(
            '[[tree.children]]\nname = "db"',
            '[[tree.children]]\nname = "mid"\n\n[[tree.children.children]]\nname = "top"',
        )
        error = rules_plan_error(text.replace("[tree]", '[tree]\nname = "top"'))

        assert (15, "tree.children[0].children[0].name") == (error.line, error.key)
        assert "the name 'top' is used twice in the tree" == error.problem

    def test_an_error_deep_in_a_long_plan_names_its_line_in_a_few_parses(
        self,
        monkeypatch: pytest.MonkeyPatch,
    ) -> None:
        padding = "".join(f"# note {n}\n" for n in range(20_000))
        text = RULES_BASE.replace("[tree]\n", f"[tree]\n{padding}").replace(
            "at = 1.0", 'at = "soon"'
        )
        expected_line = text.splitlines().index('at = "soon"') + 1
        tries: list[int] = []  # the number of lines of each text the reader parses to find the line
        holds = reading._holds

        def counted(rows: list[str], path: reading.KeyPath) -> bool:
            tries.append(len(rows))
            return holds(rows, path)

        monkeypatch.setattr(reading, "_holds", counted)

        with pytest.raises(PlanError) as info:
            parse_plan(text)

        assert expected_line == info.value.line
        # bisection: at most log2(20,030) < 15 tries for each of the 3 key paths
        # ("faults", 0, "at") and its starts, not one try per line
        assert 0 < len(tries) <= 3 * 15, len(tries)


# -- the line of a key in a TOML text (`line_of`, `key_lines`): tables, arrays of tables and
# inline keys, and a long multi-line string inside an array

PLAN = """\
name = "t"
duration = -2.0

[tree]

[[tree.children]]
name = "db"
setup = "rr_actors_lab.experiments.services:service"

[workload]
clients = 1

[[workload.calls]]
manager = "db"
server = "resource"
request = [\"\"\"
{lines}\"\"\", "{{key}}"]
"""


@pytest.mark.parametrize("count", [3, 500])
def test_an_error_before_a_long_string_in_an_array_names_its_own_line(count: int) -> None:
    text = PLAN.format(lines="".join(f"line {n}\n" for n in range(count)))

    with pytest.raises(PlanError) as caught:
        parse_plan(text, source="plan.toml")

    assert (2, "duration") == (caught.value.line, caught.value.key)
    assert 16 == key_lines(PLAN.format(lines="a\nb\n"))[("workload", "calls", 0, "request", 0)]


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


def test_a_seed_whose_later_repeats_would_run_past_64_bits_is_refused() -> None:
    """Repeat `r` runs with `seed + r - 1`, which `runs.csv` records so that a run can be
    made again with `--seed`; `--seed` takes 64-bit integers only. A plan whose last repeat
    would run with a seed past them is refused when read, naming `seed`, rather than
    recording a seed nobody can give back."""
    error = plan_error(f"seed = {2**63 - 1}\nrepeat = 2\n" + BASE)

    assert "seed" in str(error)
