"""What the supervisor's side gives back of a killed manager's events (`_process/received.py`):
its journal's, and its backup's outbox's (issue 40), each event once."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from rr_actors import events
from rr_actors._catalog import Catalog
from rr_actors._process.received import Received
from rr_actors._process.tally import Journal, Tally
from rr_actors._store.sqlite import SqliteStore

PID = 4242


def added(seq: int) -> events.ConsumerAdded:
    return events.ConsumerAdded(
        "erm", "r1", f"q{seq}", "app", at=1.5, pid=PID, seq=seq, host="robot", hlc=seq
    )


@pytest.fixture
def tally() -> Iterator[Tally]:
    made = Tally.create()
    assert made is not None
    yield made
    made.close()


def committed(path: Path, told: list[events.Event]) -> None:
    """Write one change per event, each with its event in the backup's outbox."""
    store = SqliteStore.open(path)
    store.load()
    catalog = Catalog()
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


def test_an_event_in_neither_is_still_counted_lost(tally: Tally, tmp_path: Path) -> None:
    journal = Journal.open(tally.path)
    assert journal is not None
    journal._write = lambda _fd, data: len(data)  # type: ignore[method-assign]  # (as if cut)
    journal(added(1))
    got: list[Any] = []
    received = Received(got.extend, tally, str(tmp_path / "none.db"))

    received.count_lost("erm", PID)

    [lost] = got
    assert (events.EventsDropped, 1, "killed") == (type(lost), lost.count, lost.cause)
