"""The hosts of a run: Linux network namespaces joined by a veth between every two (root).

    run process (root namespace, single-threaded at start)
      ├─ HostNetwork(["a", "b", "c"]) ─ ip netns add rrx-<pid>-<i>, one veth per pair
      │     a 10.91.<p>.1 <── veth rrv<j> / rrv<i> ──> b 10.91.<p>.2   (p: the pair's number)
      ├─ enter("a"): setns(2) into the first host's namespace (the run's own host: its
      │     router, clients and managers without `host`)
      ├─ set_link / set_links: `ip -n NS link set rrv<j> down|up` (a cut; a partition)
      └─ close(): ip netns del (also of runs whose process is gone: `sweep_stale`)

A veth per pair (not a bridge) makes a cut one link's business; names carry the run
process's pid, so parallel runs never clash and a killed run's are swept by the next.
"""

from __future__ import annotations

import contextlib
import ctypes
import itertools
import json
import os
import shutil
import subprocess
from pathlib import Path

__all__ = ["PREFIX", "HostNetwork", "cannot_make_hosts"]

PREFIX = "rrx"
"""Namespace names are `rrx-<run pid>-<host index>`."""

PORT = 7447
"""The Zenoh port every host's router listens on, on each of its addresses."""

_CLONE_NEWNET = 0x40000000


def cannot_make_hosts() -> str | None:
    """Why this process cannot make hosts (one line), or `None` if it can."""
    if not Path("/proc/self/ns/net").exists():
        return "a plan with [hosts] needs Linux network namespaces"
    if os.geteuid() != 0:
        return "a plan with [hosts] needs root (it makes network namespaces: `ip netns add`)"
    if shutil.which("ip") is None:
        return "a plan with [hosts] needs iproute2's `ip` (apt-get install -y iproute2)"
    return None


def _ip(*args: str) -> None:
    command = ["ip", *args]  # iproute2, with arguments the run made
    done = subprocess.run(command, capture_output=True, text=True, check=False)  # noqa: S603
    if done.returncode != 0:
        raise RuntimeError(f"`ip {' '.join(args)}` failed: {done.stderr.strip()}")


def sweep_stale() -> list[str]:
    """Delete the namespaces of runs whose process is gone; their names."""
    done = subprocess.run(
        ["ip", "-json", "netns", "list"],  # noqa: S607
        capture_output=True,
        text=True,
        check=False,
    )
    swept = []
    for entry in json.loads(done.stdout or "[]"):
        parts = entry["name"].split("-")
        ours = len(parts) == 3 and parts[0] == PREFIX and parts[1].isdigit()
        if ours and not Path(f"/proc/{parts[1]}").exists():
            with contextlib.suppress(RuntimeError):
                _ip("netns", "del", entry["name"])
                swept.append(entry["name"])
    return swept


class HostNetwork:
    """Namespaces for `names`, a veth between every two; deleted by `close`.

    Args:
        names: the hosts, the run's own first.

    Attributes:
        namespaces: each host's namespace name.
        addresses: each host's addresses (one per link), in the order of the other hosts.
        peers: for each host and each other host, the address it dials that host at.

    Raises:
        RuntimeError: an `ip` command failed (what was made is deleted again).
    """

    def __init__(self, names: tuple[str, ...]) -> None:
        sweep_stale()
        self.names = names
        stem = f"{PREFIX}-{os.getpid()}"
        self.namespaces = {name: f"{stem}-{i}" for i, name in enumerate(names)}
        self.addresses: dict[str, list[str]] = {name: [] for name in names}
        self.peers: dict[str, dict[str, str]] = {name: {} for name in names}
        self._made: list[str] = []
        try:
            for name in names:
                _ip("netns", "add", self.namespaces[name])
                self._made.append(self.namespaces[name])
                _ip("-n", self.namespaces[name], "link", "set", "lo", "up")
            for pair, (i, j) in enumerate(itertools.combinations(range(len(names)), 2)):
                self._link(pair, names[i], names[j], i, j)
        except BaseException:
            self.close()
            raise

    def _link(self, pair: int, one: str, other: str, i: int, j: int) -> None:
        ns_one, ns_other = self.namespaces[one], self.namespaces[other]
        _ip(
            *("-n", ns_one, "link", "add", f"rrv{j}", "type", "veth"),
            *("peer", "name", f"rrv{i}", "netns", ns_other),
        )
        for host, namespace, interface, address in (
            (one, ns_one, f"rrv{j}", f"10.91.{pair}.1"),
            (other, ns_other, f"rrv{i}", f"10.91.{pair}.2"),
        ):
            _ip("-n", namespace, "addr", "add", f"{address}/24", "dev", interface)
            _ip("-n", namespace, "link", "set", interface, "up")
            self.addresses[host].append(address)
        self.peers[one][other] = f"10.91.{pair}.2"
        self.peers[other][one] = f"10.91.{pair}.1"

    def interface(self, host: str, other: str) -> str:
        """The name of `host`'s end of its link to `other`."""
        return f"rrv{self.names.index(other)}"

    def set_link(self, one: str, other: str, *, up: bool) -> None:
        """Take the link between two hosts down (packets vanish, no FIN) or up again."""
        state = "up" if up else "down"
        _ip("-n", self.namespaces[one], "link", "set", self.interface(one, other), state)
        _ip("-n", self.namespaces[other], "link", "set", self.interface(other, one), state)

    def set_links(self, side: tuple[str, ...], *, up: bool) -> None:
        """Every link between `side` and the other hosts down (a partition) or up."""
        for one in side:
            for other in (n for n in self.names if n not in side):
                self.set_link(one, other, up=up)

    def enter(self, host: str) -> None:
        """Move the calling thread (at start: the whole process) into `host`'s namespace (`OSError`
        if `setns(2)` failed)."""
        libc = ctypes.CDLL(None, use_errno=True)
        fd = os.open(f"/run/netns/{self.namespaces[host]}", os.O_RDONLY)
        try:
            if libc.setns(fd, _CLONE_NEWNET) != 0:
                err = ctypes.get_errno()
                raise OSError(err, f"setns into {self.namespaces[host]}: {os.strerror(err)}")
        finally:
            os.close(fd)

    def inside(self, host: str) -> list[str]:
        """The command prefix that runs a program in `host`'s namespace."""
        return ["ip", "netns", "exec", self.namespaces[host]]

    def close(self) -> None:
        """Delete the namespaces (processes still in one keep it until they exit)."""
        while self._made:
            with contextlib.suppress(RuntimeError):
                _ip("netns", "del", self._made.pop())
