"""Spare manager processes (`rr_actors._process.spare`): forked ahead, warmed up while idle."""

from __future__ import annotations

from collections.abc import Callable

import pytest

import rr_actors as rr
from rr_actors import events
from rr_actors._process import child
from rr_actors._process.spare import Spare, SparePool
from rr_actors._store import schema
from tests.support.supervising import kill_and_wait_restarted, process
from tests.support.waiting import wait_for

BOUND = 30.0
"""Seconds a spare may take to be forked or to warm up on a loaded machine."""


def wait_until(condition: Callable[[], bool], what: str) -> None:
    """A bounded wait for a state no event announces (a spare's pipe): `waiting.wait_for`."""
    assert wait_for(condition, timeout=BOUND), what


def idle(pool: SparePool) -> list[Spare]:
    """Its idle spares, oldest first (its private fields: no runtime code needs a public view)."""
    with pool._cond:
        return list(pool._idle)


class TestStartAhead:
    """A tree's start forks each process manager's process ahead of its turn (issue 34 item 1).

    While one manager starts, the spare pool forks the processes of the ones after it (no
    more than the starts to come, without their warm-up); once the tree's start is over,
    the spares left warm up for a restart. The managers still start in order (the order
    tests of `tests/supervision` hold).
    """

    pytestmark = pytest.mark.usefixtures("process_helpers")  # the forkserver, before leak checks

    def test_a_start_of_one_manager_forks_no_spare_ahead(self) -> None:
        pool = SparePool(2, "ahead-one", delay=3600.0)
        try:
            pool.ahead(1)
            assert pool.take() is None  # the one start launches its own process
            pool.ahead(0)

            assert [] == idle(pool)
        finally:
            pool.close()

    def test_spares_are_forked_for_the_starts_to_come_and_warm_up_once_the_start_is_over(
        self,
    ) -> None:
        pool = SparePool(2, "ahead-three", delay=3600.0)
        try:
            pool.ahead(3)  # three starts: spares for the second and the third
            wait_until(lambda: len(idle(pool)) == 2, "two spares forked ahead")
            spares = idle(pool)
            assert [True, True] == [s.lean for s in spares]  # (not warming up)

            pool.ahead(0)  # the start is over: they warm up now, for a restart

            wait_until(lambda: all(s.check_warm() for s in spares), "the spares warmed up")
        finally:
            pool.close()


class TestWarmUp:
    """A spare manager process pays a restore's first-use costs while it idles: the schema
    objects a backup is checked against are made then, not after a crash (issue 20: they took
    2-3 ms of each restart at 1k entries).
    """

    def test_the_warm_up_makes_the_schema_objects_a_restore_checks_a_backup_against(self) -> None:
        schema._objects_of.cache_clear()  # as in a process that never opened a backup

        child._warm_up()

        assert 1 == schema._objects_of.cache_info().currsize
        misses = schema._objects_of.cache_info().misses
        assert schema.expected_objects() is schema.expected_objects()
        assert misses == schema._objects_of.cache_info().misses  # made once, by the warm-up


@pytest.mark.usefixtures("process_helpers")
def test_a_manager_a_spare_runs_after_a_kill_numbers_its_events(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    """A spare numbers the events of the manager it will run as it begins to idle
    (`standby`), not once it is taken: off the restart path (issue 71 item 5)."""
    name = f"erm-{uid}"
    sup = supervisors([process(name)]).start()
    pool = sup._tree.processes.spares
    assert pool is not None
    wait_until(lambda: any(s.check_warm() for s in idle(pool)), "a warm spare")
    idling = {s.process.pid for s in idle(pool)}  # (the oldest warm one is taken: any of them)
    kill_and_wait_restarted(sup, name)

    assert sup.child(name).pid in idling  # (the restart ran in a spare)
    built = sup.run_in(name, lambda _r: events.LoadFailed(name, "s", "r", "q", "E", "-").seq)
    assert built > 0
