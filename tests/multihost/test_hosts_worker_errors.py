"""A worker's own `TimeoutError` is not the harness's "no answer" (tests/support/hosts.py).

Since Python 3.11 `concurrent.futures.TimeoutError` is the builtin `TimeoutError`, which
rr_actors' `CallTimeoutError` subclasses: a call that timed out inside a worker must come
back as itself, not as "no answer within N s" (a bench once blamed the worker for a
timed-out `registrar.call` after a healed link).
"""

from __future__ import annotations

import pytest

from rr_actors.errors import CallTimeoutError
from tests.support import hosts


def time_out() -> None:
    raise CallTimeoutError("call to 'erm/echo' timed out after 2 s")


def test_a_timeout_raised_in_a_worker_is_raised_as_itself_not_as_no_answer() -> None:
    with hosts.local_host() as local, pytest.raises(CallTimeoutError) as raised:
        local.call(time_out, timeout=30)

    assert "timed out after 2 s" in str(raised.value)
    assert isinstance(raised.value.__cause__, hosts.RemoteTraceback)
