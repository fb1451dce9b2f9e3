"""The line of a key in a TOML text (`rr_actors.experiments._lines`): tables, arrays of tables
and inline keys, and a long multi-line string inside an array."""

from __future__ import annotations

import textwrap

import pytest

from rr_actors.experiments import PlanError, parse_plan
from rr_actors.experiments._lines import key_lines

PLAN = """\
name = "t"
duration = -2.0

[tree]

[[tree.children]]
name = "db"
setup = "rr_actors.experiments.services:service"

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
