"""A wrong answer a student may write (the tests check that it fails): the stale ids
released, but no id ever named unknown (the provider lost them, and says nothing)."""

from collections.abc import Set


def reconcile(mine: Set[str], held: Set[str], under_way: Set[str]) -> tuple[set[str], set[str]]:
    del under_way
    return set(mine - held), set()
