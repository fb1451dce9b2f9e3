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

import argparse
import os
import statistics
import subprocess
import sys
from pathlib import Path

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
    return f"{statistics.median(values):.3f}{unit} ({min(values):.3f}-{max(values):.3f}{unit})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=21, help="rounds of the three runs")
    args = parser.parse_args()
    times: dict[str, list[float]] = {name: [] for name in COMMANDS}
    for _ in range(args.rounds):
        for name, code in COMMANDS.items():
            times[name].append(cpu_seconds(code))
    bare, pykka, ours = times.values()
    whole = [r / p for r, p in zip(ours, pykka, strict=True)]
    above = [(r - b) / (p - b) for r, p, b in zip(ours, pykka, bare, strict=True) if p > b]
    print(f"rounds: {args.rounds}; load average: {os.getloadavg()[0]:.1f}")
    print("| what | CPU s, median (min-max) |")
    print("|---|---:|")
    for name, values in times.items():
        print(f"| `{name}` | {spread(values)} |")
    print(f"| `import rr_actors` / `import pykka`, whole process | {spread(whole, 'x')} |")
    if above:
        print(f"| the same above `python -c pass` | {spread(above, 'x')} |")


if __name__ == "__main__":
    main()
