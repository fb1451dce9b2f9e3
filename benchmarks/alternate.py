"""Run one benchmark against two source trees alternately, in the same period: A B A B ...

"Before and after" measured hours apart on a shared 2-core VM differ by more than most
changes do; alternating the two trees, run after run, exposes both to the same noise.
Each run is the tree's own copy of the benchmark script, run by that tree's Python (a
venv where the tree is installed), in the tree's directory. Every run's output is
printed whole; for tables in Markdown (`| name | ... | 1.7x |`) the last column of each
row is also collected per tree and shown side by side at the end.

Usage:
    python benchmarks/alternate.py --before TREE PYTHON [--pairs 3] [--pin] -- SCRIPT ARGS...

Example (the restructuring of issue 13 against 0.1.0's last commit):
    git worktree add /tmp/before 889a687
    python -m venv /tmp/venv-before && /tmp/venv-before/bin/pip install -e /tmp/before
    python benchmarks/alternate.py --before /tmp/before /tmp/venv-before/bin/python \\
        --pairs 3 --pin -- bench_core.py --rounds 10

Each run imports `rr_actors` from its tree (`PYTHONPATH`), whichever tree the venv has
installed. `--pin` runs each benchmark under `taskset -c 0` (one CPU: the ratios hold better, the
absolute figures are slower).
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent.parent
ROW = re.compile(r"^\|\s*(?P<name>[^|]+?)\s*\|.*\|\s*(?P<last>[0-9.]+x)\s*\|\s*$")


def run(tree: Path, python: str, script: str, args: list[str], *, pin: bool) -> str:
    """One run of `tree`'s copy of `script`; its standard output."""
    command = [python, str(tree / "benchmarks" / script), *args]
    if pin:
        command = ["taskset", "-c", "0", *command]
    env = {**os.environ, "PYTHONPATH": str(tree)}  # its own tree, wherever the venv points
    done = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        sys.stderr.write(done.stderr)
        raise SystemExit(f"{' '.join(command)} failed with exit code {done.returncode}")
    return done.stdout


def ratios(output: str) -> dict[str, str]:
    """The last column of every Markdown table row that ends in a ratio (`1.7x`)."""
    found: dict[str, str] = {}
    for line in output.splitlines():
        match = ROW.match(line.strip())
        if match:
            found[match["name"]] = match["last"]
    return found


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", nargs=2, metavar=("TREE", "PYTHON"), required=True)
    parser.add_argument("--pairs", type=int, default=3, help="before/after pairs (default 3)")
    parser.add_argument("--pin", action="store_true", help="run under taskset -c 0")
    parser.add_argument("script", help="the benchmark script's file name in benchmarks/")
    parser.add_argument("args", nargs=argparse.REMAINDER, help="its arguments (after --)")
    options = parser.parse_args()
    args = [a for a in options.args if a != "--"]
    trees = {
        "before": (Path(options.before[0]).resolve(), options.before[1]),
        "after": (HERE, sys.executable),
    }
    collected: dict[str, dict[str, list[str]]] = {"before": {}, "after": {}}
    for pair in range(1, options.pairs + 1):
        for label, (tree, python) in trees.items():
            output = run(tree, python, options.script, args, pin=options.pin)
            print(f"== {label} ({tree}), run {pair} ==")
            print(output)
            for name, value in ratios(output).items():
                collected[label].setdefault(name, []).append(value)
    names = [n for n in collected["after"] if n in collected["before"]]
    if names:
        print("== last column per run: before | after ==")
        for name in names:
            before = ", ".join(collected["before"][name])
            after = ", ".join(collected["after"][name])
            print(f"{name}: {before} | {after}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
