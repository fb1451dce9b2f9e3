"""The platform tricks and their plain fallback (`rr_actors._platform`): the one chosen.

`PLATFORM` is `linux` on Linux and `portable` elsewhere or with
`RR_ACTORS_PLATFORM=portable`. Every test that uses manager processes must pass on both:
`tests/core/test_portable.py` runs those modules (this one too) again, in a
subprocess on the portable platform, as part of the normal run. Tests of what only a
trick does are marked `linux_trick` (see `supervising.py`) and skipped there.
"""

from __future__ import annotations

import os
import sys

from rr_actors._platform import PLATFORM

_FORCED = os.environ.get("RR_ACTORS_PLATFORM") == "portable"


def test_the_platform_is_the_one_the_environment_asks_for() -> None:
    expected = "portable" if _FORCED or not sys.platform.startswith("linux") else "linux"

    assert expected == PLATFORM.name
