"""The line of a plan's error when the text holds a long multi-line string inside an array."""

from __future__ import annotations

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
