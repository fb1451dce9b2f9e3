"""OS- and CPython-specific tricks, chosen once, each with a plain fallback.

Everything rr_actors does that only works on Linux, with glibc, or by reaching into
CPython's private machinery lives in `linux`; `base.PortablePlatform` does the same jobs
plainly (or not at all, where the job is only an optimisation). `PLATFORM` is chosen once,
at import: `linux` on Linux, the portable one elsewhere or when the environment variable
`RR_ACTORS_PLATFORM=portable` is set (the test suite runs under both).

`fork` is where every layer says what a child forked from this process must let go of.
"""

from __future__ import annotations

import os
import sys

from rr_actors._platform import fork, linux
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

fork.after_fork_in_child("the forkserver", PLATFORM.forget_in_child)
