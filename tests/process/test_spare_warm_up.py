"""A spare manager process pays a restore's first-use costs while it idles: the schema
objects a backup is checked against are made then, not after a crash (issue 20: they took
2-3 ms of each restart at 1k entries)."""

from __future__ import annotations

from rr_actors._process import child
from rr_actors._store import schema


def test_the_warm_up_makes_the_schema_objects_a_restore_checks_a_backup_against() -> None:
    schema._objects_of.cache_clear()  # as in a process that never opened a backup

    child._warm_up()

    assert 1 == schema._objects_of.cache_info().currsize
    misses = schema._objects_of.cache_info().misses
    assert schema.expected_objects() is schema.expected_objects()
    assert misses == schema._objects_of.cache_info().misses  # made once, by the warm-up
