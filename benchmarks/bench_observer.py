"""The observer's figures: how fast a restart shows, what an open page costs, its memory.

Three parts (each can be run alone with `--only`):

    restart     SIGKILL a process manager `--kills` times; for each, the time from the kill to
                the page (a real chromium, Playwright) showing the new restart count, next to
                the restart itself (ChildRestarted.restart_s) and to the event stream (an SSE
                client of the same observer); median and p90 (target: page under 250 ms)
    overhead    a dedup-hit call (+ its unload) against a process manager, per call, with no
                observer, with an observer, and with an observer and a page open; and the
                mission's stops (F1, F2: robot stopped) and time, `--missions` runs each
                without and with an observer and a page (target: under 10 % more)
    memory      one mission stretched over `--soak` seconds with a page open and a WARNING
                every 0.2 s: browser memory (its processes' RSS, the page's JS heap) and this
                process's RSS every `--sample` seconds (flat: no growth after the warm-up)
    page        what one open page costs per catalog size (`--resources 1000,5000`): the
                bytes of its first paint and of one change, this process's CPU per change
                with no page and with one stream reading, and a chromium page's time to
                draw the catalogs and its JS heap

    python benchmarks/bench_observer.py                      # about 3 minutes (soak 60 s)
    python benchmarks/bench_observer.py --only memory --soak 600 --sample 60   # 10 minutes
    python benchmarks/bench_observer.py --only page --resources 1000,2000       # a minute

It needs the dev extra (playwright, psutil) and Debian's chromium (`RR_CHROMIUM` to use
another). Prints tables; asserts nothing.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import _harness
import psutil
from playwright.sync_api import sync_playwright

import rr_actors as rr
from rr_actors_lab.mission.config import MissionConfig
from rr_actors_lab.mission.run import run_mission
from rr_actors_lab.observe import observe

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # the repository: tests.support
from tests.support.observing import CHROMIUM_ARGS, chromium, stream


def erm_setup(registrar: rr.ResourceRegistrar) -> None:
    """The manager of these measurements (defined here: a manager process unpickles it by
    value, without importing the tests' helpers, which import pytest)."""
    registrar.register_server("camera", load=lambda r: {"device": r}, unload=lambda q, r: None)


table = _harness.print_table


@contextlib.contextmanager
def browser() -> Iterator[tuple[Any, str]]:
    path = chromium()
    if path is None:
        raise SystemExit("no chromium: apt-get install -y chromium (or set RR_CHROMIUM)")
    with sync_playwright() as playwright, tempfile.TemporaryDirectory() as profile:
        context = playwright.chromium.launch_persistent_context(
            profile,
            executable_path=path,
            headless=True,
            args=CHROMIUM_ARGS,
            viewport={"width": 1400, "height": 1000},
        )
        try:
            yield context, profile
        finally:
            context.close()


def ms(seconds: float) -> str:
    return f"{seconds * 1e3:.1f}"


# -- restart ------------------------------------------------------------------------------


def bench_restart(kills: int, settle: float) -> None:
    page_s: list[float] = []
    stream_s: list[float] = []
    restart_s: list[float] = []
    sup = rr.Supervisor(
        [rr.ManagerSpec("erm", erm_setup, isolation="process")],
        max_restarts=kills + 5,
        period=3600.0,
    )
    restarted: list[float] = []
    done = threading.Event()

    def on_event(event: rr.events.Event) -> None:
        if isinstance(event, rr.events.ChildRestarted):
            restarted.append(event.restart_s)
            done.set()

    with sup, sup.subscribe(on_event), browser() as (context, _):
        observer = observe(sup)
        page = context.new_page()
        page.goto(observer.url)
        page.wait_for_selector('.node[data-child="erm"][data-state="running"]')
        with stream(observer.url) as events:
            events.until(lambda s: "tree" in s.sections, timeout=10)
            for n in range(1, kills + 1):
                pid = sup.child("erm").pid
                assert pid is not None
                done.clear()
                killed = time.monotonic()
                os.kill(pid, signal.SIGKILL)
                events.until(
                    lambda s, n=n: (
                        next(c for c in s.sections["tree"]["children"] if c["name"] == "erm")[
                            "restarts"
                        ]
                        == n
                    ),
                    timeout=10,
                )
                stream_s.append(time.monotonic() - killed)
                page.wait_for_selector(
                    f'.node[data-child="erm"][data-restarts="{n}"]', timeout=10_000
                )
                page_s.append(time.monotonic() - killed)
                done.wait(5)
                sup.wait_restarted("erm", timeout=10, restarts=n)
                time.sleep(settle)  # the spare process pool refills (as between real crashes)
        restart_s.extend(restarted)
    rows = [
        ("the restart itself (ChildRestarted.restart_s)", *summary(restart_s)),
        ("kill -> event stream shows restarts + 1", *summary(stream_s)),
        ("kill -> page shows restarts + 1 (chromium)", *summary(page_s)),
    ]
    table(
        f"SIGKILL of a process manager to the page ({kills} kills), ms",
        ("from the kill to", "median", "p90", "max"),
        rows,
    )


def summary(values: list[float]) -> tuple[str, str, str]:
    if not values:
        return ("-", "-", "-")
    return ms(statistics.median(values)), ms(_harness.percentile(values, 0.9)), ms(max(values))


# -- overhead -----------------------------------------------------------------------------


def dedup_calls(app: rr.ResourceRegistrar, calls: int) -> float:
    """Seconds per dedup-hit call + unload over `calls` calls."""
    start = time.perf_counter()
    for _ in range(calls):
        app.unload(app.call("erm", "camera", "shared").id)
    return (time.perf_counter() - start) / calls


def bench_overhead(calls: int, rounds: int, missions: int) -> None:
    """Rows interleaved round by round (noise from other programs spreads evenly)."""
    rows = ("no observer", "a no-op subscriber", "observer open", "observer + page")
    samples: dict[str, list[float]] = {row: [] for row in rows}
    sup = rr.Supervisor([rr.ManagerSpec("erm", erm_setup, isolation="process")])
    with sup, browser() as (context, _):
        app = sup.registrar("bench")
        holder = app.call("erm", "camera", "shared")  # the resource stays loaded: dedup hits
        dedup_calls(app, calls)  # warm-up
        for _ in range(rounds):
            samples["no observer"].append(dedup_calls(app, calls))
            with sup.subscribe(lambda _: None):
                samples["a no-op subscriber"].append(dedup_calls(app, calls))
            with observe(sup) as observer:
                samples["observer open"].append(dedup_calls(app, calls))
                page = context.new_page()
                page.goto(observer.url)
                page.wait_for_selector('.node[data-child="erm"][data-state="running"]')
                samples["observer + page"].append(dedup_calls(app, calls))
                page.close()
        app.unload(holder.id)
    medians = {row: statistics.median(values) for row, values in samples.items()}
    base, subscribed = medians["no observer"], medians["a no-op subscriber"]
    table(
        f"dedup-hit call + unload against a process manager, median of {rounds} rounds of "
        f"{calls}, us",
        ("observer", "per call", "vs none", "vs a no-op subscriber"),
        [
            (
                row,
                f"{v * 1e6:.0f}",
                f"{(v / base - 1) * 100:+.1f} %",
                f"{(v / subscribed - 1) * 100:+.1f} %",
            )
            for row, v in medians.items()
        ],
    )
    bench_mission_stops(missions)


STOP_ROWS = ("no observer", "observer open", "observer + page")


def bench_mission_stops(missions: int) -> None:
    stops: dict[str, list[float]] = {row: [] for row in STOP_ROWS}
    times: dict[str, list[float]] = {row: [] for row in STOP_ROWS}
    with browser() as (context, _):
        for round_ in range(missions):
            for label, values in stops.items():
                report = mission_with(label, context)
                values.extend(f.robot_stopped_s for f in report.faults if f.id in ("F1", "F2"))
                times[label].append(report.mission_time_s)
            print(f"  mission round {round_ + 1}/{missions} done", file=sys.stderr)
    base_stop = statistics.median(stops["no observer"])
    base_time = statistics.median(times["no observer"])
    rows = []
    for label in STOP_ROWS:
        stop, took = statistics.median(stops[label]), statistics.median(times[label])
        rows.append(
            (
                label,
                f"{stop * 1e3:.0f}",
                f"{(stop / base_stop - 1) * 100:+.1f} %",
                f"{took:.2f}",
                f"{(took / base_time - 1) * 100:+.1f} %",
            )
        )
    table(
        f"the mission (--fast), {missions} runs each, medians: robot stopped per stop "
        "(F1, F2), mission time",
        ("observer", "stop, ms", "vs none", "mission, s", "vs none"),
        rows,
    )


def mission_with(label: str, context: Any) -> Any:
    """One fast mission: no observer, an observer, or an observer open in a page throughout."""
    urls: list[str] = []
    opened = threading.Event()

    def observed(sup: rr.Supervisor) -> None:
        urls.append(observe(sup).url)
        opened.set()

    with tempfile.TemporaryDirectory() as out:
        result: list[Any] = []
        hook = None if label == "no observer" else observed
        runner = threading.Thread(
            target=lambda: result.append(run_mission(MissionConfig.fast(), out, on_supervisor=hook))
        )
        runner.start()
        if label == "observer + page":
            page = context.new_page()
            if opened.wait(30):
                page.goto(urls[0])
            while runner.is_alive():
                page.wait_for_timeout(100)  # (the page lives on in the browser meanwhile)
            page.close()
        runner.join()
    return result[0]


# -- memory -------------------------------------------------------------------------------


def browser_memory(profile: str) -> tuple[float, float]:
    """MiB of the browser's processes (those started with this profile): RSS, and USS.

    RSS counts the pages they share once per process; USS (unique set size) counts only
    what each one holds alone, so its sum does not grow with sharing.
    """
    rss = uss = 0
    for proc in psutil.process_iter(["cmdline"]):
        with contextlib.suppress(psutil.Error):
            if any(profile in part for part in proc.info["cmdline"] or ()):
                info = proc.memory_full_info()
                rss += info.rss
                uss += info.uss
    return rss / 2**20, uss / 2**20


def bench_memory(soak: float, sample: float) -> None:
    speed = 2.0
    config = MissionConfig.fast()
    import dataclasses  # noqa: PLC0415

    config = dataclasses.replace(
        config, distance_m=max(config.distance_m, speed * soak), speed=speed
    )
    me = psutil.Process()
    rows: list[tuple[Any, ...]] = []
    opened: list[rr.Supervisor] = []
    urls: list[str] = []

    def observed(sup: rr.Supervisor) -> None:
        urls.append(observe(sup).url)
        opened.append(sup)

    stop_statuses = threading.Event()

    def statuses() -> None:  # a WARNING on the robot every 0.2 s: timeline rows and events
        while not stop_statuses.wait(0.2):
            with contextlib.suppress(rr.RrError, IndexError):
                opened[0].run_in(
                    "rm",
                    lambda reg: reg.send_status(
                        reg.server_queries("robot")[0].id, rr.Status.WARNING, "soak"
                    ),
                )

    with browser() as (context, profile), tempfile.TemporaryDirectory() as out:
        result: list[Any] = []
        runner = threading.Thread(
            target=lambda: result.append(run_mission(config, out, on_supervisor=observed))
        )
        runner.start()
        page = context.new_page()
        deadline = time.monotonic() + 30
        while not urls and time.monotonic() < deadline:
            page.wait_for_timeout(10)
        page.goto(urls[0])
        page.wait_for_selector('.node[data-child="rm"][data-state="running"]')
        threading.Thread(target=statuses, daemon=True).start()
        start = time.monotonic()
        while runner.is_alive():
            heap = page.evaluate("() => performance.memory ? performance.memory.usedJSHeapSize : 0")
            nodes = page.evaluate("() => document.getElementsByTagName('*').length")
            rss, uss = browser_memory(profile)
            rows.append(
                (
                    f"{time.monotonic() - start:.0f}",
                    f"{rss:.0f}",
                    f"{uss:.0f}",
                    f"{heap / 2**20:.1f}",
                    nodes,
                    f"{me.memory_info().rss / 2**20:.0f}",
                )
            )
            page.wait_for_timeout(sample * 1000)
        stop_statuses.set()
        runner.join()
    table(
        f"a page open for a mission of {soak:.0f} s (WARNING every 0.2 s), "
        f"sampled every {sample:g} s",
        (
            "t, s",
            "browser RSS, MiB",
            "browser USS, MiB",
            "page JS heap, MiB",
            "DOM nodes",
            "this process RSS, MiB",
        ),
        rows,
    )
    print(f"mission ok: {result[0].ok if result else None}")


# -- page ---------------------------------------------------------------------------------


def bench_page(sizes: list[int], changes: int) -> None:
    """One page's cost against a catalog of `n` resources (a thread manager: no IPC noise)."""
    rows: list[tuple[Any, ...]] = []
    me = psutil.Process()
    with browser() as (context, _):
        for n in sizes:
            sup = rr.Supervisor([rr.ManagerSpec("erm", erm_setup, isolation="thread")])
            with sup:
                observer = observe(sup)
                app = sup.registrar("bench")
                held = [app.call("erm", "camera", f"/dev/video{i}") for i in range(n)]

                def shown(state: Any, n: int = n) -> bool:
                    section = state["sections"].get("catalog/erm")
                    return bool(section and len(section["catalog"]["resources"]) == n)

                wait_until(observer.url, shown)
                cpu_none = cpu_per_change(me, app, changes)
                with stream(observer.url) as page:
                    first = first_paint_bytes(page, n)
                    got = [0]
                    reader = threading.Thread(target=read_on, args=(page, got), daemon=True)
                    reader.start()
                    cpu_page = cpu_per_change(me, app, changes)
                    per_change = got[0] / changes
                tab = context.new_page()
                start = time.perf_counter()
                tab.goto(observer.url)
                tab.wait_for_selector('#catalogs [data-registrar="erm"] .resource', timeout=120_000)
                drawn = time.perf_counter() - start
                heap = tab.evaluate(
                    "() => performance.memory ? performance.memory.usedJSHeapSize : 0"
                )
                tab.close()
                for query in held:
                    app.unload(query.id)
            rows.append(
                (
                    n,
                    f"{first / 1024:.0f}",
                    f"{per_change / 1024:.1f}",
                    f"{cpu_none * 1e3:.1f}",
                    f"{cpu_page * 1e3:.1f}",
                    f"{drawn * 1e3:.0f}",
                    f"{heap / 2**20:.1f}",
                )
            )
    table(
        f"one open page against a catalog of n resources ({changes} changes each)",
        (
            "resources",
            "first paint, KiB",
            "stream per change, KiB",
            "CPU per change, no page, ms",
            "with a page, ms",
            "chromium draws it, ms",
            "page JS heap, MiB",
        ),
        rows,
    )


def wait_until(url: str, predicate: Any, timeout: float = 60.0) -> None:
    from tests.support.observing import get_json  # noqa: PLC0415

    deadline = time.monotonic() + timeout
    while not predicate(get_json(url, "/api/state")):
        if time.monotonic() > deadline:
            raise SystemExit("the observer did not show the catalog")
        time.sleep(0.05)


def first_paint_bytes(page: Any, n: int) -> int:
    """Bytes a new page reads until it holds the catalogs of `n` resources and the graph."""
    got = [0]
    readline = page.response.readline

    def counted() -> bytes:
        line: bytes = readline()
        got[0] += len(line)
        return line

    page.response.readline = counted
    try:
        while not (painted(page.sections, n) and page.events):  # (the recent events too)
            page.next()  # (sections, and patches applied)
    finally:
        page.response.readline = readline
    return got[0]


def painted(sections: dict[str, Any], n: int) -> bool:
    """Whether a page holds both catalogs (`n` resources, `n` client records) and the graph."""
    erm, bench = sections.get("catalog/erm"), sections.get("catalog/bench")
    return bool(
        erm
        and bench
        and len(erm["catalog"]["resources"]) == n
        and len(bench["catalog"]["clients"]) == n
        and len(sections.get("graph", {}).get("edges", ())) == n
    )


def read_on(page: Any, got: list[int]) -> None:
    """Read the stream to its end, counting its bytes in `got[0]`."""
    with contextlib.suppress(Exception):
        while line := page.response.readline():
            got[0] += len(line)


def cpu_per_change(me: Any, app: rr.ResourceRegistrar, changes: int) -> float:
    """This process's CPU seconds per change of the catalog (a load, then its unload, each
    after the observer's catalog interval: the page gets every one), the observer's own
    catalog reads included."""
    before = sum(me.cpu_times()[:2])
    held = None
    for i in range(changes):
        if held is None:
            held = app.call("erm", "camera", f"change-{i}")
        else:
            app.unload(held.id)
            held = None
        time.sleep(0.6)
    if held is not None:
        app.unload(held.id)
    return (sum(me.cpu_times()[:2]) - before) / changes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--only", choices=("restart", "overhead", "stops", "memory", "page"), default=None
    )
    parser.add_argument(
        "--resources", default="1000,5000", help="catalog sizes of the page part, comma-separated"
    )
    parser.add_argument("--changes", type=int, default=30, help="changes per size (page part)")
    parser.add_argument("--kills", type=int, default=20)
    parser.add_argument(
        "--settle", type=float, default=1.0, help="seconds between a restart and the next kill"
    )
    parser.add_argument("--calls", type=int, default=300, help="dedup-hit calls per round")
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--missions", type=int, default=5)
    parser.add_argument("--soak", type=float, default=60.0, help="seconds of the memory run")
    parser.add_argument("--sample", type=float, default=10.0, help="seconds between samples")
    args = parser.parse_args()
    print(f"python {sys.version.split()[0]}, {os.cpu_count()} CPUs, chromium {chromium()}")
    if args.only in (None, "restart"):
        bench_restart(args.kills, args.settle)
    if args.only in (None, "overhead"):
        bench_overhead(args.calls, args.rounds, args.missions)
    elif args.only == "stops":
        bench_mission_stops(args.missions)
    if args.only in (None, "memory"):
        bench_memory(args.soak, args.sample)
    if args.only in (None, "page"):
        bench_page([int(n) for n in args.resources.split(",")], args.changes)


if __name__ == "__main__":
    main()
