"""The Zenoh carrier's wire: key expressions and the header in front of every payload.

`Keys` builds and parses every key (no other module writes one); `header` and `parse`
the header. The layout: docs/explanation/inside.md ("The Zenoh wire").
"""

from __future__ import annotations

import re
import struct
import sys
from typing import NamedTuple

from rr_actors._core.wire import WIRE_VERSION
from rr_actors._transport.codec import NO_REPLY
from rr_actors.config import NAME

MESSAGE = 0
"""A message for a registrar (its frame's token says whether it wants an answer)."""
ANSWER = 1
"""An answer: its frame's token is the one of the message it answers."""
VERSION = 2
"""An answer saying the message was of another version and was not read."""
PLAIN = 0x80
"""A flag of the kind byte older senders set for builtin data; ignored when read (a buggy
sender can flag anything: no frame is unpickled on Zenoh's thread)."""

STAMPED = 0x40
"""A flag of the kind byte: an 8-byte clock stamp follows the frame's token (`envelope`)."""

PYTHON = (sys.version_info.major, sys.version_info.minor)

_MAGIC = b"rz"
_FIXED = struct.Struct("!2sBBBBB")  # magic, wire version, Python major, minor, kind, id length


class Header(NamedTuple):
    """What a payload's header says (sender, versions, kind, clock stamp); a fixed layout."""

    wire: int
    python: tuple[int, int]
    kind: int  # without the flags (`PLAIN` is ignored)
    sender: str
    size: int  # bytes of the header: the frame starts there
    stamp: int | None = None

    @property
    def ours(self) -> bool:
        """Whether it was written by a process of this wire version and Python minor."""
        return self.wire == WIRE_VERSION and self.python == PYTHON


def header(kind: int, sender: str) -> bytes:
    """The header of a payload of `kind` sent by the process whose Zenoh id is `sender`."""
    zid = sender.encode("ascii")
    return _FIXED.pack(_MAGIC, WIRE_VERSION, *PYTHON, kind, len(zid)) + zid


def parse(data: bytes) -> Header | None:
    """The header of `data`, or `None` if it is not one of ours."""
    if len(data) < _FIXED.size:
        return None
    magic, wire, major, minor, kind, length = _FIXED.unpack_from(data)
    end = _FIXED.size + length
    if magic != _MAGIC or len(data) < end:
        return None
    try:
        sender = data[_FIXED.size : end].decode("ascii")
    except UnicodeDecodeError:
        return None
    stamp = None
    if kind & STAMPED:
        at = end + _skip(data, end) + _TOKEN.size
        if len(data) < at + _TOKEN.size:
            return None
        (stamp,) = _TOKEN.unpack_from(data, at)
    return Header(wire, (major, minor), kind & ~(PLAIN | STAMPED), sender, end, stamp)


_TOKEN = struct.Struct("<Q")
_LONG = b"\xff\xff\xff\xff"  # the length field of a frame over 2 GiB starts so


def _skip(data: bytes | memoryview, at: int) -> int:
    """Bytes of the frame's length field at `at` (4, or 12 for a frame over 2 GiB)."""
    return 12 if data[at : at + 4] == _LONG else 4


def envelope(kind: int, sender: str, frame: bytes, stamp: int) -> bytes:
    """The payload of `frame` (`codec.frame`) of `kind`, sent by `sender` at `stamp`."""
    cut = _skip(frame, 0) + _TOKEN.size
    return b"".join(
        (header(kind | STAMPED, sender), frame[:cut], _TOKEN.pack(stamp), memoryview(frame)[cut:])
    )


def payload_of(data: bytes, head: Header) -> tuple[int, memoryview]:
    """The token and the pickle of the frame after `head`."""
    body = memoryview(data)[head.size :]
    skip = _skip(body, 0)
    if len(body) < skip + _TOKEN.size:
        return NO_REPLY, body[len(body) :]
    (token,) = _TOKEN.unpack_from(body, skip)
    after = skip + _TOKEN.size + (_TOKEN.size if head.stamp is not None else 0)
    return token, body[after:]


def versions_text(theirs: Header) -> str:
    return (
        f"rr_actors wire version {theirs.wire} on Python {theirs.python[0]}.{theirs.python[1]}"
        f" there, wire version {WIRE_VERSION} on Python {PYTHON[0]}.{PYTHON[1]} here"
    )


_ZID = re.compile(r"[0-9a-f]{1,32}")  # a Zenoh id as `str(session.zid())` writes it
_LIMIT_DIGITS = 19  # max_message_bytes: an int64 at most (and int() stays cheap)
_STAMP_DIGITS = 20  # a clock stamp: 64 bits at most (`_core.hlc`)
_COUNT_DIGITS = 6  # a count of hosts or members


class ServerKey(NamedTuple):
    """What a registrar's token says:
    `live/reg/<name>/<zid>/<sup>/<limit>/<stamp>/<side>/<members>`."""

    name: str
    zid: str
    supervisor: str  # a Zenoh id, or "none"
    limit: int
    stamp: int  # the clock stamp of when it began to serve (`_core.hlc`)
    side: int = 0  # the hosts its process heard then, its own included (0: unknown)
    members: int = 0  # the system's members then, as its process counted them (0: unknown)

    @property
    def who(self) -> str:  # (`resolve.Sided`)
        return self.zid

    @property
    def rank(self) -> tuple[int, int]:
        return (self.stamp, int(self.zid, 16))


class HostKey(NamedTuple):
    """What a host's token says: `live/host/<zid>/<most>` (its router's)."""

    zid: str
    most: int  # the most hosts the router heard at once, itself included


class NameAt(NamedTuple):
    """What a claim or a "stopped" mark says: registrar `name` at process `zid`."""

    name: str
    zid: str


OBSERVER_PARTS = ("state", "delta", "fault", "here")
"""What a host's observer declares under `rr/<system>/obs/<member>/`."""


class ObserverKey(NamedTuple):
    """What an observer key says: `obs/<member>/<part>`."""

    member: str
    part: str  # one of `OBSERVER_PARTS`


class Keys:
    """Every key expression of one system, built and parsed (a parser never raises)."""

    __slots__ = ("prefix",)

    def __init__(self, system: str) -> None:
        self.prefix = f"rr/{system}"

    def everything(self) -> str:
        """Every key of the system: what its access-control rule allows."""
        return f"{self.prefix}/**"

    def registrar(self, name: str) -> str:
        """Messages for registrar `name` (its subscriber)."""
        return f"{self.prefix}/reg/{name}"

    def answers(self, zid: str) -> str:
        """Answers for process `zid` (its subscriber)."""
        return f"{self.prefix}/ans/{zid}"

    def ping(self, zid: str) -> str:
        """Process `zid`'s queryable that answers a ping."""
        return f"{self.prefix}/ping/{zid}"

    def events(self, zid: str) -> str:
        """Process `zid`'s events (JSON lines)."""
        return f"{self.prefix}/ev/{zid}"

    def all_events(self) -> str:
        return f"{self.prefix}/ev/*"

    def live(self) -> str:
        """Every liveliness token of the system (what presence subscribes to)."""
        return f"{self.prefix}/live/**"

    def live_of(self, name: str) -> str:
        """Every liveliness token that names registrar `name` (what presence asks)."""
        return f"{self.prefix}/live/*/{name}/**"

    def proc(self, zid: str) -> str:
        """Process `zid`'s token: it is a member."""
        return f"{self.prefix}/live/proc/{zid}"

    def server(self, server: ServerKey) -> str:
        name, zid, supervisor, limit, stamp, side, members = server
        return f"{self.prefix}/live/reg/{name}/{zid}/{supervisor}/{limit}/{stamp}/{side}/{members}"

    def host(self, host: HostKey) -> str:
        return f"{self.prefix}/live/host/{host.zid}/{host.most}"

    def claim(self, at: NameAt) -> str:
        """A claim: `at.zid` is about to serve `at.name`."""
        return f"{self.prefix}/live/claim/{at.name}/{at.zid}"

    def stopped(self, at: NameAt) -> str:
        """A "stopped" mark: `at.name` at `at.zid` was stopped cleanly."""
        return f"{self.prefix}/live/stopped/{at.name}/{at.zid}"

    def observer(self, at: ObserverKey) -> str:
        return f"{self.prefix}/obs/{at.member}/{at.part}"

    def observers(self, part: str) -> str:
        """Key `part` of every host's observer."""
        return f"{self.prefix}/obs/*/{part}"

    def certificate(self, member: str) -> str:
        """The queryable of host `member`'s router that answers with its certificate."""
        return f"{self.prefix}/cert/{member}"

    def parse_observer(self, key: str) -> ObserverKey | None:
        head = f"{self.prefix}/obs/"
        if not key.startswith(head):
            return None
        parts = key[len(head) :].split("/")
        if len(parts) != 2 or not NAME.fullmatch(parts[0]) or parts[1] not in OBSERVER_PARTS:
            return None
        return ObserverKey(parts[0], parts[1])

    def kind(self, key: str) -> str:
        """The kind of the liveliness token `key`; `""` if not a token of this system."""
        head = f"{self.prefix}/live/"
        return key[len(head) :].split("/", 1)[0] if key.startswith(head) else ""

    def parse_proc(self, key: str) -> str | None:
        parts = self._live(key, "proc", 1)
        return parts[0] if parts is not None and _zid(parts[0]) else None

    def parse_server(self, key: str) -> ServerKey | None:
        """What a registrar's token says (one without `<side>/<members>`: 0, unknown)."""
        parts = self._live(key, "reg", 5, 7)
        if parts is None:
            return None
        name, zid, supervisor, limit, stamp, *sides = parts
        if not (
            NAME.fullmatch(name)
            and _zid(zid)
            and (supervisor == "none" or _zid(supervisor))
            and _number(limit, _LIMIT_DIGITS)
            and int(limit) > 0
            and _number(stamp, _STAMP_DIGITS)
            and int(stamp) < 1 << 64
            and all(_number(count, _COUNT_DIGITS) for count in sides)
        ):
            return None
        side, members = (int(count) for count in sides) if sides else (0, 0)
        return ServerKey(name, zid, supervisor, int(limit), int(stamp), side, members)

    def parse_host(self, key: str) -> HostKey | None:
        parts = self._live(key, "host", 2)
        if parts is None or not _zid(parts[0]) or not _number(parts[1], _COUNT_DIGITS):
            return None
        return HostKey(parts[0], int(parts[1]))

    def parse_claim(self, key: str) -> NameAt | None:
        return self._name_at(key, "claim")

    def parse_stopped(self, key: str) -> NameAt | None:
        return self._name_at(key, "stopped")

    def _live(self, key: str, kind: str, *counts: int) -> list[str] | None:
        """The segments after `<prefix>/live/<kind>/`, if as many as one of `counts`."""
        head = f"{self.prefix}/live/{kind}/"
        if not key.startswith(head):
            return None
        parts = key[len(head) :].split("/")
        return parts if len(parts) in counts else None

    def _name_at(self, key: str, kind: str) -> NameAt | None:
        parts = self._live(key, kind, 2)
        if parts is None or not NAME.fullmatch(parts[0]) or not _zid(parts[1]):
            return None
        return NameAt(parts[0], parts[1])


def _zid(text: str) -> bool:
    return _ZID.fullmatch(text) is not None


def _number(text: str, digits: int) -> bool:
    """Whether `text` is at most `digits` ASCII digits as `str(int)` writes them."""
    return (
        text.isascii()
        and text.isdigit()
        and len(text) <= digits
        and (text == "0" or not text.startswith("0"))
    )
