"""Pools benchmark: many thread managers in a few OS processes (`SupervisorSpec(isolation=
"process")`), their memory, and a pool's kill to all its managers serving again.

A tree of P pools of S thread managers each (a state_dir: every manager keeps its catalog
in SQLite, `save_on_modify`) is started; each manager is given one resource by a consumer
registrar of this process. Printed: the time to start the tree; its memory (PSS, from
`/proc/<pid>/smaps_rollup`, Linux) summed over the pools' processes, this process (the
supervisor's, with its consumer) and the forkserver, and per manager.

Then, K times, one pool's process is SIGKILLed; the time runs from the kill until every one
of its S managers answered a call (restarted, catalog restored, serving). Beside it, in
the same run and alternated with it kill by kill, its floor: a process manager of the same
tree (one manager, one resource) SIGKILLed, until it answered a call.

Beside them, in the same run (`--compare N`, before the pools): the memory per manager of
N thread managers (this process's PSS with them, less without) and of N process managers
(their processes' PSS, summed), each with its catalog and one resource.

Target (issue 69 item 5): 1,000 managers (10 pools of 100) within 1 GiB of PSS in all.

Run: `flock /work/big.lock python benchmarks/bench_pools.py [--pools 10] [--size 100]
[--kills 3] [--compare 20]` (more than 300 managers: one such run at a time on a shared machine).
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import tempfile
import time

import _harness

import rr_actors as rr
from rr_actors._process.control import forker_pid
from rr_actors._process.manager import mp_context
from rr_actors.errors import UnknownRegistrarError


def setup(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("echo", load=lambda r: r, unload=lambda r, s: None)


def pss_kib(pid: int) -> int:
    return _harness.memory_kib(pid, "Pss") or 0


def forkserver_pid() -> int:
    """The pid of the process that forks the managers' processes (0: unknown)."""
    return forker_pid(mp_context()) or 0


def serve_all(app: rr.ResourceRegistrar, names: list[str]) -> None:
    """One call answered by each of `names` (each retried while it restarts)."""
    for name in names:
        deadline = time.monotonic() + 120.0
        while True:
            try:
                app.call(name, "echo", name, timeout=60.0)
                break
            except (rr.RegistrarUnavailableError, UnknownRegistrarError):
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.005)  # (a benchmark's retry, not a test's synchronisation)


def per_manager(count: int, isolation: str, state: str) -> float:
    """MiB of PSS per manager of a tree of `count` managers of `isolation` (a resource each)."""
    specs = [rr.ManagerSpec(f"{isolation}{n}", setup, isolation=isolation) for n in range(count)]  # type: ignore[arg-type]
    before = pss_kib(os.getpid())
    with rr.Supervisor(specs, state_dir=os.path.join(state, isolation)) as sup:
        app = sup.registrar(f"app-{isolation}")
        serve_all(app, [s.name for s in specs])
        if isolation == "thread":
            kib = pss_kib(os.getpid()) - before
        else:
            kib = sum(pss_kib(sup.child(s.name).pid or 0) for s in specs)
    return kib / 1024 / count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pools", type=int, default=10)
    parser.add_argument("--size", type=int, default=100, help="thread managers per pool")
    parser.add_argument("--kills", type=int, default=3)
    parser.add_argument("--compare", type=int, default=20, help="thread and process managers")
    args = parser.parse_args()  # (no forkserver before the tree: it preloads a pool's modules)
    pools = [
        rr.SupervisorSpec(
            f"pool{p}",
            tuple(rr.ManagerSpec(f"p{p}m{m}", setup) for m in range(args.size)),
            isolation="process",
            max_restarts=args.kills + 1,
        )
        for p in range(args.pools)
    ]
    floor = rr.ManagerSpec("solo", setup, isolation="process")
    with tempfile.TemporaryDirectory() as state:
        if args.compare:
            thread = per_manager(args.compare, "thread", state)
            process = per_manager(args.compare, "process", state)
            print(f"## PSS per manager, {args.compare} of each beside the pools")
            print()
            print(
                f"thread managers: {thread:.2f} MiB each; process managers: {process:.1f} MiB each"
            )
            print()
        sup = rr.Supervisor(
            [*pools, floor], state_dir=state, max_restarts=2 * args.kills + 2, period=3600.0
        )
        began = time.perf_counter()
        with sup:
            started = time.perf_counter() - began
            app = sup.registrar("bench-app")
            names = [m.name for pool in pools for m in pool.children]
            serve_all(app, [*names, "solo"])
            total = args.pools * args.size
            pool_kib = [pss_kib(sup.child(p.name).pid or 0) for p in pools]
            own, server = pss_kib(os.getpid()), pss_kib(forkserver_pid())
            all_kib = sum(pool_kib) + own + server
            print(f"## {args.pools} pools x {args.size} thread managers ({total} managers)")
            print()
            print(f"start (every manager serving): {started:.2f} s")
            print(
                f"PSS: pools {sum(pool_kib) / 1024:.0f} MiB (each {min(pool_kib) / 1024:.1f}-"
                f"{max(pool_kib) / 1024:.1f} MiB), supervisor's process {own / 1024:.0f} MiB, "
                f"forkserver {server / 1024:.0f} MiB; in all {all_kib / 1024:.0f} MiB = "
                f"{all_kib / 1024 / total:.2f} MiB per manager"
            )
            if args.kills:
                kills(sup, app, pools, args.kills)
    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


def kills(
    sup: rr.Supervisor, app: rr.ResourceRegistrar, pools: list[rr.SupervisorSpec], count: int
) -> None:
    """Kill to serving: a pool (all its managers) against the floor, alternated."""
    pool_times: list[float] = []
    solo_times: list[float] = []
    for k in range(count):  # alternated with the floor: both meet the same noise
        victim = pools[k % len(pools)]
        began = time.perf_counter()
        os.kill(sup.child(victim.name).pid or 0, signal.SIGKILL)
        sup.wait_restarted(victim.name, timeout=120.0)
        serve_all(app, [m.name for m in victim.children])
        pool_times.append((time.perf_counter() - began) * 1000)
        began = time.perf_counter()
        os.kill(sup.child("solo").pid or 0, signal.SIGKILL)
        sup.wait_restarted("solo", timeout=120.0)
        serve_all(app, ["solo"])
        solo_times.append((time.perf_counter() - began) * 1000)
    print()
    print("| kill to serving (ms) | median | min-max |")
    print("|---|---|---|")
    for label, times in (
        (f"a pool of {len(pools[0].children)}, all serving", pool_times),
        ("one process manager (floor)", solo_times),
    ):
        median, low, high = statistics.median(times), min(times), max(times)
        print(f"| {label} | {median:.0f} | {low:.0f}-{high:.0f} |")
    ratio = statistics.median(pool_times) / statistics.median(solo_times)
    print(f"\nratio pool / floor: {ratio:.1f}x")


if __name__ == "__main__":
    main()
