"""`import rr_actors` against `import pykka`, measured in the same run (issue 54 part 7).

    python benchmarks/bench_import.py --rounds 21

Each round starts three fresh interpreters one after the other, from the checkout (so its
`rr_actors` is the one imported): `python -c pass`, `python -c "import pykka"` and
`python -c "import rr_actors"`, and takes each one's CPU seconds (user + system, from
`os.wait4`: the kernel's own accounting, which a busy machine disturbs less than the wall
clock). Printed, as medians (min-max) over the rounds:

- each command's CPU seconds;
- `import rr_actors` over `import pykka`, whole process, per round;
- the same above the bare interpreter (`python -c pass` subtracted from both in the round):
  the imports' own cost, the stricter of the two ratios.

The goal (issue 54): `import rr_actors` within 2x `import pykka`. The package imports
its errors, configuration and status types; the runtime waits for the first use of one of
its names (PEP 562), which `tests/test_init.py` holds without timing anything.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import _harness

ROOT = Path(__file__).resolve().parent.parent
COMMANDS = {"python -c pass": "pass", "import pykka": "import pykka"}
COMMANDS["import rr_actors"] = "import rr_actors"


def cpu_seconds(code: str) -> float:
    """User + system CPU seconds of a fresh `python -c code`, run in the checkout."""
    process = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT)
    _, status, usage = os.wait4(process.pid, 0)
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"python -c {code!r} failed")
    return usage.ru_utime + usage.ru_stime


def spread(values: list[float], unit: str = "") -> str:
    """`median (min-max)` of `values`."""
    return f"{_harness.median(values):.3f}{unit} ({min(values):.3f}-{max(values):.3f}{unit})"


def main(argv: list[str] | None = None) -> None:
    args = _harness.parse(_harness.options(__doc__, rounds=21), argv)
    times = _harness.alternate(
        {name: (lambda code=code: cpu_seconds(code)) for name, code in COMMANDS.items()},
        args.rounds,
        warm_up=False,
    )
    bare, pykka, ours = times.values()
    whole = [r / p for r, p in zip(ours, pykka, strict=True)]
    above = [(r - b) / (p - b) for r, p, b in zip(ours, pykka, bare, strict=True) if p > b]
    print(_harness.header(f"rounds: {args.rounds}"))
    rows = [(f"`{name}`", spread(values)) for name, values in times.items()]
    rows.append(("`import rr_actors` / `import pykka`, whole process", spread(whole, "x")))
    if above:
        rows.append(("the same above `python -c pass`", spread(above, "x")))
    print(_harness.table(["what", "CPU s, median (min-max)"], rows))


if __name__ == "__main__":
    main()
