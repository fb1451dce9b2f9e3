"""What the mission does: its faults, its configuration, its error, and where it can run."""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import signal
import sys
from typing import Any, Literal

import rr_actors as rr

__all__ = [
    "DEFAULT_FAULT_AT",
    "FAULTS",
    "FAULT_WHAT",
    "HOST_FAULTS",
    "HOST_OF",
    "MANAGERS",
    "MANAGER_OF",
    "MissionConfig",
    "MissionError",
    "MissionInterruptedError",
    "unsupported_platform",
]

FAULTS = ("F1", "F2", "F3", "F4", "F5")
"""The thesis's five faults, in the order the mission meets them."""

HOST_FAULTS = ("F6",)
"""The faults of the mission across two hosts (`hosts=2`) only: F6, the WiFi cut."""

FAULT_WHAT = {
    "F1": "LiDAR 1 disconnected",
    "F2": "motor driver failed",
    "F3": "external resource manager killed",
    "F4": "component manager killed",
    "F5": "robot manager killed",
    "F6": "WiFi cut between the robot and the station",
}
"""What each fault is, in words (the report's `what`)."""

MANAGERS = ("erm", "cm", "rm")
"""The mission's managers, in start order (each its own process under one supervisor)."""

MANAGER_OF = {"F3": "erm", "F4": "cm", "F5": "rm"}
"""Which manager each software fault kills."""

HOST_OF = {
    "erm": "robot",
    "rm": "robot",
    "cm": "station",
    "mission": "station",
    "F1": "robot",
    "F2": "robot",
    "F3": "robot",
    "F4": "station",
    "F5": "robot",
    "F6": "both",
}
"""Where each manager runs, and where each fault strikes, across two hosts (thesis 6.1: the
robot's computer runs the external resource manager and the robot manager with their
programs; the operator station runs the mission and the component manager it asks through)."""

DEFAULT_FAULT_AT = {"F1": 0.15, "F2": 0.35, "F3": 0.5, "F4": 0.65, "F5": 0.8, "F6": 0.85}
"""Where each fault is injected, as a fraction of the path."""


class MissionError(rr.RrError):
    """The mission could not be completed (a fault was not recovered, or it timed out)."""


class MissionInterruptedError(KeyboardInterrupt):
    """Ctrl-C (SIGINT) ended the mission; everything was unloaded and stopped all the same.

    A `KeyboardInterrupt`, not an `RrError` (as `ExperimentInterruptedError`): an `except
    Exception` around `run_mission` must not swallow it. No report was written.

    Attributes:
        at_s: the mission time (seconds, `--step`'s pauses left out) of the Ctrl-C.
        failed_unloads: how many of the mission's unloads failed while it cleaned up.
        leaked: pids of the mission's programs still alive after the managers stopped
            (killed).
    """

    def __init__(self, at_s: float, failed_unloads: int, leaked: list[int]) -> None:
        super().__init__(f"interrupted at {at_s:.1f} s")
        self.at_s = at_s
        self.failed_unloads = failed_unloads
        self.leaked = leaked


def unsupported_platform() -> str | None:
    """Why the mission cannot run on this platform, or `None` if it can.

    The mission watches and signals its programs through pidfds (`os.pidfd_open`,
    `signal.pidfd_send_signal`: Linux 5.3 or later) and reads their creation times from
    `/proc`, so it needs Linux. The rest of rr_actors does not.
    """
    if hasattr(os, "pidfd_open") and hasattr(signal, "pidfd_send_signal"):
        return None
    return (
        f"the mission needs Linux: it watches and signals its programs through pidfds "
        f"(os.pidfd_open), which this platform ({sys.platform}) does not have"
    )


@dataclasses.dataclass(frozen=True)
class MissionConfig:
    """What the mission does.

    Attributes:
        distance_m: length of the path, in metres.
        speed: driving speed, in metres per second.
        faults: which faults to inject (`"F1"` ... `"F5"`; `"F6"` with `hosts=2`).
        fault_at: where to inject each, as a fraction of the path (0..1).
        seed: seeds the LiDAR noise and a small jitter of the injection points.
        isolation: `"process"` (each manager an OS process) or `"thread"`.
        lidar_rate: LiDAR scans per second.
        driver_rate: odometry updates per second.
        nav_rate: navigation updates per second.
        scan_timeout: seconds after which navigation treats the last scan as stale.
        cmd_timeout: seconds after which the driver's watchdog treats a command as stale.
        recovery_timeout: seconds a fault may take to be recovered before the mission fails.
        call_timeout: timeout of the mission's calls, in seconds.
        hosts: 1 (one supervisor) or 2 (the robot's and the station's, in two network
            namespaces: `rr-actors demo --hosts 2`, as root).
        cut_s: F6: seconds the link between the hosts stays down (longer than `lease`).
        lease: with `hosts=2`: seconds after which a silent host counts as gone.

    Raises:
        ConfigError: a field is invalid; the message names it.
    """

    distance_m: float = 16.0
    speed: float = 0.5
    faults: tuple[str, ...] = FAULTS
    fault_at: dict[str, float] = dataclasses.field(default_factory=lambda: dict(DEFAULT_FAULT_AT))
    seed: int = 0
    isolation: Literal["process", "thread"] = "process"
    lidar_rate: float = 20.0
    driver_rate: float = 50.0
    nav_rate: float = 20.0
    scan_timeout: float = 0.5
    cmd_timeout: float = 0.5
    recovery_timeout: float = 20.0
    call_timeout: float = 15.0
    hosts: int = 1
    cut_s: float = 5.0
    lease: float = 3.0

    def __post_init__(self) -> None:
        for field in ("distance_m", "speed", "lidar_rate", "driver_rate", "nav_rate"):
            value = getattr(self, field)
            if (
                isinstance(value, bool)
                or not isinstance(value, int | float)
                or not (0 < value < math.inf)  # (nan too: it never drives to the goal)
            ):
                raise rr.ConfigError(f"{field} must be a positive number, got {value!r}")
        if self.hosts not in (1, 2) or isinstance(self.hosts, bool):
            raise rr.ConfigError(f"hosts must be 1 or 2, got {self.hosts!r}")
        for field in ("cut_s", "lease"):
            value = getattr(self, field)
            if isinstance(value, bool) or not isinstance(value, int | float) or value <= 0:
                raise rr.ConfigError(f"{field} must be a positive number, got {value!r}")
        if self.cut_s <= self.lease:
            raise rr.ConfigError(
                f"cut_s must be longer than lease ({self.lease:g} s), got {self.cut_s!r}"
            )
        known = FAULTS + HOST_FAULTS
        for field, named in (("faults", list(self.faults)), ("fault_at", list(self.fault_at))):
            if unknown := [f for f in named if f not in known]:
                close = difflib.get_close_matches(str(unknown[0]).upper(), known, n=1)
                hint = f"; did you mean {close[0]!r}?" if close else ""
                listed = list(known)
                raise rr.ConfigError(f"{field}: unknown fault(s) {unknown}{hint} (known: {listed})")
        if self.hosts == 1 and any(f in HOST_FAULTS for f in self.faults):
            raise rr.ConfigError("faults: F6 (the WiFi cut) needs hosts=2 (--hosts 2)")
        object.__setattr__(self, "faults", tuple(f for f in known if f in self.faults))
        for fault in self.faults:
            point = self.fault_at.get(fault)
            if point is None or not 0.0 < point < 1.0:
                raise rr.ConfigError(
                    f"fault_at[{fault!r}] must be a fraction of the path in (0, 1), got {point!r}"
                )
        if self.isolation not in ("process", "thread"):
            raise rr.ConfigError(f"isolation must be 'process' or 'thread', got {self.isolation!r}")

    @classmethod
    def fast(cls, **changes: Any) -> MissionConfig:
        """A mission of a few seconds (for CI): a short path at high speed.

        Args:
            **changes: fields to set on top of the fast defaults.
        """
        base: dict[str, Any] = {
            "distance_m": 6.0,
            "speed": 2.0,
            "lidar_rate": 50.0,
            "nav_rate": 50.0,
            "fault_at": {"F1": 0.1, "F2": 0.25, "F3": 0.4, "F4": 0.55, "F5": 0.7, "F6": 0.8},
        }
        base.update(changes)
        return cls(**base)

    @classmethod
    def fast_two_hosts(cls, **changes: Any) -> MissionConfig:
        """`fast` across two hosts: a longer path, so that the robot still drives for
        longer than the `lease` after F6 (and its stop shows)."""
        base: dict[str, Any] = {
            "hosts": 2,
            "faults": FAULTS + HOST_FAULTS,
            "distance_m": 16.0,
            "fault_at": {"F1": 0.05, "F2": 0.12, "F3": 0.2, "F4": 0.27, "F5": 0.34, "F6": 0.45},
        }
        base.update(changes)
        return cls.fast(**base)

    @property
    def nominal_time_s(self) -> float:
        """How long the drive takes without faults: distance over speed, in seconds."""
        return self.distance_m / self.speed
