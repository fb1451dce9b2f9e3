"""What an experiment gives back (`rr_actors_lab.experiments.results`): runs.csv when compared
values give runs different columns: every column is kept."""

from __future__ import annotations

import csv
from pathlib import Path

from rr_actors_lab.experiments import parse_plan, run

PLAN = """\
name = "renamed"
duration = 0.3

[tree]
[[tree.children]]
name = "a"
setup = "rr_actors_lab.experiments.services:service"
isolation = "thread"

[compare]
setting = "tree.children.a.name"
values = ["a", "b"]
"""


def test_a_compared_manager_name_keeps_the_column_of_each_name(tmp_path: Path) -> None:
    run(parse_plan(PLAN), out=tmp_path / "out", record_events=False)

    with (tmp_path / "out" / "runs.csv").open(newline="") as file:
        reader = csv.DictReader(file)
        rows = list(reader)
        columns = reader.fieldnames or []

    assert ["unavailable_s_a", "unavailable_s_b"] == [
        c for c in columns if c.startswith("unavailable_s_")
    ]
    assert columns.index("unavailable_s_b") == columns.index("unavailable_s_a") + 1
    assert [("a", "0.0", ""), ("b", "", "0.0")] == [
        (r["value"], r["unavailable_s_a"], r["unavailable_s_b"]) for r in rows
    ]
