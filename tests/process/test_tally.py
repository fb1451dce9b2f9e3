"""A manager process's journal (`_process/tally.py`): what the supervisor's side reads back."""

from __future__ import annotations

import os
import pickle
from collections.abc import Iterator
from typing import Any

import pytest

from rr_actors._process.tally import Journal, Tally


class Counted:
    """An event stand-in that counts how often it was unpickled."""

    unpickled = 0

    def __init__(self, seq: int) -> None:
        self.seq = seq

    def __setstate__(self, state: dict[str, Any]) -> None:
        Counted.unpickled += 1
        self.__dict__.update(state)


@pytest.fixture
def tally() -> Iterator[Tally]:
    made = Tally.create()
    assert made is not None
    yield made
    made.close()


def test_the_events_that_arrived_are_skipped_unread(tally: Tally) -> None:
    journal = Journal.open(tally.path)
    assert journal is not None
    for seq in range(1, 6):
        journal(Counted(seq))
    Counted.unpickled = 0

    kept = tally.after(3)  # 1-3 arrived: only 4 and 5 are read

    assert ([4, 5], 2, 5) == ([e.seq for e in kept], Counted.unpickled, tally.built())


def test_a_record_cut_short_by_the_kill_ends_the_reading(tally: Tally) -> None:
    journal = Journal.open(tally.path)
    assert journal is not None
    for seq in (1, 2, 3):
        journal(Counted(seq))
    os.truncate(tally.path, os.path.getsize(tally.path) - 5)  # the kill within the third

    assert [1, 2] == [e.seq for e in tally.after(0)]


def test_the_journal_hands_back_the_pickle_it_kept(tally: Tally) -> None:
    journal = Journal.open(tally.path)
    assert journal is not None

    data = journal(Counted(1))

    assert data is not None
    assert 1 == pickle.loads(data).seq
    assert [1] == [e.seq for e in tally.after(0)]


def test_an_event_that_does_not_pickle_is_handed_back_as_none(tally: Tally) -> None:
    journal = Journal.open(tally.path)
    assert journal is not None

    assert journal(Unpicklable()) is None
    assert 2 == tally.built()  # (counted: lost if it is never sent)


class Unpicklable:
    seq = 2

    def __reduce__(self) -> Any:
        raise TypeError("not picklable")
