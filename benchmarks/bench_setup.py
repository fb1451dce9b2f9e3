"""The README's second command, timed: what `docs/index.md`'s table of its steps reports.

    python benchmarks/bench_setup.py              # quiet: nothing else running
    python benchmarks/bench_setup.py --busy 2     # beside two CPU-bound processes

Runs, from the checkout, the two steps of the README's second command that take time
(not `apt-get`: the system packages are there or not), each in a fresh virtual
environment made for the purpose, and prints what `docs/index.md` needs, ready to paste:

1. `pip install -e ".[dev,bench]"` into a fresh venv, pip's cache warm (the same install
   is done once, untimed, into another fresh venv first; `--no-warm-up` leaves that out
   and times whatever the cache holds);
2. `python -m pytest -q -n 5 --dist loadfile` with that venv's interpreter: its wall time,
   and how many tests passed and failed (the summary line).

With `--busy N`, N processes that only spin (`while True: pass`) run beside it all (the
table's "two CPU-bound processes beside it" column is `--busy 2`). The load average
before and after, the commit, the date and the cores are printed with the figures: a
figure is only worth what was running beside it, and a loaded shared machine makes
neither column.

`--only install` or `--only tests` times one step; `--python PATH` runs the tests with an
existing interpreter instead of a fresh venv (and `--select` runs only some tests: how
`tests/test_benchmarks.py` keeps this script from rotting, in seconds).
"""

from __future__ import annotations

import argparse
import datetime
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _harness

ROOT = Path(__file__).resolve().parent.parent
INSTALL = ["-m", "pip", "install", "--quiet", "-e", ".[dev,bench]"]
TESTS = ["-m", "pytest", "-q", "-n", "5", "--dist", "loadfile"]
"""The README's second command's steps (`.ci/run` runs the same)."""


def _minutes(seconds: float) -> str:
    minutes, rest = divmod(round(seconds), 60)
    return f"{minutes} min {rest} s" if minutes else f"{seconds:.1f} s"


def _venv(where: Path) -> Path:
    """A fresh virtual environment at `where`; its interpreter."""
    subprocess.run([sys.executable, "-m", "venv", str(where)], check=True)
    return where / "bin" / "python"


def _timed(argv: list[str], log: Path) -> tuple[float, int]:
    """Run `argv` in the checkout, its output to `log`; its wall time and exit code."""
    started = time.monotonic()
    with log.open("w") as out:
        code = subprocess.run(argv, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, check=False)
    return time.monotonic() - started, code.returncode


def _outcome(log: Path) -> str:
    """pytest's counts from its summary line (`3243 passed, 3 failed`)."""
    summary = log.read_text(errors="replace").strip().splitlines()[-1:] or [""]
    counts = re.findall(r"(\d+) (passed|failed|errors?|skipped)", summary[0])
    return ", ".join(f"{int(n):,} {what}" for n, what in counts) or summary[0]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--busy", type=int, default=0, help="CPU-bound processes beside it (0)")
    parser.add_argument("--only", choices=("install", "tests"), help="time one step only")
    parser.add_argument("--no-warm-up", action="store_true", help="no untimed install first")
    parser.add_argument("--python", type=Path, help="run the tests with this interpreter")
    parser.add_argument("--select", nargs="+", help="test paths to run (default: all)")
    args = parser.parse_args()

    rows: list[tuple[str, str, str]] = []
    before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="bench-setup-") as tmp, _harness.busy(args.busy):
        work = Path(tmp)
        python = args.python
        if python is None:  # a fresh venv, the install timed (untimed with --only tests)
            if args.only != "tests" and not args.no_warm_up:
                _timed([str(_venv(work / "warm")), *INSTALL], work / "warm.log")
            python = _venv(work / "venv")
            took, code = _timed([str(python), *INSTALL], work / "install.log")
            if code != 0:
                print((work / "install.log").read_text()[-3000:], file=sys.stderr)
                return 1
            cache = "pip's cache as it was" if args.no_warm_up else "pip's cache warm"
            if args.only != "tests":
                rows.append((f'`pip install -e ".[dev,bench]"` ({cache})', _minutes(took), ""))
        if args.only != "install":
            log = work / "tests.log"
            took, _ = _timed([str(python), *TESTS, *(args.select or [])], log)
            rows.append((f"`python {' '.join(TESTS)}`", _minutes(took), _outcome(log)))
    after = os.getloadavg()[0]

    now = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    print(f"the README's second command, timed at {_harness.commit()}, {now}")
    print(
        f"{os.cpu_count()} cores; {args.busy} CPU-bound process(es) beside it; "
        f"load average {before:.1f} before, {after:.1f} after"
    )
    print()
    print("| step | wall time | outcome |")
    print("|---|---|---|")
    for row in rows:
        print("| " + " | ".join(row) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
