"""The restart policy's pure decisions (`rr_actors._supervision.policy`): the intensity
window on an injected clock."""

from __future__ import annotations

import pytest

from rr_actors._supervision.policy import RestartIntensity
from tests.support.supervising import (
    FakeClock,
)


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


# -- RestartIntensity -----------------------------------------------------------------------


def test_intensity_allows_max_restarts_within_the_period_and_not_one_more(
    clock: FakeClock,
) -> None:
    intensity = RestartIntensity(max_restarts=3, period=5.0, clock=clock)

    assert [True, True, True, False] == [intensity.add() for _ in range(4)]


def test_restarts_older_than_the_period_no_longer_count(clock: FakeClock) -> None:
    intensity = RestartIntensity(max_restarts=2, period=5.0, clock=clock)
    intensity.add()
    intensity.add()
    clock.now += 5.0

    assert (True, 1) == (intensity.add(), intensity.recent)


def test_zero_max_restarts_gives_up_at_the_first_crash(clock: FakeClock) -> None:
    assert not RestartIntensity(max_restarts=0, period=5.0, clock=clock).add()
