"""Request digests (`rr_actors._catalog.digest`): equal values of different types share one,
a custom class or a value that raises has none, and a container subclass keeps its base's."""

from __future__ import annotations

import collections
import collections.abc
import decimal
import enum
import fractions
from typing import Any

import pytest

from rr_actors._catalog import (
    Catalog,
    ResourceState,
    request_digest,
)
from rr_actors._catalog.digest import requests_equal


class Level(enum.IntEnum):
    ONE = 1


class Name(enum.StrEnum):
    CAM = "cam"


@pytest.mark.parametrize(
    "values",
    [
        [1, 1.0, True, Level.ONE, decimal.Decimal(1), fractions.Fraction(1)],
        ["cam", Name.CAM],
        [b"ab", bytearray(b"ab")],
        [{"a": 1, "b": [2]}, {"b": [2.0], "a": True}],
        [{1, 2}, frozenset({2.0, 1})],
        [float("nan"), float("nan")],
    ],
)
def test_equal_values_of_different_types_have_one_digest(values):
    assert 1 == len({request_digest(v) for v in values})


def test_values_of_custom_classes_have_no_digest():
    class Loose(enum.Enum):
        A = 1

        def __eq__(self, other):
            return other == self.value

        __hash__ = enum.Enum.__hash__

    assert [None, None] == [request_digest(Loose.A), request_digest([object()])]


def test_a_plain_enum_member_is_digested_by_its_class_and_name():
    """Requests holding enum members (a robot's mode) are indexed, not scanned."""
    mode = {"mode": ResourceState.LOADED, "rate": 10}
    same = request_digest({"rate": 10.0, "mode": ResourceState.LOADED})
    other = request_digest({"mode": ResourceState.LOADING, "rate": 10})

    assert (same, True) == (request_digest(mode), other not in (None, same))


@pytest.mark.parametrize(
    "value",
    [
        collections.namedtuple("Point", "x y")(1, 2),
        collections.OrderedDict(a=1, b=2),
        collections.defaultdict(list, a=[1]),
    ],
    ids=repr,
)
def test_a_container_subclass_that_keeps_its_base_eq_keeps_its_base_digest(value: Any) -> None:
    base = {collections.OrderedDict: dict, collections.defaultdict: dict}.get(type(value), tuple)

    assert request_digest(base(value)) == request_digest(value)


# -- comparisons that raise -------------------------------------------------------------------


class RaisingItems(collections.abc.Mapping):  # type: ignore[type-arg]
    def __repr__(self) -> str:  # the test's id: the same in every pytest-xdist worker
        return "RaisingItems()"

    def __getitem__(self, key: Any) -> Any:
        raise KeyError(key)

    def __iter__(self) -> Any:
        raise RuntimeError("broken mapping")

    def __len__(self) -> int:
        return 1


@pytest.mark.parametrize(
    "request_value",
    [decimal.Decimal("sNaN"), {"x": [decimal.Decimal("sNaN")]}, RaisingItems()],
    ids=repr,
)
def test_a_request_that_raises_while_digested_or_compared_has_no_digest_and_never_raises(
    request_value: Any,
) -> None:
    catalog = Catalog()
    catalog.begin_load("r0", "s", {"plain": 1})
    catalog.begin_load("r1", "s", request_value)
    catalog.find("s", request_value)  # a comparison that raises means "different"

    assert (None, "r0", False) == (
        request_digest(request_value),
        catalog.find("s", {"plain": 1}).id,
        requests_equal(request_value, decimal.Decimal("sNaN")),
    )
