"""A wrong answer a student may write (the tests check that it fails): every status
climbs, but a repeated one is taken as no news and stops: the camera's second WARNING
never reaches the actions' clients."""

from collections.abc import Collection

from rr_actors import Status

_last: dict[str, Status] = {}  # the last status climbed to each parent


def climb(parent: str | None, resources: Collection[str], status: Status) -> list[str]:
    if parent is None or parent not in resources or _last.get(parent) is status:
        return []
    _last[parent] = status
    return [parent]
