"""A manager process's journal (`_process/tally.py`): what the supervisor's side reads back."""

from __future__ import annotations

import errno
import os
import pickle
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from rr_actors import events
from rr_actors._process import tally as tally_module
from rr_actors._process.tally import Journal, Received, Tally
from tests.support.durable_pair import new_store


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

    kept = tally.kept(3)  # 1-3 arrived: only 4 and 5 are read

    assert ([4, 5], 2, 0) == ([e.seq for e in kept], Counted.unpickled, tally.doubted())


def test_a_record_cut_short_by_the_kill_ends_the_reading(tally: Tally) -> None:
    journal = Journal.open(tally.path)
    assert journal is not None
    for seq in (1, 2, 3):
        journal(Counted(seq))
    os.truncate(tally.path, os.path.getsize(tally.path) - 5)  # the kill within the third

    assert [1, 2] == [e.seq for e in tally.kept(0)]


def test_the_journal_hands_back_the_pickle_it_kept(tally: Tally) -> None:
    journal = Journal.open(tally.path)
    assert journal is not None

    data = journal(Counted(1))

    assert data is not None
    assert 1 == pickle.loads(data).seq
    assert [1] == [e.seq for e in tally.kept(0)]


def test_an_event_that_does_not_pickle_is_handed_back_as_none(tally: Tally) -> None:
    journal = Journal.open(tally.path)
    assert journal is not None

    assert journal(Unpicklable()) is None
    assert 2 == tally.doubted()  # (counted: lost if it is never sent)


class Unpicklable:
    seq = 2

    def __reduce__(self) -> Any:
        raise TypeError("not picklable")


# -- what the supervisor's side gives back of a killed manager's events (`Received`):
# its journal's, and its backup's outbox's, each event once
PID = 4242


def added(seq: int) -> events.ConsumerAdded:
    return events.ConsumerAdded(
        "erm", "r1", f"q{seq}", "app", at=1.5, pid=PID, seq=seq, host="robot", hlc=seq
    )


def committed(path: Path, told: list[events.Event]) -> None:
    """Write one change per event, each with its event in the backup's outbox."""
    store, catalog = new_store(path)
    catalog.begin_load("r1", "leaf", 1)
    catalog.finish_load("r1", 1)
    for event in told:
        catalog.add_consumer("r1", f"q{event.seq}", "app")  # type: ignore[union-attr]
        store.write(catalog.drain_changes(), (event,))
    store._db.close()  # (no clean close: killed)


def test_an_event_committed_but_never_published_is_given_back_from_the_outbox(
    tally: Tally, tmp_path: Path
) -> None:
    journal = Journal.open(tally.path)
    assert journal is not None
    backup = tmp_path / "erm.db"
    got: list[Any] = []
    received = Received(got.extend, tally, str(backup))
    for seq in (1, 2):
        journal(added(seq))
    received.deliver("erm", [added(1), added(2)])
    committed(backup, [added(1), added(2), added(3)])  # 3: killed after its commit

    received.count_lost("erm", PID)

    assert [1, 2, 3] == [e.seq for e in got]  # no EventsDropped: nothing is missing


def test_an_event_sent_out_of_order_and_lost_is_given_back_and_none_twice(
    tally: Tally, tmp_path: Path
) -> None:
    # Events built on two threads may be sent out of their order: 4 arrived, 3 (built
    # before its commit, on the actor's thread) never did, nor did it reach the journal.
    journal = Journal.open(tally.path)
    assert journal is not None
    backup = tmp_path / "erm.db"
    got: list[Any] = []
    received = Received(got.extend, tally, str(backup))
    for seq in (1, 2, 4, 5):
        journal(added(seq))
    received.deliver("erm", [added(1), added(2), added(4)])
    committed(backup, [added(2), added(3), added(5)])

    received.count_lost("erm", PID)

    assert [1, 2, 4, 3, 5] == [e.seq for e in got]


def _full(_fd: int, _data: bytes) -> int:
    raise OSError(errno.ENOSPC, "No space left on device")


def test_an_event_in_neither_is_still_counted_lost(tally: Tally, tmp_path: Path) -> None:
    journal = Journal.open(tally.path)
    assert journal is not None
    journal._write = _full  # type: ignore[method-assign]  # (a full disk: published, not kept)
    journal(added(1))
    got: list[Any] = []
    received = Received(got.extend, tally, str(tmp_path / "none.db"))

    received.count_lost("erm", PID)

    [lost] = got
    assert (events.EventsDropped, 1, "killed") == (type(lost), lost.count, lost.cause)


def test_nothing_is_read_back_at_an_exit_nobody_listens_to(tally: Tally, tmp_path: Path) -> None:
    # (a later subscriber hears nothing older than itself: reading them would be for nobody)
    journal = Journal.open(tally.path)
    assert journal is not None
    backup = tmp_path / "erm.db"
    journal(added(1))
    committed(backup, [added(1), added(2)])
    got: list[Any] = []
    received = Received(got.extend, tally, str(backup))

    received.count_lost("erm", PID, listened=False)

    assert ([], None) == (got, received.tally)  # read nothing, counted nothing; closed


# -- numbers no event took, and the journal's cut (issue 68: a killed process's last events)


def _kept(
    tally: Tally, tmp_path: Path, seqs: tuple[int, ...]
) -> tuple[Journal, list[Any], Received]:
    """A journal that kept events `seqs`, and a receiver (no backup) handing what it gets
    to the list."""
    journal = Journal.open(tally.path)
    assert journal is not None
    got: list[Any] = []
    received = Received(got.extend, tally, str(tmp_path / "none.db"))
    for seq in seqs:
        journal(added(seq))
    return journal, got, received


def test_numbers_of_events_a_kill_came_before_are_told_unused_not_lost(
    tally: Tally, tmp_path: Path
) -> None:
    # 3 was built on the actor's thread and waited for its commit; 4, built after it on
    # another thread, was published and kept; the kill came before 3's commit
    _journal, got, received = _kept(tally, tmp_path, (1, 2, 4))
    received.deliver("erm", [added(1), added(2)])

    received.count_lost("erm", PID)

    assert [1, 2, 4, "EventsUnpublished"] == [e.seq or type(e).__name__ for e in got]
    assert ((3,), PID) == (got[-1].seqs, got[-1].pid)


def test_an_event_kept_out_of_order_and_never_sent_is_given_back(
    tally: Tally, tmp_path: Path
) -> None:
    # 4 arrived; 3, built before it on another thread, was published (kept) after it had
    # been sent: a hole below the last number received, read back from the journal
    journal, got, received = _kept(tally, tmp_path, (1, 2, 4))
    received.deliver("erm", [added(1), added(2), added(4)])
    journal(added(3))

    received.count_lost("erm", PID)

    assert [1, 2, 4, 3] == [e.seq for e in got]


def test_a_record_torn_by_the_kill_is_a_kill_before_its_event(tally: Tally, tmp_path: Path) -> None:
    journal, got, received = _kept(tally, tmp_path, (1, 2, 4))
    journal(added(3))
    os.truncate(tally.path, os.path.getsize(tally.path) - 5)  # the kill within 3's write
    received.deliver("erm", [added(1), added(2)])

    received.count_lost("erm", PID)

    assert [1, 2, 4, "EventsUnpublished"] == [e.seq or type(e).__name__ for e in got]
    assert (3,) == got[-1].seqs


def test_events_kept_then_cut_from_the_journal_unsent_are_counted_lost(
    tally: Tally, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(tally_module, "JOURNAL_BYTES", 1)
    journal, got, received = _kept(tally, tmp_path, (1, 2, 3))
    received.deliver("erm", [added(1)])
    journal.sent()  # the batch of 1 went; 2 and 3, kept, are cut before they are sent
    journal(added(4))

    received.count_lost("erm", PID)

    assert [1, 4, "EventsDropped"] == [e.seq or type(e).__name__ for e in got]
    assert (2, "killed") == (got[-1].count, got[-1].cause)
