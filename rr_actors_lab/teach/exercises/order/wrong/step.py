"""A wrong answer a student may write (the tests check that it fails): "unload" put
one place too early, before the last dependency (an off-by-one in the insert)."""

from collections.abc import Sequence


def release_order(dependencies: Sequence[str]) -> list[str]:
    order = list(dependencies)
    order.insert(len(order) - 1, "unload")
    return order
