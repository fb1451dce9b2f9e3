"""The classroom kit (`rr-actors teach`): what its checks cost, and what a replay's step costs.

`--what check` (default): each exercise's check of its starter and of its solution, as a
student runs it (`python -m rr_actors_lab teach check DIR --json`, a process of its own),
CPU seconds of that process and its children (the budget: 60 s over at least 200 seeds),
and the story a failing check prints (its steps, the events of the run it tells, shrunk
for a violation of the checker's rules). A starter's check ends at its first failing seed;
a solution's runs them all; an exercise's wrong answer (`wrong/`, if it ships one) is
checked too. The floor: `rr-actors teach list` (the interpreter and the kit's import).

`--what replay`: for each exercise (`--exercises`) and seed, the starter's run replayed:

    server   every step in order, then `--jumps` random ones (a scrub): the time to make
             its sections (`Replay.sections`) and to put them in the hub (`Replay.show`)
    browser  a real chromium (Playwright) `--clicks` times: from a click on "step" (or a
             scrub) to the page showing that step drawn, the next frame painted
    branch   `--branches` times (seed 1): a kill of a manager from a random step
             (`Replay.branch`: the seed run again with that fault, then folded)

in milliseconds, median, p90, max (the target: at most 100 ms a step).

    python benchmarks/bench_teach.py [--seeds 3 --only climb]
    python benchmarks/bench_teach.py --what replay [--exercises camera --seeds 1 --clicks 5]
"""

from __future__ import annotations

import dataclasses
import json
import os
import random
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import _harness

ROOT = _harness.ROOT
sys.path.insert(0, str(ROOT))  # this checkout's rr_actors_lab, and tests.support
from playwright.sync_api import sync_playwright  # noqa: E402

from rr_actors_lab.teach import grade, kit, replay  # noqa: E402
from tests.support.observing import CHROMIUM_ARGS, chromium  # noqa: E402


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


def checks(args: Any) -> None:

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
    print(_harness.header(f"floor: `rr-actors teach list`, {floor:.2f} CPU s"))
    print(_harness.table(head, rows, right=4))


CLICK = """async ([button, target]) => {
  const panel = document.querySelector("#replay-panel");
  const t0 = performance.now();
  const shown = new Promise((resolve) => {
    const watch = new MutationObserver(() => {
      if (panel.dataset.step !== String(target)) return;
      watch.disconnect();
      requestAnimationFrame(() => setTimeout(() => resolve(performance.now() - t0), 0));
    });
    watch.observe(panel, { attributes: true, attributeFilter: ["data-step"] });
  });
  if (button) document.querySelector(button).click();
  else {
    const scrub = document.querySelector("#replay-scrub");
    scrub.value = target;
    scrub.dispatchEvent(new Event("input"));
  }
  return await shown;
}"""


def ms(values: list[float]) -> tuple[str, str, str]:
    p90 = _harness.percentile(values, 0.9)
    return f"{_harness.median(values):.2f}", f"{p90:.2f}", f"{max(values):.2f}"


def server(shown: replay.Replay, jumps: int, rng: random.Random) -> dict[str, list[float]]:
    times: dict[str, list[float]] = {"sections, in order": [], "show, in order": []}
    times |= {"sections, a scrub": [], "show, a scrub": []}
    order = list(range(1, len(shown) + 1))
    scrubs = [rng.randint(1, len(shown)) for _ in range(jumps)]
    for how, steps in (("in order", order), ("a scrub", scrubs)):
        for n in steps:
            t0 = time.perf_counter()
            shown.sections(n)
            t1 = time.perf_counter()
            shown.show(n)
            t2 = time.perf_counter()
            times[f"sections, {how}"].append((t1 - t0) * 1000)
            times[f"show, {how}"].append((t2 - t1) * 1000)
    return times


def browser(shown: replay.Replay, clicks: int, rng: random.Random) -> dict[str, list[float]]:
    path = chromium()
    if path is None:
        raise SystemExit("no chromium: apt-get install -y chromium (or set RR_CHROMIUM)")
    times: dict[str, list[float]] = {"page: step": [], "page: scrub": []}
    observer, on_page = replay.open_replay(shown.plan, shown.run)
    try:
        with sync_playwright() as playwright, tempfile.TemporaryDirectory() as profile:
            context = playwright.chromium.launch_persistent_context(
                profile,
                executable_path=path,
                headless=True,
                args=CHROMIUM_ARGS,
                viewport={"width": 1400, "height": 1000},
            )
            page = context.new_page()
            page.goto(observer.url)
            page.wait_for_selector('#replay-panel[data-step="1"]')
            for _ in range(min(clicks, len(on_page) - 1)):
                times["page: step"].append(
                    page.evaluate(CLICK, ["#replay-step", on_page.shown + 1])
                )
            for _ in range(clicks):
                target = rng.choice([n for n in range(1, len(on_page) + 1) if n != on_page.shown])
                times["page: scrub"].append(page.evaluate(CLICK, [None, target]))
            context.close()
    finally:
        observer.close()
    return times


def branches(shown: replay.Replay, count: int, rng: random.Random) -> dict[str, list[float]]:
    times: dict[str, list[float]] = {"branch: a kill, run again": []}
    managers = [m.name for m in shown.plan.managers() if m.isolation == "process"]
    for _ in range(count):
        shown.show(rng.randint(2, len(shown)))
        t0 = time.perf_counter()
        shown.branch("kill", rng.choice(managers))
        times["branch: a kill, run again"].append((time.perf_counter() - t0) * 1000)
    return times


def replays(args: Any) -> None:
    rng = random.Random(1)  # noqa: S311 - which steps to scrub to, not a secret
    rows: list[tuple[Any, ...]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.exercises.split(","):
            _chosen, folder = kit.start(name, Path(tmp) / name)
            for seed in range(1, args.seeds + 1):
                plan, run = grade.seed_run(folder, seed)
                rerun = grade.rerun(folder, seed)
                if args.duration is not None:
                    plan = dataclasses.replace(plan, duration=args.duration)
                    run = rerun(plan)
                t0 = time.perf_counter()
                shown = replay.Replay(plan, run, rerun=rerun)
                built = (time.perf_counter() - t0) * 1000
                where = f"{name} seed {seed} ({len(shown)} steps, built in {built:.1f} ms)"
                for what, values in server(shown, args.jumps, rng).items():
                    rows.append((where, what, len(values), *ms(values)))
                if args.clicks > 0 and seed == 1:
                    for what, values in browser(shown, args.clicks, rng).items():
                        rows.append((where, what, len(values), *ms(values)))
                if args.branches > 0 and seed == 1:
                    for what, values in branches(shown, args.branches, rng).items():
                        rows.append((where, what, len(values), *ms(values)))
    print(_harness.header("a replay's steps"))
    print(_harness.table(("run", "per step", "n", "median ms", "p90 ms", "max ms"), rows, right=2))


def main() -> None:
    parser = _harness.options(__doc__)
    parser.add_argument("--what", choices=["check", "replay"], default="check")
    parser.add_argument("--seeds", type=int, help="check: seeds per check (default: its own)")
    parser.add_argument("--only", nargs="*", help="check: these exercises only")
    parser.add_argument("--exercises", default="camera,restarts,refcount", help="replay: a,b,c")
    parser.add_argument("--jumps", type=int, default=200, help="replay: random steps (server)")
    parser.add_argument("--clicks", type=int, default=30, help="replay: steps and scrubs (page)")
    parser.add_argument("--branches", type=int, default=3, help="replay: kills run again")
    parser.add_argument("--duration", type=float, help="replay: seconds of each run")
    args = _harness.parse(parser, None)
    if args.what == "check":
        checks(args)
    else:
        args.seeds = args.seeds or 2
        replays(args)


if __name__ == "__main__":
    main()
