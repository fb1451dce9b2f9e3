"""Seeds on every core: `rr-actors experiment PLAN --simulate --seeds A-B --jobs N` for
N = 1 up to the cores available, each in the same run (issue 52, part 6).

Rows: jobs, wall seconds of the whole command (worker start-up included), seeds per
wall-minute, the speed-up over `--jobs 1` of this run, and whether its `seeds.jsonl` is
the serial one's (hash, verdict and counts of every seed; the CPU seconds aside). Then
what 10,000 seeds of the plan would take on 16 cores, from this run's CPU seconds per
seed, if each core ran as one core here and start-up were free (a bound, not a
measurement: this machine has 2 cores).

    python benchmarks/bench_jobs.py --plan killheavy --seeds 1-40

Run it on an otherwise idle machine: the speed-up is the figure, and a process beside
it takes a core from `--jobs 2` only (do not pin it with `taskset -c 0`: that would
give the workers one core).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def sweep(plan: str, seeds: str, jobs: int, out: Path) -> float:
    """Wall seconds of one sweep of `plan` over `seeds` with `jobs` workers."""
    env = {**os.environ, "PYTHONHASHSEED": "0"}
    command = [sys.executable, "-m", "rr_actors_lab", "experiment", plan, "--simulate"]
    command += ["--seeds", seeds, "--jobs", str(jobs), "--out", str(out), "--quiet"]
    started = time.perf_counter()
    subprocess.run(command, env=env, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - started


def lines(out: Path) -> list[dict[str, object]]:
    """The seeds' lines without their CPU seconds (the one field that is not the run's)."""
    text = (out / "seeds.jsonl").read_text().splitlines()
    return [{k: v for k, v in json.loads(line).items() if k != "cpu_s"} for line in text]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--plan", default="killheavy", help="a plan (default killheavy)")
    parser.add_argument("--seeds", default="1-40", help="A-B (default 1-40)")
    args = parser.parse_args()
    first, _, last = args.seeds.partition("-")
    count = int(last or first) - int(first) + 1
    cores = len(os.sched_getaffinity(0))
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-jobs-") as folder:
        serial: list[dict[str, object]] = []
        cpu = 0.0
        for jobs in range(1, cores + 1):
            out = Path(folder) / f"jobs-{jobs}"
            wall = sweep(args.plan, args.seeds, jobs, out)
            if jobs == 1:
                serial = lines(out)
                text = (out / "seeds.jsonl").read_text().splitlines()
                cpu = sum(float(json.loads(line)["cpu_s"]) for line in text)
            rows.append((jobs, wall, lines(out) == serial))
    base = rows[0][1]
    print(f"{args.plan}, seeds {args.seeds} ({count}), {cores} cores available")
    print(f"{'jobs':>4}  {'wall s':>7}  {'seeds/wall-min':>14}  {'speed-up':>8}  same as --jobs 1")
    for jobs, wall, same in rows:
        per_minute = 60 * count / wall
        print(f"{jobs:>4}  {wall:>7.1f}  {per_minute:>14.1f}  {base / wall:>7.2f}x  {same}")
    per_seed = cpu / count
    print(
        f"CPU per seed (--jobs 1): {per_seed:.2f} s; 10,000 seeds on 16 such cores: "
        f"about {10_000 * per_seed / 16 / 60:.0f} min (at best)"
    )


if __name__ == "__main__":
    main()
