"""What tracing (`rr-actors demo --trace`) costs the thesis mission, spans exported to a file.

Each row runs `rr-actors demo --fast --quiet` (all five faults unless `--faults`) once a
round, the rows in turn within each round (interleaved: other processes' noise spreads
evenly); the table shows each row's medians over `--rounds` rounds and their ratios to
`untraced`, measured in the same run (the issue's goal for `traced`: at most 1.03x):

    untraced       no `--trace` (no subscriber, no span): the floor
    not sampled    `--trace`, `OTEL_TRACES_SAMPLER=always_off`: the subscriber of the
                   tree takes every event and builds every side, the SDK records nothing
    traced         `--trace`, sampling 1.0 (`always_on`), `OTEL_TRACES_EXPORTER=console`:
                   every span written to a file (the command's output)

Figures: `mission s` is the report's mission time (the drive from start to goal, its
fault stops included: the mission's throughput, metres per second, is the distance over
it); `wall s` is the whole command (managers started, the steps, everything unloaded and
stopped, the spans exported).

    taskset -c 0 python benchmarks/bench_otel_mission.py [--rounds 5] [--faults F1,F4]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROWS = {
    "untraced": ([], {}),
    "not sampled": (["--trace"], {"OTEL_TRACES_SAMPLER": "always_off"}),
    "traced": (["--trace"], {"OTEL_TRACES_SAMPLER": "always_on"}),
}


def run(row: str, folder: Path, extra: list[str]) -> tuple[float, float, int]:
    """(mission time, wall time, spans written) of one `demo` run in `row`'s setting."""
    flags, env = ROWS[row]
    out = folder / row.replace(" ", "-")
    spans = folder / "spans.txt"
    command = [sys.executable, "-m", "rr_actors_lab", "demo", "--fast", "--quiet", *extra, *flags]
    began = time.perf_counter()
    with spans.open("w", encoding="utf-8") as written:
        subprocess.run(
            [*command, "--out", str(out)],
            stdout=written,
            stderr=subprocess.DEVNULL,
            env={**os.environ, "OTEL_TRACES_EXPORTER": "console", **env},
            check=True,
            timeout=600,
        )
    wall = time.perf_counter() - began
    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    count = spans.read_text(encoding="utf-8").count('"kind": "SpanKind.')  # (one a span)
    return float(report["mission_time_s"]), wall, count


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--faults", default="", help="--faults of demo (default: all five)")
    parser.add_argument("--distance", default="", help="--distance of demo (default: fast's)")
    args = parser.parse_args(argv)
    extra = ["--faults", args.faults] if args.faults else []
    extra += ["--distance", args.distance] if args.distance else []

    mission: dict[str, list[float]] = {row: [] for row in ROWS}
    wall: dict[str, list[float]] = {row: [] for row in ROWS}
    spans: dict[str, int] = {}
    with tempfile.TemporaryDirectory() as folder:
        for _ in range(args.rounds):
            for row in ROWS:
                took, whole, spans[row] = run(row, Path(folder), extra)
                mission[row].append(took)
                wall[row].append(whole)

    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else "?"
    print(
        f"python {platform.python_version()} on {platform.machine()}, CPUs {cpus}, "
        f"load {os.getloadavg()[0]:.2f}; {args.rounds} rounds of `demo --fast "
        f"{' '.join(extra)}`"
    )
    floor_mission = statistics.median(mission["untraced"])
    floor_wall = statistics.median(wall["untraced"])
    print(f"{'row':<12} {'mission s':>10} {'ratio':>7} {'wall s':>8} {'ratio':>7} {'spans':>6}")
    for row in ROWS:
        took, whole = statistics.median(mission[row]), statistics.median(wall[row])
        print(
            f"{row:<12} {took:>10.3f} {took / floor_mission:>6.3f}x {whole:>8.2f}"
            f" {whole / floor_wall:>6.3f}x {spans[row]:>6}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
