"""JSON from another host nested past Python's parser is refused like any garbage.

`json.loads` raises `RecursionError`, not a `ValueError`, for `[[[[...` a few hundred
kilobytes deep (far under the 32 MiB a host may send): the page's host logged a
traceback for every such message instead of dropping it unread, and a fault request of
the page 2 KiB deep was a 500 instead of a 400.
"""

from __future__ import annotations

import json
import logging
import uuid

import pytest

import rr_actors as rr
from rr_actors.observe._crossing import decode
from tests.support.observing import request
from tests.support.supervising import echo_setup


@pytest.mark.parametrize("data", [b"[" * 200_000, b'{"a":' * 200_000], ids=["arrays", "objects"])
def test_a_message_nested_too_deeply_is_dropped_without_a_traceback(
    data: bytes, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.DEBUG, logger="rr_actors"):
        assert decode("robot", data) is None

    assert [] == [r for r in caplog.records if r.levelno >= logging.WARNING]


def test_a_fault_request_nested_too_deeply_is_a_400_and_nothing_is_done() -> None:
    pytest.importorskip("uvicorn")
    name = f"erm-{uuid.uuid4().hex[:8]}"
    with rr.Supervisor([rr.ManagerSpec(name, echo_setup)]) as sup:
        observer = sup.observe(allow_faults=True)
        headers = {"Content-Type": "application/json"}
        body = b"[" * 2000 + b"]" * 2000  # (under the 4 KiB a request may have)

        status, _, answer = request(
            observer.url, "/api/faults/kill", method="POST", body=body, headers=headers
        )

        assert (400, "the body is not JSON") == (status, json.loads(answer)["message"])
        assert "running" == sup.child(name).state
