"""JSON from another host nested past Python's parser is refused like any garbage.

`json.loads` raises `RecursionError`, not a `ValueError`, for `[[[[...` a few hundred
kilobytes deep (far under the 32 MiB a host may send): the page's host logged a
traceback for every such message instead of dropping it unread.
"""

from __future__ import annotations

import logging

import pytest

from rr_actors.observe._crossing import decode


@pytest.mark.parametrize("data", [b"[" * 200_000, b'{"a":' * 200_000])
def test_a_message_nested_too_deeply_is_dropped_without_a_traceback(
    data: bytes, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.DEBUG, logger="rr_actors"):
        assert decode("robot", data) is None

    assert [] == [r for r in caplog.records if r.levelno >= logging.WARNING]
