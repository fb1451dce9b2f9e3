"""How a value is pickled to leave its process (`rr_actors._core.wire.dumps`): code pickled
by value keeps its file's name (cloudpickle 3.1.3 names it `"<dynamic-code>"`), and small
builtin data takes the C pickler alone, with cloudpickle's bytes."""

from __future__ import annotations

import pickle
import traceback
from typing import Any

import cloudpickle
import pytest

from rr_actors._core import wire


def divider() -> Any:
    """A function of this file pickled by value (a closure), with a nested one of its own
    (tests/transport/test_codec.py frames it too)."""

    def divide(request: int) -> float:
        def inverse() -> float:
            return 1 / request  # the line a traceback must show

        return inverse()

    return divide


def test_code_pickled_by_value_keeps_its_file_so_a_traceback_shows_file_and_line() -> None:
    divide = pickle.loads(wire.dumps(divider()))

    with pytest.raises(ZeroDivisionError) as info:
        divide(0)

    called = traceback.extract_tb(info.value.__traceback__)[1:]  # (the first is this test's)
    assert [(__file__, "divide"), (__file__, "inverse")] == [(f.filename, f.name) for f in called]
    assert "return 1 / request  # the line a traceback must show" == called[-1].line


def test_cloudpickle_still_has_the_reducer_of_code_objects_it_is_asked_for() -> None:
    # the one thing of cloudpickle's own this relies on (pyproject.toml's pin says so)
    assert wire._CLOUDPICKLE_CODE is not None


@pytest.mark.parametrize("value", ["shared-2", {"a": [1, 2.5, None]}, ("a", 1, b"x")])
def test_small_builtin_data_is_pickled_by_the_c_pickler_as_cloudpickle_would(
    value: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    expected = cloudpickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
    monkeypatch.setattr(wire, "Pickler", None)  # (a pickler built: a TypeError)
    assert expected == wire.dumps(value)
