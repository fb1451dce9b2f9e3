"""A wrong answer a student may write (the tests check that it fails): the same request
object, not an equal one (`is` for `==`): a request that came in a message is a copy,
never the stored object, so an equal call loads a second resource beside the first."""

from typing import Any


def shares(stored: Any, request: Any, loading: bool, failed: bool) -> bool:
    del loading
    return stored is request and not failed
