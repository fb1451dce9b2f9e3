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

__all__ = [
    "ANSWER",
    "MESSAGE",
    "OBSERVER_PARTS",
    "PLAIN",
    "PYTHON",
    "STAMPED",
    "VERSION",
    "Header",
    "HostKey",
    "Keys",
    "NameAt",
    "ObserverKey",
    "ServerKey",
    "claim_key",
    "envelope",
    "header",
    "host_key",
    "parse",
    "payload_of",
    "proc_key",
    "server_key",
    "stopped_key",
    "versions_text",
]

MESSAGE = 0
"""A message for a registrar (its frame's token says whether it wants an answer)."""
ANSWER = 1
"""An answer: its frame's token is the one of the message it answers."""
VERSION = 2
"""An answer saying the message was of another version and was not read."""
PLAIN = 0x80
"""A flag of the kind byte that older senders of this wire version set when the pickle held
only builtin data (their receivers decoded such a frame on Zenoh's own thread). It is no
longer set, and ignored when read: a buggy sender can flag anything, so no frame is
unpickled on Zenoh's thread."""

STAMPED = 0x40
"""A flag of the kind byte: an 8-byte clock stamp follows the frame's token (`envelope`)."""

PYTHON = (sys.version_info.major, sys.version_info.minor)

_MAGIC = b"rz"
_FIXED = struct.Struct("!2sBBBBB")  # magic, wire version, Python major, minor, kind, id length


class Header:
    """What a payload's header says: who sent it, in which versions, what kind it is, and
    the sender's clock stamp (`None`: none came).

    A message or an answer carries the sender's hybrid logical clock stamp (`_core.hlc`):
    its kind has the `STAMPED` flag, and the 8-byte stamp (little endian) follows the
    frame's token, before the pickle (`envelope`). There, a process of another wire version
    still reads the token, to answer `VERSION`; the frame's length field is not the
    frame's then (it is never read: the sample's length is). The receiver's clock takes the
    stamp in before the message is handled (`inbox`).

    The header's layout never changes, so a process of another rr_actors wire version or
    Python minor version can always read it: nothing after it is unpickled unless both
    versions match (pickles do not cross those safely); a message of another version is
    answered with a `VERSION` frame that carries no pickle, only the header.
    """

    __slots__ = ("kind", "python", "sender", "size", "stamp", "wire")

    def __init__(
        self,
        wire: int,
        python: tuple[int, int],
        kind: int,
        sender: str,
        size: int,
        stamp: int | None = None,
    ):
        self.wire = wire
        self.python = python
        self.kind = kind & ~(PLAIN | STAMPED)  # (PLAIN is ignored: see `PLAIN`)
        self.sender = sender
        self.size = size  # bytes of the header: the frame starts there
        self.stamp = stamp

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
    return Header(wire, (major, minor), kind, sender, end, stamp)


_TOKEN = struct.Struct("<Q")


_LONG = b"\xff\xff\xff\xff"  # the length field of a frame over 2 GiB starts so


def _skip(data: bytes | memoryview, at: int) -> int:
    """Bytes of the frame's length field at `at` (4, or 12 for a frame over 2 GiB)."""
    return 12 if data[at : at + 4] == _LONG else 4


def envelope(kind: int, sender: str, frame: bytes, stamp: int) -> bytes:
    """The payload of `frame` (`codec.frame`) of `kind`, sent by process `sender` with the
    clock stamp `stamp`."""
    cut = (12 if frame[:4] == _LONG else 4) + _TOKEN.size
    return b"".join(
        (header(kind | STAMPED, sender), frame[:cut], _TOKEN.pack(stamp), memoryview(frame)[cut:])
    )


def payload_of(data: bytes, head: Header) -> tuple[int, memoryview]:
    """The token and the pickle of the frame after `head` (nothing is unpickled).

    The frame's own length field (`multiprocessing.connection`'s: 4 bytes, or 12 for a
    frame over 2 GiB) is skipped: the Zenoh sample's length is the frame's. So is the
    clock stamp after the token, if `head` says there is one.
    """
    body = memoryview(data)[head.size :]
    skip = _skip(body, 0)
    if len(body) < skip + _TOKEN.size:
        return NO_REPLY, body[len(body) :]
    (token,) = _TOKEN.unpack_from(body, skip)
    after = skip + _TOKEN.size + (_TOKEN.size if head.stamp is not None else 0)
    return token, body[after:]


def versions_text(theirs: Header) -> str:
    """`wire version W on Python X.Y` for the sender of `theirs` and for this process."""
    return (
        f"rr_actors wire version {theirs.wire} on Python {theirs.python[0]}.{theirs.python[1]}"
        f" there, wire version {WIRE_VERSION} on Python {PYTHON[0]}.{PYTHON[1]} here"
    )


# -- key expressions ---------------------------------------------------------------------------
#
# `Keys` builds every key of a system and parses the liveliness ones: nothing else writes a
# key. One parser per kind of token (`rr/<system>/live/<kind>/...`): each returns `None` for
# a malformed key (a value, never an exception), so that a token a buggy member declared
# costs a log line, not the presence thread's work or a `serve`.

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
    """Every key expression of one system (docs/explanation/inside.md): built and parsed here.

    A builder takes what the key says and writes it (`keys.server(ServerKey(...))`); its
    parser (`keys.parse_server(key)`) gives it back, or `None` for a malformed key.

    Args:
        system: the system's name (a registrar name: `rr_actors.config.NAME`).
    """

    __slots__ = ("prefix",)

    def __init__(self, system: str) -> None:
        self.prefix = f"rr/{system}"

    # -- built -----------------------------------------------------------------------------

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
        """Process `zid`'s queryable that answers a ping (`outbox`)."""
        return f"{self.prefix}/ping/{zid}"

    def events(self, zid: str) -> str:
        """Process `zid`'s events (JSON lines: `events`)."""
        return f"{self.prefix}/ev/{zid}"

    def all_events(self) -> str:
        """The events of every process of the system (what a system-wide subscriber
        declares)."""
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
        """A registrar's token: `server.zid` serves `server.name`."""
        name, zid, supervisor, limit, stamp, side, members = server
        return f"{self.prefix}/live/reg/{name}/{zid}/{supervisor}/{limit}/{stamp}/{side}/{members}"

    def host(self, host: HostKey) -> str:
        """A host's token: `host.zid` is its router."""
        return f"{self.prefix}/live/host/{host.zid}/{host.most}"

    def claim(self, at: NameAt) -> str:
        """A claim: `at.zid` is about to serve `at.name`."""
        return f"{self.prefix}/live/claim/{at.name}/{at.zid}"

    def stopped(self, at: NameAt) -> str:
        """A "stopped" mark: `at.name` at `at.zid` was stopped cleanly."""
        return f"{self.prefix}/live/stopped/{at.name}/{at.zid}"

    def observer(self, at: ObserverKey) -> str:
        """Host `at.member`'s observer key `at.part` (one of `OBSERVER_PARTS`)."""
        return f"{self.prefix}/obs/{at.member}/{at.part}"

    def observers(self, part: str) -> str:
        """Key `part` of every host's observer (what a page's host subscribes to)."""
        return f"{self.prefix}/obs/*/{part}"

    def certificate(self, member: str) -> str:
        """The queryable of host `member`'s router that answers with its certificate."""
        return f"{self.prefix}/cert/{member}"

    # -- parsed ----------------------------------------------------------------------------

    def parse_observer(self, key: str) -> ObserverKey | None:
        """What an observer key `<prefix>/obs/<member>/<part>` says, or `None` if it is
        malformed (a member that is not a name, a part not in `OBSERVER_PARTS`)."""
        head = f"{self.prefix}/obs/"
        if not key.startswith(head):
            return None
        parts = key[len(head) :].split("/")
        if len(parts) != 2 or not NAME.fullmatch(parts[0]) or parts[1] not in OBSERVER_PARTS:
            return None
        return ObserverKey(parts[0], parts[1])

    def kind(self, key: str) -> str:
        """The kind of the liveliness token `key` (`proc`, `reg`, `claim`, `stopped`, or
        what a later version may add); `""` if `key` is not a token of this system."""
        head = f"{self.prefix}/live/"
        return key[len(head) :].split("/", 1)[0] if key.startswith(head) else ""

    def parse_proc(self, key: str) -> str | None:
        """The Zenoh id in a process token, or `None` (see `proc_key`)."""
        return proc_key(key, self.prefix)

    def parse_server(self, key: str) -> ServerKey | None:
        """What a registrar's token says, or `None` (see `server_key`)."""
        return server_key(key, self.prefix)

    def parse_host(self, key: str) -> HostKey | None:
        """What a host's token says, or `None` (see `host_key`)."""
        return host_key(key, self.prefix)

    def parse_claim(self, key: str) -> NameAt | None:
        """What a claim says, or `None` (see `claim_key`)."""
        return claim_key(key, self.prefix)

    def parse_stopped(self, key: str) -> NameAt | None:
        """What a "stopped" mark says, or `None` (see `stopped_key`)."""
        return stopped_key(key, self.prefix)


def _live_parts(key: str, prefix: str, kind: str, *counts: int) -> list[str] | None:
    """The segments after `<prefix>/live/<kind>/` of `key` if there are as many as one
    of `counts`, or `None`."""
    head = f"{prefix}/live/{kind}/"
    if not key.startswith(head):
        return None
    parts = key[len(head) :].split("/")
    return parts if len(parts) in counts else None


def _zid(text: str) -> bool:
    return _ZID.fullmatch(text) is not None


def proc_key(key: str, prefix: str) -> str | None:
    """The Zenoh id in a process token `<prefix>/live/proc/<zid>`, or `None` if malformed."""
    parts = _live_parts(key, prefix, "proc", 1)
    return parts[0] if parts is not None and _zid(parts[0]) else None


def _number(text: str, digits: int) -> bool:
    """Whether `text` is a decimal number of at most `digits` ASCII digits, written as
    `str(int)` writes it (no leading zero: a key parsed is the key built)."""
    return (
        text.isascii()
        and text.isdigit()
        and len(text) <= digits
        and (text == "0" or not text.startswith("0"))
    )


def server_key(key: str, prefix: str) -> ServerKey | None:
    """What a registrar's token
    `<prefix>/live/reg/<name>/<zid>/<sup>/<limit>/<stamp>[/<side>/<members>]` says (one
    without its side: 0, unknown), or `None` if it is malformed (a name that is not one,
    an id that is not hex, a limit that is not a positive integer, a stamp that is not
    one of 64 bits, a side or a count of members that is not a small number)."""
    parts = _live_parts(key, prefix, "reg", 5, 7)
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


def host_key(key: str, prefix: str) -> HostKey | None:
    """What a host's token `<prefix>/live/host/<zid>/<most>` says, or `None` if it is
    malformed."""
    parts = _live_parts(key, prefix, "host", 2)
    if parts is None or not _zid(parts[0]) or not _number(parts[1], _COUNT_DIGITS):
        return None
    return HostKey(parts[0], int(parts[1]))


def _name_at(key: str, prefix: str, kind: str) -> NameAt | None:
    parts = _live_parts(key, prefix, kind, 2)
    if parts is None or not NAME.fullmatch(parts[0]) or not _zid(parts[1]):
        return None
    return NameAt(parts[0], parts[1])


def claim_key(key: str, prefix: str) -> NameAt | None:
    """What a claim `<prefix>/live/claim/<name>/<zid>` says, or `None` if malformed."""
    return _name_at(key, prefix, "claim")


def stopped_key(key: str, prefix: str) -> NameAt | None:
    """What a "stopped" mark `<prefix>/live/stopped/<name>/<zid>` says, or `None` if
    malformed."""
    return _name_at(key, prefix, "stopped")
