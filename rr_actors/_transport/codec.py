"""What crosses the wire: frames of `token + pickle`, with a fast path for small data.

One frame per message (`multiprocessing.connection` framing): an 8-byte little-endian
token (0: no answer wanted), then the payload as `rr_actors._core.wire` pickles it.
"""

from __future__ import annotations

import dataclasses
import io
import os
import pickle
import struct
from collections.abc import Callable, Iterator
from multiprocessing.connection import Connection
from typing import Any

from rr_actors._core import runtime
from rr_actors._core.directory import Reply
from rr_actors._core.wire import Pickler, WireMessage, plain

NO_REPLY = 0
"""The token of a message that wants no answer."""

_TOKEN = struct.Struct("<Q")
_LENGTH = struct.Struct("!i")  # multiprocessing.connection's frame header
_LONG_LENGTH = struct.Struct("!iQ")  # ... for frames over 2 GiB: -1, then the length


@dataclasses.dataclass(frozen=True)
class Claim(WireMessage):
    """Rule 22: the kept one of two servers of `name` tells the other's process."""

    name: str
    who: str
    stamp: int
    process: int
    side: int = 0
    members: int = 0

    @property
    def rank(self) -> tuple[int, int]:
        return (self.stamp, self.process)


@dataclasses.dataclass(frozen=True)
class Run(WireMessage):
    """Control request: run `fn(registrar)` in the registrar's process, answer its result."""

    fn: Callable[[Any], Any]
    reply: Reply | None

    def start(self, run: Callable[[Callable[[Any], Any]], Any], thread_name: str) -> None:
        """Run `run(self.fn)` on a fresh daemon thread; answer its result or error."""
        reply = self.reply
        assert reply is not None

        def task() -> None:
            try:
                result = run(self.fn)
            except BaseException as exc:  # noqa: BLE001 - the caller gets it
                reply.set_error(exc)
            else:
                reply.set_result(result)

        runtime.Thread(target=task, name=thread_name, daemon=True).start()


def frame(token: int, obj: Any) -> bytes:
    """The bytes on the wire for `obj`: header, `token`, pickle; pickling errors propagate."""
    if plain(obj):
        payload = pickle.dumps(obj, pickle.HIGHEST_PROTOCOL)
        size = len(payload) + _TOKEN.size
        if size <= 0x7FFFFFFF:
            return b"".join((_LENGTH.pack(size), _TOKEN.pack(token), payload))
        return b"".join((_LONG_LENGTH.pack(-1, size), _TOKEN.pack(token), payload))
    buffer = io.BytesIO()
    buffer.write(_LENGTH.pack(0))
    buffer.write(_TOKEN.pack(token))
    Pickler(buffer, protocol=pickle.HIGHEST_PROTOCOL).dump(obj)
    size = buffer.tell() - _LENGTH.size
    if size > 0x7FFFFFFF:
        return _LONG_LENGTH.pack(-1, size) + buffer.getbuffer()[_LENGTH.size :]
    buffer.seek(0)
    buffer.write(_LENGTH.pack(size))
    return buffer.getvalue()


@dataclasses.dataclass(frozen=True)
class Oversized:
    """A received frame whose payload (`size` bytes) was over the limit: only its token kept."""

    token: int
    size: int


def payload_size(data: bytes | memoryview) -> int:
    """The size in bytes of the pickle in a frame made by `frame`."""
    header = _LONG_LENGTH.size if data[:4] == b"\xff\xff\xff\xff" else _LENGTH.size
    return len(data) - header - _TOKEN.size


_SKIP_CHUNK = 64 * 1024


def frames(conn: Connection, limit: int | None = None) -> Iterator[bytes | bytearray | Oversized]:
    """The frames received on `conn` until it ends; one over `limit` is an `Oversized`."""
    fd = conn.fileno()
    try:
        while True:
            header = _read(fd, _LENGTH.size, at_start=True)
            if header is None:
                return
            (size,) = _LENGTH.unpack(header)
            if size == -1:
                (size,) = struct.unpack("!Q", _read(fd, 8))
            elif size < 0:
                return  # not a frame of ours: the stream cannot be followed any further
            if limit is not None and size - _TOKEN.size > limit:
                (token,) = _TOKEN.unpack(_read(fd, _TOKEN.size))
                yield Oversized(token, size - _TOKEN.size)  # (answered before the rest comes)
                _skip(fd, size - _TOKEN.size)
                continue
            yield _read(fd, size)
    except (EOFError, OSError):
        return


def _read(fd: int, size: int, *, at_start: bool = False) -> Any:
    """Exactly `size` bytes from `fd`; at EOF `None` if `at_start`, else `EOFError`."""
    if size == 0:
        return b""
    data = os.read(fd, size)
    if len(data) == size:
        return data
    if not data:
        if at_start:
            return None
        raise EOFError
    buffer = bytearray(size)
    buffer[: len(data)] = data
    view = memoryview(buffer)
    got = len(data)
    while got < size:
        count = os.readv(fd, [view[got:]])
        if count == 0:
            raise EOFError
        got += count
    return buffer


def _skip(fd: int, size: int) -> None:
    """Read `size` bytes from `fd` and drop them, a small buffer at a time."""
    buffer = bytearray(min(size, _SKIP_CHUNK))
    view = memoryview(buffer)
    while size > 0:
        count = os.readv(fd, [view[: min(size, len(buffer))]])
        if count == 0:
            raise EOFError
        size -= count


def unframe(data: bytes | bytearray) -> tuple[int, memoryview]:
    """Token and payload of a received frame (ValueError if it is too short)."""
    if len(data) < _TOKEN.size:
        raise ValueError(f"a frame of {len(data)} bytes is too short to hold a token")
    (token,) = _TOKEN.unpack_from(data)
    return token, memoryview(data)[_TOKEN.size :]


def split_frame(data: bytes) -> tuple[int, memoryview]:
    """Token and payload of a whole frame made by `frame` (its header included)."""
    header = _LONG_LENGTH.size if data[:4] == b"\xff\xff\xff\xff" else _LENGTH.size
    return unframe(memoryview(data)[header:])  # type: ignore[arg-type]


def what(message: Any, target: str) -> str:
    """A few words naming a message, for error texts."""
    server = getattr(message, "server", None)
    if isinstance(server, str) and hasattr(message, "request"):
        return f"request of call to '{target}/{server}'"
    if isinstance(message, Run):
        return f"function run on registrar {target!r}"
    return f"{type(message).__name__} message to registrar {target!r}"
