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

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _harness

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
    parser = _harness.options(__doc__, rounds=5)
    parser.add_argument("--faults", default="", help="--faults of demo (default: all five)")
    parser.add_argument("--distance", default="", help="--distance of demo (default: fast's)")
    args = _harness.parse(parser, argv)
    extra = ["--faults", args.faults] if args.faults else []
    extra += ["--distance", args.distance] if args.distance else []

    runs: dict[str, list[tuple[float, float, int]]] = {row: [] for row in ROWS}
    with tempfile.TemporaryDirectory() as folder:

        def once(row: str) -> float:
            runs[row].append(run(row, Path(folder), extra))
            return runs[row][-1][1]

        _harness.alternate(
            {row: (lambda row=row: once(row)) for row in ROWS}, args.rounds, warm_up=False
        )

    print(_harness.header(f"{args.rounds} rounds of `demo --fast {' '.join(extra)}`"))
    mission = {row: [r[0] for r in rs] for row, rs in runs.items()}
    wall = {row: [r[1] for r in rs] for row, rs in runs.items()}
    floor_mission = _harness.median(mission["untraced"])
    floor_wall = _harness.median(wall["untraced"])
    rows = []
    for row in ROWS:
        took, whole = _harness.median(mission[row]), _harness.median(wall[row])
        rows.append(
            (
                row,
                f"{took:.3f}",
                f"{took / floor_mission:.3f}x",
                f"{whole:.2f}",
                f"{whole / floor_wall:.3f}x",
                runs[row][-1][2],
            )
        )
    print(_harness.table(["row", "mission s", "ratio", "wall s", "ratio", "spans"], rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
