"""Fidelity of verdicts: do a shipped plan's real and simulated runs break the same rules?

    python benchmarks/bench_verdict_kinds.py --runs 2 --seeds 1-50 --out /tmp/kinds
    python benchmarks/bench_verdict_kinds.py --plans simchain,simretry --runs 1 --seeds 1-5

Issue 42's fidelity figure: "a shipped plan's real and simulated runs give the same
verdict kinds". For each plan of `rr_actors_lab/experiments/plans/` (or `--plans`):

    check_simulable(plan) ─► refused: a row saying why (no run, real or simulated)
    the plan as the simulation runs it: a `[compare]` cut to its first value
      (OUT/plans/NAME.toml; `--duration` shortens both sides alike)
    real:      rr-actors experiment NAME.toml --repeat N --out OUT/real/NAME
               then the checker of every run (`check.check_file`, what
               `rr-actors check OUT/real/NAME` prints)
    simulated: rr-actors experiment NAME.toml --simulate --seeds A-B --out OUT/sim/NAME
               (each seed's verdict in OUT/sim/NAME/seeds.jsonl; the histories of those
               that did not hold kept beside it: `rr-actors replay OUT/sim/NAME --seed S
               --story` tells one)

Both are the command-line runs a user makes, each in its own process (the sweep under
`PYTHONHASHSEED=0`, so that every seed replays). A *kind* is a rule's name (`end`,
`kept`, ...) of a violation; the table counts, per kind, the runs (real) or seeds
(simulated) whose verdict had one, and says whether the two sides saw the same kinds.
A kind seen only on the simulation is expected when the real runs are few: replay its
seed (`--story`) to tell a protocol bug from a checker's false positive or an artefact
of the simulation (docs/performance.md, "Simulation fidelity", explains each one
recorded). It exits 0 when every command ran, whatever the kinds; 1 if one failed.

Why a script of its own, not a flag of `bench_simulation_fidelity.py`: that one runs
the simulation alone, many times a seed in worker processes, and compares history
hashes; this one runs real experiments and compares the checker's findings.
"""

from __future__ import annotations

import argparse
import collections
import datetime
import json
import os
import re
import subprocess
import sys
import tempfile
import time
import tomllib
from collections.abc import Iterable, Mapping
from pathlib import Path

import _harness

import rr_actors_lab
from rr_actors_lab.experiments import check, load_plan
from rr_actors_lab.experiments.plan import PlanError
from rr_actors_lab.experiments.simulate import check_simulable

ROOT = Path(__file__).resolve().parent.parent
PLANS = Path(rr_actors_lab.__file__).parent / "experiments" / "plans"
TIMEOUT = 1800.0
"""Seconds one command (a plan's real runs, or its seeds) may take before it counts as hung."""

FINDING = re.compile(r"^\s*(violation|unverifiable) \[([a-z-]+)\]")
"""A finding's line as `check.format_verdict` prints it: its kind, and its rule."""


# -- the comparison (pure: verdict summaries in, a table's cells out) -------------------------


def kinds_of_lines(findings: Iterable[str]) -> set[str]:
    """The rules of the violations among a run's finding lines (`seeds.jsonl`'s
    `findings`); windows and unverifiable findings are not kinds."""
    return {m[2] for line in findings if (m := FINDING.match(line)) and m[1] == "violation"}


def kinds_of_verdict(verdict: check.Verdict) -> set[str]:
    """The rules of a verdict's violations."""
    return {f.rule for f in verdict.findings if f.kind == "violation"}


def tally(runs: Iterable[set[str]]) -> collections.Counter[str]:
    """Per kind, how many runs had it (a run counts once per kind)."""
    counts: collections.Counter[str] = collections.Counter()
    for kinds in runs:
        counts.update(kinds)
    return counts


def same_kinds(real: Mapping[str, int], simulated: Mapping[str, int]) -> bool:
    """Whether both sides saw the same kinds (how often does not count)."""
    return {k for k, n in real.items() if n} == {k for k, n in simulated.items() if n}


def show_kinds(counts: Mapping[str, int]) -> str:
    """`end 3, kept 1` (most runs first, then by name), or `-` for none."""
    ranked = sorted((k for k, n in counts.items() if n), key=lambda k: (-counts[k], k))
    return ", ".join(f"{k} {counts[k]}" for k in ranked) or "-"


def show_verdicts(verdicts: Iterable[str]) -> str:
    """`5 (4 held, 1 violated)`: how many runs, and their verdicts."""
    counted = collections.Counter(verdicts)
    parts = [f"{counted[v]} {v}" for v in ("held", "violated", "unverifiable") if counted[v]]
    return f"{sum(counted.values())} ({', '.join(parts)})"


# -- running ----------------------------------------------------------------------------------


def first_value_only(source: Path, folder: Path) -> Path:
    """`source` with its `[compare]` cut to its first value, written to `folder`: the plan
    the simulation runs (it takes a compared plan's first value)."""
    text = source.read_text(encoding="utf-8")
    compare = tomllib.loads(text).get("compare")
    path = folder / source.name
    if compare is not None:
        section = text.index("\n[compare]")
        head, tail = text[:section], text[section:]
        first = json.dumps(compare["values"][0])  # (a TOML value: int, float, bool, string)
        cut = f"\nvalues = [{first}]"
        tail, count = re.subn(r"\nvalues\s*=\s*\[[^\]]*\]", cut, tail, count=1)
        if count != 1:
            raise SystemExit(f"{source}: no `values = [...]` in its [compare]")
        text = head + tail
    path.write_text(text, encoding="utf-8")
    plan = load_plan(path)
    if plan.compare is not None and len(plan.compare.values) != 1:
        raise SystemExit(f"{path}: [compare] not cut to one value")
    return path


def command(*args: str) -> None:
    """Run `rr-actors ARGS` in a process of its own; stop (exit 1) if it failed."""
    done = subprocess.run(
        [sys.executable, "-m", "rr_actors_lab", *args],
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
        check=False,
    )
    if done.returncode:
        print(f"rr-actors {' '.join(args)} exited {done.returncode}:\n{done.stderr[-3000:]}")
        raise SystemExit(1)


def real_runs(plan: Path, runs: int, out: Path, duration: float | None) -> list[check.Verdict]:
    """`runs` real runs of `plan` and each one's verdict."""
    extra = ["--duration", str(duration)] if duration is not None else []
    command("experiment", str(plan), "--repeat", str(runs), "--out", str(out), "--quiet", *extra)
    return list(check.check_file(out).values())


def simulated_runs(
    plan: Path, seeds: str, out: Path, duration: float | None
) -> list[tuple[str, set[str]]]:
    """`plan` on the simulation over `seeds`: each seed's verdict and kinds."""
    extra = ["--duration", str(duration)] if duration is not None else []
    command("experiment", str(plan), "--simulate", "--seeds", seeds, "--out", str(out), *extra)
    lines = (out / "seeds.jsonl").read_text(encoding="utf-8").splitlines()
    rows = [json.loads(line) for line in lines if line.strip()]
    return [(row["verdict"], kinds_of_lines(row["findings"])) for row in rows]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plans", help="shipped plans' names, comma-separated (every one)")
    parser.add_argument("--runs", type=int, default=2, help="real runs of each plan (2)")
    parser.add_argument("--seeds", default="1-50", help="simulated seeds, A-B (1-50)")
    parser.add_argument("--duration", type=float, help="each run's duration instead (s)")
    parser.add_argument("--out", help="keep the runs here (a temporary folder otherwise)")
    args = parser.parse_args()
    names = args.plans.split(",") if args.plans else sorted(p.stem for p in PLANS.glob("*.toml"))

    with tempfile.TemporaryDirectory(prefix="bench-kinds-") as tmp:
        out = Path(args.out) if args.out else Path(tmp)
        (out / "plans").mkdir(parents=True, exist_ok=True)
        load_before = os.getloadavg()[0]
        started = time.monotonic()
        rows = []
        for name in names:
            source = PLANS / f"{name}.toml"
            try:
                check_simulable(load_plan(source))
            except PlanError as exc:
                why = str(exc).removeprefix(f"{source}: ")
                rows.append((name, f"refused by the simulation: {why}"))
                print(f"{name}: refused ({why})", flush=True)
                continue
            began = time.monotonic()
            plan = first_value_only(source, out / "plans")
            real = real_runs(plan, args.runs, out / "real" / name, args.duration)
            simulated = simulated_runs(plan, args.seeds, out / "sim" / name, args.duration)
            real_kinds = tally(kinds_of_verdict(v) for v in real)
            sim_kinds = tally(kinds for _, kinds in simulated)
            cells = (
                show_verdicts(v.verdict for v in real),
                show_kinds(real_kinds),
                show_verdicts(verdict for verdict, _ in simulated),
                show_kinds(sim_kinds),
                "yes" if same_kinds(real_kinds, sim_kinds) else "no",
            )
            rows.append((name, cells))
            print(f"{name}: {' | '.join(cells)} ({time.monotonic() - began:.0f} s)", flush=True)
        wall = time.monotonic() - started
        load_after = os.getloadavg()[0]
    _harness.print_table(
        "",
        (
            "plan",
            "real runs",
            "kinds in real runs",
            "seeds",
            "kinds in simulated runs",
            "same kinds",
        ),
        [
            (name, cells, "", "", "", "") if isinstance(cells, str) else (name, *cells)
            for name, cells in rows
        ],
        right=6,
    )
    print(
        f"\n{args.runs} real run(s) and seeds {args.seeds} a plan; "
        f"{datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC, {os.cpu_count()} cores, "
        f"load average {load_before:.1f} before, {load_after:.1f} after; "
        f"{wall:.0f} s of wall time"
        + (f"; runs kept in {args.out} (real/, sim/: rr-actors replay)" if args.out else "")
    )


if __name__ == "__main__":
    main()
