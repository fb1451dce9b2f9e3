"""A Python program run in a child process to its end, as a command line runs it."""

from __future__ import annotations

import subprocess
import sys
from typing import Any


def python(*argv: str, timeout: float, **options: Any) -> subprocess.CompletedProcess[str]:
    """`python *argv` (this interpreter) run to its end within `timeout` seconds: its exit
    code and its output and errors as text; a non-zero exit does not raise. `options` go
    to `subprocess.run` (`env`, `cwd`, `input`)."""
    return subprocess.run(
        [sys.executable, *argv],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
        **options,
    )
