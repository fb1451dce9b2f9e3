"""Rule 22's policy (`resolve=`): which of two servers of one name a heal keeps."""

from __future__ import annotations

import dataclasses
import logging

import pytest

import rr_actors as rr
from rr_actors._core.hlc import from_seconds
from rr_actors._transport.resolve import Resolution


@dataclasses.dataclass(frozen=True)
class Server:
    """A carrier's view of a server (`Sided`)."""

    who: str
    at: float
    side: int = 0
    members: int = 0

    @property
    def stamp(self) -> int:
        return from_seconds(self.at)

    @property
    def rank(self) -> tuple[int, int]:
        return (self.stamp, int(self.who))


LONE = Server("7", 100.0, side=3, members=3)  # served first, with every host heard
MAJORITY = Server("9", 200.0, side=2, members=3)  # began beyond a cut, on two of three
MINORITY = Server("8", 300.0, side=1, members=3)  # began beyond a cut, alone
UNKNOWN = Server("6", 400.0)  # a carrier that does not say its side


@pytest.mark.parametrize(
    ("servers", "first_served", "majority"),
    [
        ([LONE, MAJORITY], LONE, MAJORITY),  # (both began on a majority: the later)
        ([MAJORITY, LONE], LONE, MAJORITY),  # (the order they are seen in does not matter)
        ([LONE, MINORITY], LONE, LONE),
        ([MAJORITY, MINORITY], MAJORITY, MAJORITY),
        ([UNKNOWN, MINORITY], MINORITY, MINORITY),  # (a tie: first served)
        ([LONE, MAJORITY, MINORITY], LONE, MAJORITY),
    ],
)
def test_each_named_strategy_keeps_one_server_whatever_order_they_are_seen_in(
    servers: list[Server], first_served: Server, majority: Server
) -> None:
    assert first_served == Resolution("first_served").kept("erm", servers)
    assert majority == Resolution("majority").kept("erm", servers)
    assert majority == Resolution("majority").kept("erm", servers[::-1])


def test_a_function_gets_plain_data_first_served_first_and_chooses() -> None:
    given: list[rr.Claimant] = []

    def later(first: rr.Claimant, second: rr.Claimant) -> rr.Claimant:
        given.extend((first, second))
        return second

    assert MAJORITY == Resolution(later).kept("erm", [MAJORITY, LONE])
    assert [
        rr.Claimant("erm", "7", LONE.stamp, 100.0, side=3, members=3),
        rr.Claimant("erm", "9", MAJORITY.stamp, 200.0, side=2, members=3),
    ] == given


@pytest.mark.parametrize(
    ("resolve", "logged"),
    [
        (lambda first, second: 1 / 0, "raised ZeroDivisionError"),
        (lambda first, second: "the second", "which is neither claimant"),
    ],
    ids=["raises", "answers-neither"],
)
def test_a_function_that_fails_falls_back_to_first_served_with_a_warning(
    resolve: object, logged: str, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING, logger="rr_actors"):
        assert LONE == Resolution(resolve).kept("erm", [MAJORITY, LONE])

    assert [logging.WARNING] == [record.levelno for record in caplog.records]
    assert logged in caplog.text
    assert "registrar erm" in caplog.text


@pytest.mark.parametrize("resolve", ["largest", "", None, 3, rr.Claimant])
def test_a_resolve_that_is_no_strategy_is_a_config_error(resolve: object) -> None:
    with pytest.raises(rr.ConfigError, match="resolve must be"):
        Resolution(resolve)
