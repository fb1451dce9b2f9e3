"""What crosses the wire: frames of `token + pickle`, with a fast path for small data.

Wire format: one frame per message (`multiprocessing.connection` framing), `8-byte token
(little endian) + payload`. Small builtin data and the wire protocol's own records are
pickled by the C pickler alone (`plain`); everything else, the user's requests and
responses included, by cloudpickle (so they may be closures). A message's `reply` never
crosses: the sender keeps it under the token (0: no answer wanted). A receiver reads a
frame's header before its body: a frame whose payload is over its limit is skipped
without being kept (`Oversized`).

Code that crosses by value keeps the file it was written in:

```
 sender: code object ──► (_named, (code as cloudpickle pickles it, code.co_filename))
 receiver: _named(code named "<dynamic-code>", filename) ──► code.replace(co_filename=...)
```

cloudpickle 3.1.3 names every code object it pickles by value `"<dynamic-code>"` (so a
payload does not depend on where its function was defined: cloudpipe/cloudpickle#560,
for notebooks) and has no option to keep the name. A callback run in another process
(a `load`, a manager's `setup`: both are pickled by value when their module cannot be
imported there) would then show no file in a traceback, and no source line: a failed
load's cause (rule 4) or a manager's start error would not say where it failed. The
sender still knows the name, so it crosses beside the code and the receiver puts it back
(`dumps` pickles a setup the same way). Nested code (a closure's, a lambda's) is a code
object of its own and crosses the same way. With cloudpickle before 3.1.3 the name was
already there; nothing else about the code changes.
"""

from __future__ import annotations

import dataclasses
import io
import os
import pickle
import struct
import types
from collections.abc import Callable, Iterator
from multiprocessing.connection import Connection
from typing import Any

import cloudpickle

from rr_actors._core import runtime
from rr_actors._core.directory import Reply
from rr_actors._core.wire import WIRE_TYPES, WireMessage, plain
from rr_actors._types import Query, Status, StatusUpdate
from rr_actors.errors import (
    CallTimeoutError,
    ConfigError,
    DependencyCycleError,
    ErrorFrame,
    MessageTooLargeError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    ResourceLoadError,
    RrError,
    UnknownQueryError,
    UnknownServerError,
)

__all__ = [
    "NO_REPLY",
    "Oversized",
    "Run",
    "dumps",
    "frame",
    "frames",
    "payload_size",
    "plain",
    "unframe",
    "what",
]

NO_REPLY = 0
"""The token of a message that wants no answer."""

_TOKEN = struct.Struct("<Q")
_LENGTH = struct.Struct("!i")  # multiprocessing.connection's frame header
_LONG_LENGTH = struct.Struct("!iQ")  # ... for frames over 2 GiB: -1, then the length


@dataclasses.dataclass(frozen=True)
class Run(WireMessage):
    """Control request: run `fn(registrar)` in the registrar's process, answer its result."""

    fn: Callable[[Any], Any]
    reply: Reply | None

    def start(self, run: Callable[[Callable[[Any], Any]], Any], thread_name: str) -> None:
        """Run `run(self.fn)` on a fresh daemon thread (it may block; it is rare) and
        answer its result or error through `self.reply`. Both carriers' receivers use it."""
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


# Types pickled by reference with the C pickler's own machinery: cloudpickle's
# `reducer_override` (a Python call per object) is skipped for them, as for every wire
# message (`WIRE_TYPES`). Everything else goes through cloudpickle.
_VALUES_BY_REFERENCE: frozenset[type] = frozenset(
    {
        Query,
        Status,
        StatusUpdate,
        ErrorFrame,
        MessageTooLargeError,
        ResourceLoadError,
        DependencyCycleError,
        UnknownServerError,
        UnknownQueryError,
        RegistrarUnavailableError,
        RegistrarStoppedError,
        CallTimeoutError,
        ConfigError,
        RrError,
    }
)


def _by_reference(kind: type) -> bool:
    return kind in _VALUES_BY_REFERENCE or kind in WIRE_TYPES


# cloudpickle's own reducer of code objects, read once from its `Pickler.dispatch_table`
# (pickle's documented hook; which types cloudpickle puts there is its own business, so
# this is the one place rr_actors relies on it: tests/transport/test_codec.py checks it).
# A cloudpickle without it pickles code its own way, as it did before 3.1.3: file names
# may then be lost again, nothing else.
_CLOUDPICKLE_CODE: Callable[[types.CodeType], Any] | None = cloudpickle.Pickler.dispatch_table.get(
    types.CodeType
)


class _AsCloudpickleDoes:
    """A code object to pickle as cloudpickle does (the first half of `_reduce_code`)."""

    __slots__ = ("code",)

    def __init__(self, code: types.CodeType) -> None:
        self.code = code

    def __reduce__(self) -> Any:
        assert _CLOUDPICKLE_CODE is not None  # (only made when it is there)
        return _CLOUDPICKLE_CODE(self.code)


def _reduce_code(code: types.CodeType) -> tuple[Any, ...]:
    """A code object crosses with the name of its file (see the module docstring)."""
    return _named, (_AsCloudpickleDoes(code), code.co_filename)


def _named(code: types.CodeType, filename: str) -> types.CodeType:
    """`code` with its file's name put back, where cloudpickle changed it."""
    return code if code.co_filename == filename else code.replace(co_filename=filename)


class _Pickler(cloudpickle.Pickler):  # type: ignore[misc]
    """cloudpickle, with a fast path for the wire protocol's own types, and code that
    keeps its file's name."""

    def reducer_override(self, obj: Any) -> Any:
        kind = type(obj)
        if _by_reference(kind) or (kind is type and _by_reference(obj)):
            return NotImplemented
        if kind is types.CodeType and _CLOUDPICKLE_CODE is not None:  # (before its table)
            return _reduce_code(obj)
        return super().reducer_override(obj)


def frame(token: int, obj: Any) -> bytes:
    """The bytes on the wire for `obj`: header, `token`, pickle; pickling errors propagate.

    The header is `multiprocessing.connection`'s, so the receiver reads frames with
    `Connection.recv_bytes`. Small builtin data (`plain`) is pickled by the C pickler
    alone; everything else by cloudpickle.
    """
    if plain(obj):
        payload = pickle.dumps(obj, pickle.HIGHEST_PROTOCOL)
        size = len(payload) + _TOKEN.size
        if size <= 0x7FFFFFFF:
            return b"".join((_LENGTH.pack(size), _TOKEN.pack(token), payload))
        return b"".join((_LONG_LENGTH.pack(-1, size), _TOKEN.pack(token), payload))
    buffer = io.BytesIO()
    buffer.write(_LENGTH.pack(0))
    buffer.write(_TOKEN.pack(token))
    _Pickler(buffer, protocol=pickle.HIGHEST_PROTOCOL).dump(obj)
    size = buffer.tell() - _LENGTH.size
    if size > 0x7FFFFFFF:
        return _LONG_LENGTH.pack(-1, size) + buffer.getbuffer()[_LENGTH.size :]
    buffer.seek(0)
    buffer.write(_LENGTH.pack(size))
    return buffer.getvalue()


def dumps(obj: Any) -> bytes:
    """`obj` pickled as a frame's payload is (by cloudpickle, code keeping its file's name),
    for what reaches another process by another way (a manager's `setup`); pickling
    errors propagate."""
    buffer = io.BytesIO()
    _Pickler(buffer, protocol=pickle.HIGHEST_PROTOCOL).dump(obj)
    return buffer.getvalue()


@dataclasses.dataclass(frozen=True)
class Oversized:
    """A received frame whose payload was over the limit: skipped, only its token kept.

    Attributes:
        token: the frame's token (`NO_REPLY`: no answer wanted).
        size: its payload's size in bytes.
    """

    token: int
    size: int


def payload_size(data: bytes | memoryview) -> int:
    """The size in bytes of the payload (the pickled message) of a frame made by `frame`."""
    header = _LONG_LENGTH.size if data[:4] == b"\xff\xff\xff\xff" else _LENGTH.size
    return len(data) - header - _TOKEN.size


_SKIP_CHUNK = 64 * 1024


def frames(conn: Connection, limit: int | None = None) -> Iterator[bytes | bytearray | Oversized]:
    """The frames received on `conn`, until it ends (EOF, a socket error, a bad header).

    Reads each frame's header first (`multiprocessing.connection`'s framing), then its
    body. A frame whose payload is over `limit` bytes is not kept: once its token is
    read, an `Oversized` stands in for it (so it can be answered at once), then the rest
    of it is read into a small buffer and dropped; the connection stays in step for the
    frames after it.
    """
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
    """Exactly `size` bytes from `fd` (a `bytes`, or a `bytearray` if it took several reads).

    Returns `None` at an end of the stream before the first byte when `at_start`.

    Raises:
        EOFError: the stream ended part of the way.
    """
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
    """Split a received frame into token and payload; raises ValueError if it is too short."""
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
