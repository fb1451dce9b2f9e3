"""What crosses the wire (`rr_actors._transport.codec`): the pickling of messages and
their frames, read as `multiprocessing.connection` writes them.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import multiprocessing.connection
import multiprocessing.context
import multiprocessing.forkserver
import multiprocessing.synchronize
import pickle
import socket
import struct
import threading
import traceback
import uuid
from typing import Any

import cloudpickle
import pytest

import rr_actors as rr
from rr_actors._core.wire import plain
from rr_actors._registrar.messages import Fetch, Load, Revoke
from rr_actors._transport.codec import frame, frames, unframe
from tests.core import test_wire as wire_tests

# -- encoding: the C pickler's fast path ----------------------------------------------------


class _MyStr(str):
    """A subclass of a builtin: not plain."""


def _nested(depth: int) -> list[Any]:
    value: list[Any] = []
    for _ in range(depth):
        value = [value]
    return value


# -- cutting frames out of the byte stream ------------------------------------------------------


def _frames_of(chunks: list[bytes]) -> list[bytes]:
    """What `_frames` yields for a peer that writes `chunks` one by one, then closes."""
    ours, theirs = socket.socketpair()
    conn = multiprocessing.connection.Connection(ours.detach())
    got: list[bytes] = []
    reader = threading.Thread(target=lambda: got.extend(frames(conn)))
    reader.start()
    with theirs:
        for chunk in chunks:
            theirs.sendall(chunk)
    reader.join(10)
    conn.close()
    return got


def _wire(payload: bytes) -> bytes:
    return struct.pack("!i", len(payload)) + payload


@pytest.mark.parametrize(
    "value",
    [
        Load("q1", "leaf", {"cmd": ["driver", "--id", 7], "rate": 2.5}, "C", ("C",), None),  # type: ignore[arg-type]
        Fetch("leaf", "C", None),  # type: ignore[arg-type]
        rr.Query("q2", "leaf", "P", "C", ("a", 1), {"pid": 4}),
        ("answer", 3, None, b"x", frozenset({1}), {2, 3}),
        rr.Status.FATAL,
    ],
)
def test_small_builtin_data_is_pickled_by_the_c_pickler_as_cloudpickle_would(value: Any) -> None:
    assert plain(value)
    data = frame(9, value)
    token, payload = unframe(data[4:])
    assert token == 9
    assert pickle.loads(payload) == value
    assert bytes(payload) == cloudpickle.dumps(value, pickle.HIGHEST_PROTOCOL)


@pytest.mark.parametrize(
    "value",
    [
        {"f": lambda: 1},  # needs cloudpickle
        [_MyStr("x")],  # a subclass
        Load("q1", "leaf", {"at": uuid.UUID(int=1)}, "C", (), None),  # not builtin data
        list(range(300)),  # too wide
        _nested(70),  # too deep
    ],
)
def test_anything_else_goes_through_cloudpickle(value: Any) -> None:
    assert not plain(value)
    token, payload = unframe(frame(1, value)[4:])
    assert token == 1
    decoded = cloudpickle.loads(payload)
    if not isinstance(value, dict):
        assert decoded == value


def test_code_pickled_by_value_keeps_its_file_so_a_traceback_shows_file_and_line() -> None:
    # (how: `rr_actors._core.wire`, tests/core/test_wire.py; here: a frame gets it)
    divide = pickle.loads(unframe(frame(1, wire_tests.divider())[4:])[1])

    with pytest.raises(ZeroDivisionError) as info:
        divide(0)

    called = traceback.extract_tb(info.value.__traceback__)[1:]  # (the first is this test's)
    written = wire_tests.__file__  # (where the function was written)
    assert [(written, "divide"), (written, "inverse")] == [(f.filename, f.name) for f in called]
    assert "return 1 / request  # the line a traceback must show" == called[-1].line


def test_a_load_crosses_without_its_reply_and_otherwise_unchanged() -> None:
    load = Load("q", "leaf", {"n": 1}, "C", ("C",), object())  # type: ignore[arg-type]
    assert load.detached() == dataclasses.replace(load, reply=None)


def test_every_wire_message_crosses_without_its_reply() -> None:
    fetch = Fetch("leaf", "C", object())  # type: ignore[arg-type]
    assert fetch.detached() == dataclasses.replace(fetch, reply=None)
    assert Revoke(("q",)).detached() == Revoke(("q",))  # (no reply to keep)


def test_many_frames_that_arrive_in_one_read_are_each_handed_on() -> None:
    payloads = [b"a", b"", b"bb" * 1000, b"c" * 70_000]

    assert payloads == _frames_of([b"".join(_wire(p) for p in payloads)])


def test_a_frame_that_arrives_a_byte_at_a_time_is_handed_on_whole() -> None:
    wire = _wire(b"hello") + _wire(b"world")

    assert [b"hello", b"world"] == _frames_of([wire[i : i + 1] for i in range(len(wire))])


def test_a_frame_larger_than_a_read_is_handed_on_whole() -> None:
    big = bytes(range(256)) * 4_000  # 1 MB: four reads' worth

    assert [big, b"after"] == _frames_of([_wire(big) + _wire(b"after")])


def test_the_long_header_of_multiprocessing_connection_is_understood() -> None:
    # Frames over 2 GiB carry -1 and then an 8-byte length; any size may use it.
    assert [b"long", b"short"] == _frames_of(
        [struct.pack("!iQ", -1, 4) + b"long" + _wire(b"short")]
    )


def test_a_connection_that_ends_inside_a_frame_hands_on_only_the_whole_ones() -> None:
    assert [b"whole"] == _frames_of([_wire(b"whole") + struct.pack("!i", 10) + b"cut"])


def test_frames_read_match_what_connection_recv_bytes_reads() -> None:
    sent = [frame(token, value) for token, value in enumerate([1, "two", {"three": [3]}])]

    got = _frames_of([b"".join(sent)])

    left, right = multiprocessing.Pipe()
    with left, right:
        for data in sent:
            left.send_bytes(data[4:])  # the payload; send_bytes adds the same header
        expected = [right.recv_bytes() for _ in sent]
    assert expected == got
