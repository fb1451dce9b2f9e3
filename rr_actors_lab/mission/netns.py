"""Two hosts on one Linux machine for `rr-actors demo --hosts 2`: namespaces and a veth.

    rr-actors demo (root namespace)
      ── ip netns add ──► rrdemo-<pid>-station                rrdemo-<pid>-robot
      ── ip link add ───► rr0 10.66.<n>.1/24  <──── veth ────► rr0 10.66.<n>.2/24
    F6, the WiFi cut ───► ip link set rr0 down (both ends): packets vanish, no FIN is sent;
                          ip link set rr0 up: Zenoh dials again by itself

It shells out to iproute2's `ip` (root). Namespace names carry the demo's pid, so the
next demo deletes those a killed one left (`sweep_stale`), SIGKILLing what is inside.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess

__all__ = ["INTERFACE", "PREFIX", "TwoHosts", "sweep_stale", "unavailable"]

PREFIX = "rrdemo"
"""Namespace names are `rrdemo-<pid>-station` and `rrdemo-<pid>-robot`."""

INTERFACE = "rr0"
"""The veth end's name inside each namespace."""


def unavailable() -> str | None:
    """Why two hosts cannot be made here (one line, with what to run instead), or `None`."""
    if os.geteuid() != 0:
        return (
            "--hosts 2 needs root (it makes two network namespaces): run "
            "`sudo rr-actors demo --hosts 2`, or `rr-actors demo` for the mission on one host"
        )
    if shutil.which("ip") is None:
        return (
            "--hosts 2 needs iproute2's `ip` (apt-get install -y iproute2), or run "
            "`rr-actors demo` for the mission on one host"
        )
    return None


def _ip(*args: str) -> None:
    done = subprocess.run(  # noqa: S603 - iproute2's ip with our own arguments, no shell
        ["ip", *args],  # noqa: S607
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        raise OSError(f"`ip {' '.join(args)}` failed: {done.stderr.strip()}")


def _namespaces() -> list[str]:
    done = subprocess.run(
        ["ip", "-json", "netns", "list"],  # noqa: S607
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0 or not done.stdout.strip():
        return []
    return [entry["name"] for entry in json.loads(done.stdout)]


def pids_in(namespace: str) -> list[int]:
    """Every process in `namespace` (`ip netns pids`)."""
    done = subprocess.run(  # noqa: S603 - as in _ip
        ["ip", "netns", "pids", namespace],  # noqa: S607
        capture_output=True,
        text=True,
        check=False,
    )
    return [int(p) for p in done.stdout.split() if p.isdigit()]


def _delete(namespace: str) -> None:
    """SIGKILL what is left in `namespace`, then delete it."""
    for pid in pids_in(namespace):
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    with contextlib.suppress(OSError):
        _ip("netns", "del", namespace)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def sweep_stale() -> list[str]:
    """Delete the namespaces of demos whose process is gone; return their names."""
    swept = []
    for name in _namespaces():
        parts = name.split("-")
        ours = len(parts) == 3 and parts[0] == PREFIX and parts[1].isdigit()
        if ours and not _alive(int(parts[1])):
            _delete(name)
            swept.append(name)
    return swept


class TwoHosts:
    """The station's and the robot's network namespaces, joined by a veth pair (`make()` creates
    them; the mission's process takes them by name to cut and heal the link).

    Args:
        station: the station's namespace.
        robot: the robot's namespace.
        station_address: the station's IPv4 address on the veth.
        robot_address: the robot's.
    """

    def __init__(self, station: str, robot: str, station_address: str, robot_address: str) -> None:
        self.station = station
        self.robot = robot
        self.station_address = station_address
        self.robot_address = robot_address

    @classmethod
    def make(cls) -> TwoHosts:
        """Create both namespaces and the veth between them (deleting stale ones first).

        Raises:
            OSError: an `ip` command failed (its message names it); what was made is
                deleted again.
        """
        sweep_stale()
        pid = os.getpid()
        subnet = pid % 250 + 1
        hosts = cls(
            f"{PREFIX}-{pid}-station",
            f"{PREFIX}-{pid}-robot",
            f"10.66.{subnet}.1",
            f"10.66.{subnet}.2",
        )
        try:
            for namespace in (hosts.station, hosts.robot):
                _ip("netns", "add", namespace)
                _ip("-n", namespace, "link", "set", "lo", "up")
            _ip(
                "-n", hosts.station, "link", "add", INTERFACE, "type", "veth",
                "peer", "name", INTERFACE, "netns", hosts.robot,
            )  # fmt: skip
            for namespace, address in (
                (hosts.station, hosts.station_address),
                (hosts.robot, hosts.robot_address),
            ):
                _ip("-n", namespace, "addr", "add", f"{address}/24", "dev", INTERFACE)
                _ip("-n", namespace, "link", "set", INTERFACE, "up")
        except BaseException:
            hosts.close()
            raise
        return hosts

    def to_arg(self) -> str:
        """The namespaces and addresses as one command-line value (`from_arg` reads it)."""
        return ",".join((self.station, self.robot, self.station_address, self.robot_address))

    @classmethod
    def from_arg(cls, value: str) -> TwoHosts:
        """The hosts `to_arg` wrote."""
        station, robot, station_address, robot_address = value.split(",")
        return cls(station, robot, station_address, robot_address)

    def exec_in(self, namespace: str) -> list[str]:
        """The command prefix that runs a program inside `namespace`."""
        return ["ip", "netns", "exec", namespace]

    def cut(self) -> None:
        """Take the link down at both ends (a WiFi that drops out: nothing is sent)."""
        for namespace in (self.station, self.robot):
            _ip("-n", namespace, "link", "set", INTERFACE, "down")

    def heal(self) -> None:
        """Bring the link up again at both ends."""
        for namespace in (self.station, self.robot):
            _ip("-n", namespace, "link", "set", INTERFACE, "up")

    def close(self) -> None:
        """SIGKILL every process left in either namespace and delete both (the veth goes
        with them). Safe to call twice."""
        for namespace in (self.robot, self.station):
            if namespace in _namespaces():
                _delete(namespace)
