"""OS- and CPython-specific tricks, chosen once, each with a plain fallback.

The Linux, glibc and CPython-private tricks live in `linux`; `base.PortablePlatform` does the same
jobs plainly (or not at all, for an optimisation). `PLATFORM` is chosen once, at import: `linux` on
Linux, the portable one elsewhere or with `RR_ACTORS_PLATFORM=portable` (the test suite runs under
both). `forkserver` is where every layer says what a forked child lets go of.
"""

from __future__ import annotations

import os
import sys

from rr_actors._platform import forkserver, linux
from rr_actors._platform.base import (
    GATE_SOURCES,
    CpuSample,
    CpuWatch,
    ExitWatch,
    ListenerGate,
    NameWatch,
    Platform,
    PortablePlatform,
)

__all__ = [
    "GATE_SOURCES",
    "PLATFORM",
    "CpuSample",
    "CpuWatch",
    "ExitWatch",
    "ListenerGate",
    "NameWatch",
    "Platform",
]


def _choose() -> Platform:
    forced = os.environ.get("RR_ACTORS_PLATFORM", "")
    if forced == "portable" or not sys.platform.startswith("linux"):
        return PortablePlatform()
    return linux.LinuxPlatform()


PLATFORM: Platform = _choose()
"""The platform's tricks, chosen once for this process (its children choose again)."""

forkserver.after_fork_in_child("the forkserver", PLATFORM.forget_in_child)
