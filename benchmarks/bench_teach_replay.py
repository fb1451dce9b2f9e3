"""What a step of `rr-actors teach replay` costs: the server's time to make it, the page's.

For each exercise (`--exercises`) and seed (`--seeds`), the starter's run is replayed:

    server   every step, in order and then `--jumps` random ones (a scrub: up to
             CHECKPOINT - 1 steps folded from a checkpoint): the time to make the step's
             sections (`Replay.sections`) and to put them in the observer's hub
             (`Replay.show`: the diffs against the last step)
    browser  the page (a real chromium, Playwright, as the tests drive it) `--clicks`
             times: from a click on "step" (or a scrub to a random step) to the page
             showing that step, tree, catalogs, graph and story drawn, the next frame
             painted (`performance.now()` in the page: the request, the stream, the render)

    branch   `--branches` times (seed 1): a kill of a manager from the page at a random step
             (`Replay.branch`: the seed run again with that fault, then folded)

`--duration` runs each plan longer (more steps). Prints a table: median, p90 and max in
milliseconds (the target: at most 100 ms a step).

    python benchmarks/bench_teach_replay.py                         # about a minute
    python benchmarks/bench_teach_replay.py --exercises camera --seeds 1 --clicks 5
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import random
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from playwright.sync_api import sync_playwright

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this repository's, tests.support
from rr_actors_lab.teach import grade, kit, replay
from tests.support.observing import CHROMIUM_ARGS, chromium

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
    values = sorted(values)
    p90 = values[min(len(values) - 1, int(len(values) * 0.9))]
    return f"{statistics.median(values):.2f}", f"{p90:.2f}", f"{values[-1]:.2f}"


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--exercises", default="camera,restarts,refcount", help="comma-separated")
    parser.add_argument("--seeds", type=int, default=2, help="seeds 1..N of each")
    parser.add_argument("--jumps", type=int, default=200, help="random steps (server)")
    parser.add_argument("--clicks", type=int, default=30, help="steps and scrubs (browser)")
    parser.add_argument("--branches", type=int, default=3, help="kills run again (seed 1)")
    parser.add_argument("--duration", type=float, help="seconds of each run (default: its plan's)")
    args = parser.parse_args()
    print(f"python {sys.version.split()[0]}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}")
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
    header = ("run", "per step", "n", "median ms", "p90 ms", "max ms")
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    for row in [header, tuple("-" * w for w in widths), *rows]:
        print("  ".join(str(c).ljust(w) for c, w in zip(row, widths, strict=True)))
    print(f"load after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
