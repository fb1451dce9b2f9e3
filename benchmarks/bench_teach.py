"""The classroom kit's exercises (`rr-actors teach`): each one's check of its starter and
of its solution, as a student runs it (`python -m rr_actors_lab teach check DIR --json`, a
process of its own), CPU seconds of that process and its children (the check's budget:
60 s over at least 200 seeds), and the story a failing check prints: its steps, and the
events of the run it tells (shrunk, for a violation of the checker's rules).

    python benchmarks/bench_teach.py                  # every exercise, its own seeds (200)
    python benchmarks/bench_teach.py --seeds 3 --only climb

A starter's check ends at its first failing seed (`seeds` run: how many it ran); a
solution's runs them all; an exercise's wrong answer (`wrong/`, if it ships one) is
checked too: the rule it breaks, at which seed, its CPU seconds. The floor beside
them: `rr-actors teach list` (the interpreter and the kit's import, no simulation).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def run(*argv: str) -> tuple[float, subprocess.CompletedProcess[str]]:
    """`python -m rr_actors_lab ARGV` with `PYTHONHASHSEED=0`: its CPU seconds (user + system,
    with its children) and its result."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONHASHSEED": "0"}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run(
        [sys.executable, "-m", "rr_actors_lab", *argv],
        capture_output=True,
        text=True,
        env=env,
        check=False,
    )
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return cpu, done


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, help="seeds per check (default: the exercise's)")
    parser.add_argument("--only", nargs="*", help="these exercises only")
    args = parser.parse_args()

    sys.path.insert(0, str(ROOT))
    from rr_actors_lab.teach import kit  # noqa: PLC0415 - this checkout's

    floor, _ = run("teach", "list")
    chosen = [e for e in kit.exercises() if not args.only or e.name in args.only]
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-teach-") as scratch:
        for exercise in chosen:
            cells = [exercise.name, exercise.kind, exercise.topic]
            reports = []
            sides = ["starter", "solution", *(["wrong"] if exercise.wrong() else [])]
            for side in sides:
                folder = Path(scratch) / f"{exercise.name}-{side}"
                kit.start(exercise.name, folder)
                changed = {"starter": {}, "solution": kit.solution_files(exercise)}
                for name, text in changed.get(side, exercise.wrong()).items():
                    (folder / name).write_text(text, encoding="utf-8")
                report = folder / "report.json"
                more = ["--seeds", str(args.seeds)] if args.seeds else []
                cpu, done = run("teach", "check", str(folder), "--json", str(report), *more)
                if not report.is_file():
                    sys.exit(f"{exercise.name} {side}: no report\n{done.stderr[-2000:]}")
                data = json.loads(report.read_text())
                reports.append((cpu, data))
            (starter_cpu, starter), (solution_cpu, solution) = reports[:2]
            wrong = "-"
            if len(reports) == 3:
                wrong_cpu, data = reports[2]
                broken = (data["failure"] or {}).get("rule", "PASSES")
                wrong = f"{broken} (seed {data['seeds_run']}, {wrong_cpu:.1f})"
            failure = starter["failure"] or {}
            verdicts = f"{'fails' if not starter['passed'] else 'PASSES'}/"
            verdicts += "passes" if solution["passed"] else "FAILS"
            cells += [
                verdicts,
                f"{starter['seeds_run']}",
                f"{starter_cpu:.1f}",
                f"{solution['seeds_run']}",
                f"{solution['interleavings']}",
                f"{solution_cpu:.1f}",
                f"{failure.get('story_events', '-')}",
                f"{failure.get('shrunk_events') or '-'}",
                f"{failure.get('run_events', '-')}",
                wrong,
            ]
            rows.append(cells)
    head = [
        "exercise", "kind", "topic", "starter/solution", "seeds (starter)", "CPU s starter",
        "seeds (solution)", "interleavings", "CPU s solution", "story steps",
        "shrunk run events", "run events", "wrong answer: rule (seed, CPU s)",
    ]  # fmt: skip
    print(f"floor: `rr-actors teach list`, {floor:.2f} CPU s")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for cells in rows:
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
