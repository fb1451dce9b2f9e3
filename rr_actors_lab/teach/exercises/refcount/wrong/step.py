"""A wrong answer a student may write (the tests check that it fails): never unload,
keeping every resource loaded for a later call (a cache that is never emptied)."""

from collections.abc import Collection


def unloads(left: Collection[str]) -> bool:
    del left
    return False
