"""The observer across hosts: what sharing costs a host, and how fast a page shows the other host.

Run (as root): `python benchmarks/bench_observer_hosts.py [--only cost|latency]
[--resources N] [--window S] [--kills N] [--cuts N]`. Two Linux network namespaces
(`tests/support/hosts.py`'s `TwoHosts`), `alpha` and `bravo`, each with one `rr.ZenohNetwork` of
mutual TLS (lease 1 s; `bravo` dials `alpha`) and a supervisor in a worker process.

* cost: `bravo` runs a thread manager `slots` serving `--resources` resources (loaded by
  a consumer registrar of its supervisor). Measured over `--window` seconds, idle and
  then with one load and one unload every 0.5 s (two catalog changes a second), with
  (i) no observer, (ii) `observe(sup, across_hosts=False)` (this host only, for
  comparison) and (iii) `observe(sup)` across hosts while `alpha`'s observer follows it
  (its `SystemView`): the CPU time of `bravo`'s process (the supervisor, the router and
  the manager: one process) and of `alpha`'s, from `/proc/<pid>/stat`, and the bytes
  `bravo`'s share published (`Share.sent_bytes`: deltas and state answers). No page is
  open for this part: a page's own cost is the one-host observer's (`bench_observer.py
  --only page`), the same hub and stream on the page's host.
* latency: `alpha`'s page in a headless chromium that runs in `alpha`'s namespace (as the
  tests do). From a SIGKILL of `bravo`'s process manager `cam` to the page showing its
  restart count + 1, `--kills` times; from `ip link set down` of the veth to the page
  showing the link cut and to `bravo`'s tree greyed, and from `ip link set up` to both
  live again, `--cuts` times.

Every time is `time.monotonic` in this process (one clock for every namespace). Without
root nothing is measured (one line says why).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import _harness

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # the repository: tests.support

from tests.support import hosts, pki  # noqa: E402 (the namespaces, the certificates)

PORT = 7447
SYSTEM = "bench"
LEASE = 1.0


# -- what runs in the workers ------------------------------------------------------------------


def slots_setup(registrar: Any) -> None:
    registrar.register_server("slot", load=lambda request: request, unload=lambda _q, _r: None)


def camera_setup(registrar: Any) -> None:
    registrar.register_server("camera", load=lambda request: request, unload=lambda _q, _r: None)


def start_tree(name: str, manager: str, isolation: str, state_dir: str) -> int:
    """A supervisor in this worker with one manager; this process's pid."""
    import rr_actors as rr  # noqa: PLC0415

    setup = slots_setup if manager == "slots" else camera_setup
    sup = rr.Supervisor(
        [rr.ManagerSpec(manager, setup=setup, isolation=isolation)],  # type: ignore[arg-type]
        name=name,
        max_restarts=1000,  # (kills 1 s apart: never give up)
        period=1.0,
        state_dir=state_dir,
        network=hosts.KEPT["network"],
    )
    sup.start()
    hosts.KEPT["sup"] = sup
    return os.getpid()


def fill(resources: int) -> None:
    """The supervisor's consumer `load` holds `resources` resources at `slots`."""
    app = hosts.KEPT["app"] = hosts.KEPT["sup"].registrar("load")
    hosts.KEPT["held"] = [app.call("slots", "slot", n, timeout=30).id for n in range(resources)]


def observe(across: bool | None) -> str:
    """(Re)open this host's observer (`None`: close it); its URL."""
    old = hosts.KEPT.pop("observer", None)
    if old is not None:
        old.close()
    if across is None:
        return ""
    from rr_actors_lab.observe import observe as opened  # noqa: PLC0415 - in the namespace

    observer = opened(hosts.KEPT["sup"], across_hosts=across)
    hosts.KEPT["observer"] = observer
    return str(observer.url)


def sent_bytes() -> int:
    observer = hosts.KEPT.get("observer")
    share = getattr(observer, "_share", None)
    return 0 if share is None else int(share.sent_bytes)


def state_bytes() -> int:
    """Bytes of this host's whole shared state as JSON (what a page's host asks for once)."""
    import json  # noqa: PLC0415

    share = hosts.KEPT["observer"]._share
    return len(json.dumps(share.state(), separators=(",", ":")))


def churn_start(period: float) -> None:
    """Load and unload one more resource at `slots`, one change every `period` s."""
    app = hosts.KEPT["app"]
    stop = threading.Event()

    def run() -> None:
        n = 10**6
        while not stop.wait(period):
            query = app.call("slots", "slot", n, timeout=30)
            if stop.wait(period):
                app.unload(query.id)
                break
            app.unload(query.id)
            n += 1

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    hosts.KEPT["churn"] = (stop, thread)


def churn_stop() -> None:
    stop, thread = hosts.KEPT.pop("churn")
    stop.set()
    thread.join(30)


def sees(member: str, registrar: str, timeout: float) -> bool:
    """Whether this host's observer shows `member`'s catalog of `registrar` (bounded)."""
    deadline = time.monotonic() + timeout
    hub = hosts.KEPT["observer"]._hub
    pause = threading.Event()
    while hub.get(f"host/{member}/catalog/{registrar}") is None:
        if time.monotonic() > deadline:
            return False
        pause.wait(0.05)
    return True


def restarted_at(name: str, restarts: int) -> float:
    """When (wall clock) child `name` was restarted `restarts` times and runs (bounded)."""
    hosts.KEPT["sup"].wait_restarted(name, timeout=30, restarts=restarts)
    return time.time()


def manager_pid(name: str) -> int:
    return int(hosts.KEPT["sup"].child(name).pid)


def stop_tree() -> None:
    observe(None)
    sup = hosts.KEPT.pop("sup", None)
    if sup is not None:
        sup.stop()


# -- the benchmark's side ------------------------------------------------------------------------


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process `pid` (its threads) so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@contextlib.contextmanager
def lab(b_manager: str, b_isolation: str) -> Iterator[tuple[hosts.TwoHosts, Any, Any]]:
    with hosts.TwoHosts() as net:
        ca = pki.make_ca(net.directory, SYSTEM)
        members = ["alpha", "bravo"]

        def tls(name: str, address: str) -> dict[str, Any]:
            cert, key = pki.issue(net.directory, name, [address], ca=ca)
            return {"ca": str(ca[0]), "cert": str(cert), "key": str(key), "members": members}

        a, b = net.a.spawn(), net.b.spawn()
        listen = f"tls/{net.a.address}:{PORT}"
        a.call(hosts.rr_join, system=SYSTEM, listen=[listen], connect=[], lease=LEASE,
               tls=tls("alpha", net.a.address), timeout=30)  # fmt: skip
        b.call(hosts.rr_join, system=SYSTEM, listen=[], connect=[listen], lease=LEASE,
               tls=tls("bravo", net.b.address), timeout=30)  # fmt: skip
        try:
            yield net, a, b
        finally:
            for worker in (a, b):
                with contextlib.suppress(Exception):
                    worker.call(stop_tree, timeout=60)
                with contextlib.suppress(Exception):
                    worker.call(hosts.rr_stop, timeout=30)


def cost(resources: int, window: float) -> None:
    print(f"cost: {resources} resources at bravo, windows of {window:g} s")
    with lab("slots", "thread") as (net, a, b):
        b_pid = b.call(start_tree, "robot", "slots", "thread", str(net.directory / "b"), timeout=60)
        a_pid = a.call(
            start_tree, "operator", "cam", "thread", str(net.directory / "a"), timeout=60
        )
        b.call(fill, resources, timeout=300)
        rows = []
        for label, across in (("no observer", None), ("observer, this host only", False),
                              ("observer across hosts", True)):  # fmt: skip
            b.call(observe, across, timeout=60)
            a.call(observe, None if across is None else across, timeout=60)
            if across:
                assert a.call(sees, "bravo", "slots", 60.0, timeout=90), "alpha never saw bravo"
                size = b.call(state_bytes, timeout=30)
                print(f"  bravo's whole state: {size / 1024:.0f} KiB of JSON (asked once)")
            for load in ("idle", "2 changes/s"):
                if load != "idle":
                    b.call(churn_start, 0.5, timeout=10)
                threading.Event().wait(1.0)  # (settle: the first full state is not counted)
                cpu_b, cpu_a, sent = (
                    cpu_seconds(b_pid),
                    cpu_seconds(a_pid),
                    b.call(sent_bytes, timeout=10),
                )
                start = time.monotonic()
                threading.Event().wait(window)
                took = time.monotonic() - start
                cpu_b = (cpu_seconds(b_pid) - cpu_b) / took
                cpu_a = (cpu_seconds(a_pid) - cpu_a) / took
                rate = (b.call(sent_bytes, timeout=10) - sent) / took
                if load != "idle":
                    b.call(churn_stop, timeout=60)
                rows.append((label, load, cpu_b, cpu_a, rate))
                print(f"  {label:28} {load:12} bravo CPU {100 * cpu_b:5.1f}%  alpha CPU "
                      f"{100 * cpu_a:5.1f}%  bravo sent {rate / 1024:7.2f} KiB/s")  # fmt: skip
        _harness.print_table(
            "",
            ("observer", "load", "bravo CPU (%)", "alpha CPU (%)", "bravo sends (KiB/s)"),
            [
                (label, load, f"{100 * cpu_b:.1f}", f"{100 * cpu_a:.1f}", f"{rate / 1024:.2f}")
                for label, load, cpu_b, cpu_a, rate in rows
            ],
            right=2,
        )


def quantiles(samples: list[float]) -> str:
    p90 = _harness.percentile(samples, 0.9)
    return (f"median {1000 * _harness.median(samples):.0f} ms, p90 {1000 * p90:.0f} ms, "
            f"max {1000 * max(samples):.0f} ms (n={len(samples)})")  # fmt: skip


WATCH = """(marks) => {
  // the wall-clock time (Date.now, this machine's clock) at which each selector first matched
  window.__marks = {};
  const look = () => {
    for (const [name, selector] of Object.entries(marks))
      if (!(name in window.__marks) && document.querySelector(selector))
        window.__marks[name] = Date.now() / 1000;
  };
  if (window.__observer) window.__observer.disconnect();
  window.__observer = new MutationObserver(look);
  window.__observer.observe(document.body, {subtree: true, attributes: true, childList: true});
  look();
}"""
"""Installed before each kill or cut: the page's own record of when it changed (Playwright's
waits poll with a back-off of up to a second, too coarse for these figures)."""


def watch(page: Any, **marks: str) -> None:
    page.evaluate(WATCH, marks)


def mark(page: Any, name: str) -> float:
    return float(page.evaluate(f"window.__marks[{name!r}]"))


def latency(kills: int, cuts: int) -> None:
    import playwright.sync_api as playwright_api  # noqa: PLC0415 - the dev extra

    from tests.support.observing import CHROMIUM_ARGS, chromium  # noqa: PLC0415

    with lab("cam", "process") as (net, a, b), tempfile.TemporaryDirectory() as scratch:
        b.call(start_tree, "robot", "cam", "process", str(net.directory / "b"), timeout=60)
        a.call(start_tree, "operator", "station", "thread", str(net.directory / "a"), timeout=60)
        b.call(observe, True, timeout=60)
        url = a.call(observe, True, timeout=60)
        wrapper = Path(scratch) / "chromium-in-a"
        wrapper.write_text(
            f'#!/bin/sh\nexec nsenter --net=/run/netns/{net.a.namespace} {chromium()} "$@"\n'
        )
        wrapper.chmod(0o700)
        with playwright_api.sync_playwright() as playwright:
            context = playwright.chromium.launch_persistent_context(
                str(Path(scratch) / "profile"), executable_path=str(wrapper), headless=True,
                args=CHROMIUM_ARGS, viewport={"width": 1400, "height": 1000})  # fmt: skip
            page = context.new_page()
            page.goto(url)
            try:
                restarts(page, b, kills)
                if cuts:
                    cut_and_heal(page, net, cuts)
            finally:
                context.close()


CAM = '.host[data-member="bravo"] .node[data-child="cam"]'
BRAVO = '.host[data-member="bravo"]'
LINK = '[data-link="alpha|bravo"]'


def restarts(page: Any, b: Any, kills: int) -> None:
    cam = page.locator(CAM)
    cam.and_(page.locator('[data-state="running"]')).wait_for(timeout=60_000)
    shown, itself = [], []
    for n in range(kills):
        cam.and_(page.locator('[data-state="running"]')).wait_for(timeout=30_000)
        before = int(cam.get_attribute("data-restarts") or 0)
        pid = b.call(manager_pid, "cam", timeout=10)
        threading.Event().wait(1.0)  # (kills 1 s apart, as bench_observer.py)
        watch(page, restarted=f'{CAM}[data-restarts="{before + 1}"]')
        restarted = b.submit(restarted_at, "cam", before + 1)
        killed = time.time()
        os.kill(pid, signal.SIGKILL)
        cam.and_(page.locator(f'[data-restarts="{before + 1}"]')).wait_for(timeout=30_000)
        shown.append(mark(page, "restarted") - killed)
        itself.append(restarted.result(30) - killed)
        print(f"  kill {n + 1}: restarted on bravo {1000 * itself[-1]:.0f} ms, "
              f"on alpha's page {1000 * shown[-1]:.0f} ms")  # fmt: skip
    print(f"kill to bravo's supervisor seeing the restart: {quantiles(itself)}")
    print(f"kill to alpha's page showing it: {quantiles(shown)}")
    print(f"the page after bravo: {quantiles([s - i for s, i in zip(shown, itself, strict=True)])}")


def cut_and_heal(page: Any, net: hosts.TwoHosts, cuts: int) -> None:
    bravo, link = page.locator(BRAVO), page.locator(LINK)
    cut_link, cut_grey, heal = [], [], []
    for n in range(cuts):
        bravo.and_(page.locator('[data-state="live"]')).wait_for(timeout=60_000)
        link.and_(page.locator('[data-up="yes"]')).wait_for(timeout=60_000)
        threading.Event().wait(1.0)
        watch(page, cut=f'{LINK}[data-up="no"]', grey=f'{BRAVO}[data-state="stale"]')
        start = time.time()
        net.link_down()
        try:
            link.and_(page.locator('[data-up="no"]')).wait_for(timeout=30_000)
            bravo.and_(page.locator('[data-state="stale"]')).wait_for(timeout=30_000)
            cut_link.append(mark(page, "cut") - start)
            cut_grey.append(mark(page, "grey") - start)
            watch(page, live=f'{BRAVO}[data-state="live"]', up=f'{LINK}[data-up="yes"]')
        finally:
            net.link_up()
        up = time.time()
        bravo.and_(page.locator('[data-state="live"]')).wait_for(timeout=60_000)
        link.and_(page.locator('[data-up="yes"]')).wait_for(timeout=60_000)
        heal.append(max(mark(page, "live"), mark(page, "up")) - up)
        print(f"  cut {n + 1}: link cut shown {1000 * cut_link[-1]:.0f} ms, greyed "
              f"{1000 * cut_grey[-1]:.0f} ms; live {1000 * heal[-1]:.0f} ms after")  # fmt: skip
    print(f"cut to 'link cut' on the page: {quantiles(cut_link)}")
    print(f"cut to bravo's tree greyed: {quantiles(cut_grey)}")
    print(f"heal to bravo live again: {quantiles(heal)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--only", choices=("cost", "latency"))
    parser.add_argument("--resources", type=int, default=1000)
    parser.add_argument("--window", type=float, default=20.0)
    parser.add_argument("--kills", type=int, default=20)
    parser.add_argument("--cuts", type=int, default=20)
    args = parser.parse_args()
    reason = hosts.require_root()
    if reason is not None:
        print(f"nothing measured: {reason}")
        return
    print(_harness.header("the start"))
    if args.only in (None, "cost"):
        cost(args.resources, args.window)
    if args.only in (None, "latency"):
        latency(args.kills, args.cuts)
    print(_harness.header("the end"))


if __name__ == "__main__":
    main()
