"""A gate on a TCP listening socket of this process (Linux): what `zenoh/ops/gate.py` works with.

Zenoh's listening socket lives in our process, so we act on a duplicate of its descriptor
(found by matching its inode from `/proc/net/tcp` with the links of `/proc/self/fd`; it
shares Zenoh's file description, and nothing here accepts, reads or closes it for Zenoh):

- `shorten_backlog(n)`: `listen(fd, n)` again changes only its accept queue's length;
- `drop_from(addresses)` / `admit_only(addresses)`: a classic BPF filter
  (`SO_ATTACH_FILTER`) that drops those sources' packets, or all others'. The kernel runs
  it before a SYN is answered, so a dropped source costs the listener nothing; a
  connection accepted later keeps a copy of the filter attached then;
- `peers()`: the remote addresses of this port's connections past the TCP handshake, from
  `/proc/net/tcp{,6}`; never `SYN_RECV` ones, whose source address anyone can forge.
"""

from __future__ import annotations

import collections
import contextlib
import ctypes
import ipaddress
import os
import socket
import struct
from collections.abc import Collection, Iterable
from pathlib import Path

from rr_actors._platform.base import GATE_SOURCES

_SO_ATTACH_FILTER = 26
_SO_DETACH_FILTER = 27
_LISTEN = "0A"
# the states of a connection past the TCP handshake (include/net/tcp_states.h): ESTABLISHED,
# FIN_WAIT1, FIN_WAIT2, CLOSE_WAIT, LAST_ACK, CLOSING; not SYN_RECV (03), TIME_WAIT (06)
_HANDSHAKEN = frozenset({"01", "04", "05", "08", "09", "0B"})

# classic BPF (linux/filter.h, linux/bpf_common.h)
_LD_B_ABS, _LD_W_ABS = 0x30, 0x20
_ALU_AND_K, _JEQ_K, _RET_K = 0x54, 0x15, 0x06
_NET = -0x100000  # SKF_NET_OFF: offsets from the network (IP) header
_ACCEPT, _DROP = 0xFFFFFFFF, 0
MAX_SOURCES = GATE_SOURCES  # (9 instructions each for IPv6: under BPF_MAXINSNS, 4096)


def _insn(code: int, k: int, jt: int = 0, jf: int = 0) -> bytes:
    return struct.pack("HBBI", code, jt, jf, k & 0xFFFFFFFF)


def _program(sources: Collection[str], *, listed: int, other: int) -> bytes:
    """A socket filter: verdict `listed` for packets from `sources`, `other` for the rest."""
    v4 = [ipaddress.ip_address(s) for s in sources if ipaddress.ip_address(s).version == 4]
    v6 = [ipaddress.ip_address(s) for s in sources if ipaddress.ip_address(s).version == 6]
    tail4, tail6 = [], []
    for address in v4:  # A holds the source; equal: the next instruction's verdict
        tail4 += [_insn(_JEQ_K, int(address), 0, 1), _insn(_RET_K, listed)]
    for address in v6:  # four words, each equal or on to the next address
        words = struct.unpack("!4I", address.packed)
        for n, word in enumerate(words):
            skip = 2 * (3 - n) + 1  # past the rest of this address and its verdict
            tail6 += [_insn(_LD_W_ABS, _NET + 8 + 4 * n), _insn(_JEQ_K, word, 0, skip)]
        tail6.append(_insn(_RET_K, listed))
    v6_part = [*tail6, _insn(_RET_K, other)]
    v4_part = [_insn(_LD_W_ABS, _NET + 12), *tail4, _insn(_RET_K, other)]
    head = [
        _insn(_LD_B_ABS, _NET),  # the IP header's first byte: its version in the high nibble
        _insn(_ALU_AND_K, 0xF0),
        # IPv4: on to the v4 part (after the next instruction); else the v6 part
        _insn(_JEQ_K, 0x40, 1, 0),
        _insn(0x05, len(v4_part)),  # BPF_JMP|BPF_JA: over the v4 part
    ]
    return b"".join([*head, *v4_part, *v6_part])


def _proc_address(hexa: str) -> str:
    """An address of `/proc/net/tcp{,6}` (host-order 32-bit words in hex), as text."""
    raw = bytes.fromhex(hexa)
    words = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))
    address = ipaddress.ip_address(words)
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        return str(address.ipv4_mapped)
    return str(address)


def _sockets() -> list[tuple[str, int, str, str, int]]:
    """(local address, local port, remote address, state, inode) of each TCP socket here."""
    found = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with contextlib.suppress(OSError), Path(table).open() as lines:
            next(lines, None)
            for line in lines:
                fields = line.split()
                local, remote, state, inode = fields[1], fields[2], fields[3], int(fields[9])
                here, port = local.split(":")
                found.append(
                    (_proc_address(here), int(port, 16), remote.split(":")[0], state, inode)
                )
    return found


def handshaken(
    sockets: Iterable[tuple[str, int, str, str, int]], address: str, port: int
) -> collections.Counter[str]:
    """Of `sockets`, the connections to `address`:`port` past the handshake, per remote address."""
    anywhere = ipaddress.ip_address(address).is_unspecified  # (0.0.0.0, ::)
    counts: collections.Counter[str] = collections.Counter()
    for local, local_port, remote, state, _ in sockets:
        if local_port == port and state in _HANDSHAKEN and (anywhere or local == address):
            counts[_proc_address(remote)] += 1
    return counts


def find_listener(host: str, port: int) -> socket.socket | None:
    """A duplicate of this process's listening socket bound to `host`:`port`, or `None`."""
    try:
        wanted = str(ipaddress.ip_address(host))
    except ValueError:
        return None
    inodes = {
        inode
        for local, local_port, _, state, inode in _sockets()
        if state == _LISTEN and local_port == port and local == wanted
    }
    if not inodes:
        return None
    with contextlib.suppress(OSError):
        for name in os.listdir("/proc/self/fd"):
            try:
                target = os.readlink(f"/proc/self/fd/{name}")
            except OSError:
                continue  # closed meanwhile
            if target.startswith("socket:[") and int(target[8:-1]) in inodes:
                return socket.socket(fileno=os.dup(int(name)))
    return None


class LinuxListenerGate:
    """A gate on one listening socket of this process, through `sock`, a duplicate
    (`find_listener`) that `close` closes."""

    def __init__(self, sock: socket.socket) -> None:
        self._sock = sock
        self.address: str = str(sock.getsockname()[0])
        self.port: int = int(sock.getsockname()[1])
        self._filter: ctypes.Array[ctypes.c_char] | None = None

    def shorten_backlog(self, backlog: int) -> None:
        self._sock.listen(backlog)

    def drop_from(self, sources: Collection[str]) -> None:
        """Drop every packet from `sources` (at most `MAX_SOURCES`; none: nothing), replacing the
        filter."""
        if not sources:
            with contextlib.suppress(OSError):
                self._sock.setsockopt(socket.SOL_SOCKET, _SO_DETACH_FILTER, 0)
            return
        self._attach(_program(self._checked(sources), listed=_DROP, other=_ACCEPT))

    def admit_only(self, sources: Collection[str]) -> None:
        """Drop every packet from any address but `sources` (at most `MAX_SOURCES`), replacing
        the filter."""
        self._attach(_program(self._checked(sources), listed=_ACCEPT, other=_DROP))

    @staticmethod
    def _checked(sources: Collection[str]) -> Collection[str]:
        if len(sources) > MAX_SOURCES:
            raise ValueError(f"at most {MAX_SOURCES} sources, not {len(sources)}")
        return sources

    def _attach(self, program: bytes) -> None:
        buffer = ctypes.create_string_buffer(program, len(program))
        fprog = struct.pack("HL", len(program) // 8, ctypes.addressof(buffer))
        self._sock.setsockopt(socket.SOL_SOCKET, _SO_ATTACH_FILTER, fprog)
        self._filter = buffer  # (the kernel copied it; kept only for a look in a debugger)

    def peers(self) -> collections.Counter[str]:
        """Connections past the TCP handshake to this socket's port, per remote address."""
        return handshaken(_sockets(), self.address, self.port)

    def close(self) -> None:
        """Close the duplicate (Zenoh's socket stays open, its filter attached)."""
        self._sock.close()
