"""A plan nested deeper than Python's TOML reader recurses is a `PlanError`, not a traceback.

`tomllib` recurses once per nested array or inline table; a plan file of a few kilobytes
(`a = [[[[...]]]]`) used to end `rr-actors experiment` in a `RecursionError`.
"""

from __future__ import annotations

import io
from pathlib import Path

import pytest

from rr_actors.__main__ import main
from rr_actors.experiments import PlanError, parse_plan

NESTED = {
    "arrays": "a = " + "[" * 5000 + "]" * 5000 + "\n",
    "inline tables": "[tree]\nb = " + "{c = " * 5000 + "1" + "}" * 5000 + "\n",
}


@pytest.mark.parametrize("text", NESTED.values(), ids=NESTED.keys())
def test_a_plan_nested_too_deeply_is_a_plan_error_naming_the_file(text: str) -> None:
    with pytest.raises(PlanError, match="nested too deeply"):
        parse_plan(text, source="deep.toml")


def test_rr_actors_experiment_on_it_is_one_line_and_exit_code_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plan = tmp_path / "deep.toml"
    plan.write_text(NESTED["arrays"])

    assert 2 == main(["experiment", str(plan), "--out", str(tmp_path / "out")], io.StringIO())

    err = capsys.readouterr().err
    assert f"rr-actors experiment: {plan}: is not a plan: nested too deeply to read\n" == err
    assert not (tmp_path / "out").exists()
