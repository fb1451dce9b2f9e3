"""Trees of N managers (issue 69): start, stop, a restart and each manager's cost, beside floors.

For each N (default 10, 50, 200, 1,000), each kind of manager (`process`, `thread`) and
with and without a fresh `state_dir` ("fresh": an empty directory of its own), a tree of
N managers (each with one server, as `bench_scale.py`'s) is measured in a Python of its
own, bounded by `--bound` seconds (plus `--bound-per-manager` per manager) and by
`--max-threads` threads in all (its processes' threads count against the machine's
`pid_max`, which other programs share); a tree past either is killed (its session) and
its row says which step it had not finished (`timeout (70 s) in stop`); whatever it
measured before is kept.

* start: `Supervisor.start()` (ordered start, every manager serving), then one call to
  each manager from one registrar of the tree (`start+calls`, from `start()` to the
  last answer);
* restart: one manager (the middle one) killed (a process manager SIGKILLed, a thread
  manager's actor crashed as by `rr_actors.testing.crash`) until a call answered by its
  next incarnation returned; meanwhile a thread calls the other managers in turn: p99 of
  those calls while it restarts, beside their p99 in the 0.3 s before the kill;
* cost per manager: threads and sockets of a manager process (the median of up to 20
  managers; a thread tree: what its process gained, divided by N), PSS (Linux,
  `/proc/<pid>/smaps_rollup`; a thread tree: the PSS its process gained, divided by N);
* stop: the app registrar's stop first (`app_stop_ms`: releasing the `app_ids` ids it
  holds, one at a time, newest first: rule 12), then `Supervisor.stop()` (`stop_ms`).

The floors, in the same run and alternated with the trees (each tree's run followed by
its floor's): for process managers `bench_scale.py`'s (N plain forkserver children
started in order, each saying "ready"; then their stop, the pipes closed and each joined;
the respawn floor: a plain child SIGKILLed and a new one started until it says "ready");
for thread managers N pykka actors started and asked once each, stopped, and one of
them stopped and started again and asked.

Run: `python benchmarks/bench_trees.py [--counts 10 50 200 1000] [--kinds process thread]
[--state none fresh] [--rounds 1] [--kills 3] [--bound 60] [--bound-per-manager 0.3]
[--plot docs/img/trees.png]`. Trees of 200 and more: `flock /work/big.lock` on the shared
machine (see CONTRIBUTING.md).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import _harness
from bench_scale import Floor, PykkaFanOut, Respawn, pss_kib

import rr_actors as rr
from rr_actors import testing
from rr_actors.testing import start_forkserver

HERE = Path(__file__).resolve()


def setup(registrar: rr.ResourceRegistrar) -> None:
    """Each manager's setup: one server (as `bench_scale.py`'s; defined here, so that it is
    pickled by value for a process manager, which cannot import a benchmark script)."""
    registrar.register_server("res", load=lambda r: r, unload=lambda r, s: None)


SAMPLED = 20
"""Manager processes whose threads, sockets and PSS are read (spread over the tree)."""


def emit(**figures: Any) -> None:
    """One line of a tree's run: figures as JSON (the parent keeps what came before a timeout)."""
    print(json.dumps(figures), flush=True)


def threads_sockets(pid: int) -> tuple[int, int]:
    """Threads and open sockets of process `pid` (Linux `/proc`)."""
    threads = len(os.listdir(f"/proc/{pid}/task"))
    sockets = 0
    for fd in os.listdir(f"/proc/{pid}/fd"):
        with contextlib.suppress(OSError):
            sockets += os.readlink(f"/proc/{pid}/fd/{fd}").startswith("socket:")
    return threads, sockets


def median_or_none(values: list[float]) -> float | None:
    """The median of `values`; `None` if there are none (`--kills 0`)."""
    return _harness.median(values) if values else None


def p99(values: list[float]) -> float | None:
    """The 0.99 quantile of `values` (the harness's nearest rank); `None` if there are none."""
    return _harness.percentile(values, 0.99) if values else None


class Caller:
    """A thread calling the tree's managers but one in turn; latencies in ms, timestamped."""

    def __init__(self, app: rr.ResourceRegistrar, names: list[str], timeout: float) -> None:
        self.app, self.names, self.timeout = app, names, timeout
        self.samples: list[tuple[float, float]] = []  # (when it began, ms)
        self.failed = 0
        self.done = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self) -> None:
        turn = 0
        while not self.done.is_set():
            name = self.names[turn % len(self.names)]
            turn += 1
            began = time.perf_counter()
            try:
                self.app.call(name, "res", f"other-{turn}", timeout=self.timeout)
            except rr.RrError:
                self.failed += 1
                continue
            self.samples.append((began, (time.perf_counter() - began) * 1000))

    def between(self, since: float, until: float) -> list[float]:
        return [ms for began, ms in self.samples if since <= began < until]

    def close(self) -> None:
        self.done.set()
        self.thread.join(self.timeout + 5)


def one_tree(
    count: int, kind: str, state: Path | None, kills: int, bound: float, heartbeat: float | None
) -> None:
    """Measure one tree (run in a Python of its own); print each step's figures as JSON."""
    start_forkserver()
    me = os.getpid()
    threads_before, sockets_before = threads_sockets(me)
    pss_before = pss_kib(me) or 0
    names = [f"m{n}" for n in range(count)]
    specs = [
        rr.ManagerSpec(n, setup, isolation=kind, start_timeout=bound, heartbeat=heartbeat)  # type: ignore[arg-type]
        for n in names
    ]
    sup = rr.Supervisor(
        specs, name=f"trees-{count}", max_restarts=1000, period=3600.0, state_dir=state
    )
    emit(step="start")
    began = time.perf_counter()
    sup.start()
    started = time.perf_counter()
    emit(start_ms=(started - began) * 1000, step="calls")
    app = sup.registrar(f"app-{count}")
    for name in names:
        app.call(name, "res", "first", timeout=bound)
    emit(calls_ms=(time.perf_counter() - started) * 1000, step="cost")
    if kind == "process":
        pids = [
            sup.child(names[i * count // min(count, SAMPLED)]).pid
            for i in range(min(count, SAMPLED))
        ]
        pairs = [threads_sockets(pid) for pid in pids if pid is not None]
        memory = [pss_kib(pid) for pid in pids if pid is not None]
        emit(
            threads=_harness.median(t for t, _ in pairs),
            sockets=_harness.median(s for _, s in pairs),
            pss_kib=_harness.median(m for m in memory if m is not None),
            step="restart",
        )
    else:
        threads, sockets = threads_sockets(me)
        emit(
            threads=(threads - threads_before) / count,
            sockets=(sockets - sockets_before) / count,
            pss_kib=((pss_kib(me) or 0) - pss_before) / count,
            step="restart",
        )
    victim = names[count // 2]
    others = [n for n in names if n != victim] or names
    caller = Caller(app, others, bound)
    restarts: list[float] = []
    during: list[float] = []
    quiet: list[float] = []
    for kill in range(kills):
        quiet_from = time.perf_counter()
        time.sleep(0.3)  # the caller's quiet window (and the last restart's spares settle)
        killed = time.perf_counter()
        if kind == "process":
            pid = sup.child(victim).pid
            assert pid is not None
            os.kill(pid, signal.SIGKILL)
        else:
            testing.crash(sup.run_in(victim, lambda r: r), timeout=bound)
        sup.wait_restarted(victim, timeout=bound)
        app.call(victim, "res", f"after-{kill}", timeout=bound)
        answered = time.perf_counter()
        restarts.append((answered - killed) * 1000)
        quiet.extend(caller.between(quiet_from, killed))
        during.extend(caller.between(killed, answered))
    caller.close()
    emit(
        restart_ms=median_or_none(restarts),
        p99_during_ms=p99(during),
        p99_quiet_ms=p99(quiet),
        failed_calls=caller.failed,
        step="stop",
    )
    stop_tree(sup, app, bound)


def stop_tree(sup: rr.Supervisor, app: rr.ResourceRegistrar, bound: float) -> None:
    """The app's stop first, timed apart: its releases (rule 12: one at a time, newest
    first) are the app's, not the tree's (`sup.stop()` would do them first otherwise)."""
    held = len(app.client_queries(timeout=bound))
    began = time.perf_counter()
    app.stop(timeout=bound)
    emit(app_stop_ms=(time.perf_counter() - began) * 1000, app_ids=held, step="stop")
    began = time.perf_counter()
    sup.stop()
    emit(stop_ms=(time.perf_counter() - began) * 1000, step="done")


WATCH = 0.5
"""Seconds between two looks at a tree's run (its threads, its time)."""


def session_threads(session: int) -> int:
    """Threads of every process of session `session` (a tree's run and its managers)."""
    total = 0
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            with contextlib.suppress(OSError, IndexError, ValueError):
                fields = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
                if int(fields[3]) == session:
                    total += int(fields[17])
    return total


def run_tree(
    count: int, kind: str, state: str, kills: int, bound: float, max_threads: int, heartbeat: str
) -> dict[str, Any]:
    """One tree's run in a Python of its own (a session of its own), killed with its
    managers after `bound` s or once they have more than `max_threads` threads in all
    (threads count against the machine's `pid_max`)."""
    scratch = tempfile.TemporaryDirectory()  # (here: a killed run's state_dir is removed too)
    where = str(Path(scratch.name) / "state") if state == "fresh" else "none"
    command = [sys.executable, str(HERE), "--one", str(count), kind, where, "--kills", str(kills)]
    command += ["--bound", str(bound), "--heartbeat", heartbeat]
    child = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    deadline = time.monotonic() + bound
    peak, stopped = 0, ""
    while True:
        try:
            out, err = child.communicate(timeout=WATCH)
            break
        except subprocess.TimeoutExpired:
            threads = session_threads(child.pid)
            peak = max(peak, threads)
            if threads > max_threads:
                stopped = f"stopped at {threads:,} threads (over {max_threads:,})"
            elif time.monotonic() > deadline:
                stopped = f"timeout ({bound:g} s)"
            if stopped:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(child.pid, signal.SIGKILL)
                out, err = child.communicate()
                break
    scratch.cleanup()
    figures: dict[str, Any] = {}
    for line in out.splitlines():
        with contextlib.suppress(ValueError):
            figures.update(json.loads(line))
    figures["peak_threads"] = peak
    figures["bound_s"] = bound
    if stopped and figures.get("step") == "done":
        figures["outcome"] = f"done ({stopped} in its exit)"
    elif stopped:
        figures["outcome"] = f"{stopped} in {figures.get('step', 'start')}"
    elif child.returncode != 0 or figures.get("step") != "done":
        last = figures.get("error") or (err.strip().splitlines() or ["?"])[-1][:80]
        figures["outcome"] = f"failed in {figures.get('step', 'start')}: {last}"
    else:
        figures["outcome"] = "done"
    if figures["outcome"] != "done":  # (why: the run's own words, its last 200 lines)
        print("\n".join(err.splitlines()[-200:]), file=sys.stderr, flush=True)
    return figures


class ThreadFloor:
    """The floor of a thread tree: pykka actors started, asked, stopped, one restarted."""

    def start_stop(self, count: int) -> tuple[float, float]:
        """ms to start `count` actors and ask each once; ms to stop them."""
        began = time.perf_counter()
        fan = PykkaFanOut(count)
        fan.fan_out()
        started = (time.perf_counter() - began) * 1000
        began = time.perf_counter()
        fan.close()
        return started, (time.perf_counter() - began) * 1000

    def restart(self, kills: int) -> list[float]:
        """ms each to stop an actor, start a new one and ask it once."""
        fan = PykkaFanOut(1)
        times = []
        for _ in range(kills):
            began = time.perf_counter()
            fan.refs[0].stop()
            fan.refs[0] = fan.refs[0].actor_class.start()
            fan.refs[0].ask("again", timeout=60)
            times.append((time.perf_counter() - began) * 1000)
        fan.close()
        return times


def bound_of(count: int, args: argparse.Namespace) -> float:
    return float(args.bound + args.bound_per_manager * count)


def measure(
    args: argparse.Namespace,
) -> tuple[
    dict[tuple[int, str, str], list[dict[str, Any]]], dict[tuple[int, str], list[dict[str, float]]]
]:
    """Every tree and its floor, alternated round by round."""
    start_forkserver()
    floor, respawn, threads = Floor(), Respawn(), ThreadFloor()
    floor.start(1)  # warm the floors' forkservers
    respawn.kill(1)
    trees: dict[tuple[int, str, str], list[dict[str, Any]]] = {}
    floors: dict[tuple[int, str], list[dict[str, float]]] = {}
    try:
        for _ in range(args.rounds):
            for count in args.counts:
                for kind in args.kinds:
                    for state in args.state:
                        bound = bound_of(count, args)
                        figures = run_tree(
                            count, kind, state, args.kills, bound, args.max_threads, args.heartbeat
                        )
                        trees.setdefault((count, kind, state), []).append(figures)
                        print(f"# {count} {kind} {state}: {figures}", file=sys.stderr, flush=True)
                        if kind == "process":
                            start_ms, pss, floor_stop_ms = floor.start(count)
                            plain = {
                                "start_ms": start_ms,
                                "stop_ms": floor_stop_ms,
                                "pss_kib": float(pss or 0),
                            }
                            plain["restart_ms"] = median_or_none(respawn.kill(args.kills))
                        else:
                            start_ms, stop_ms = threads.start_stop(count)
                            plain = {"start_ms": start_ms, "stop_ms": stop_ms}
                            plain["restart_ms"] = median_or_none(threads.restart(args.kills))
                        floors.setdefault((count, kind), []).append(plain)
    finally:
        floor.close()
        respawn.close()
    return trees, floors


def figure(run: dict[str, Any], key: str) -> float | None:
    """A run's `key`; a tree's "start_ms" is its start and the calls after it (if it got
    that far), a floor's only its start."""
    if key == "start_ms" and "outcome" in run:
        return run["start_ms"] + run["calls_ms"] if "calls_ms" in run else None
    return run.get(key)


def median_of(runs: list[dict[str, Any]], key: str) -> float | None:
    return median_or_none([value for value in (figure(r, key) for r in runs) if value is not None])


def show(value: float | None, digits: int = 0) -> str:
    return "-" if value is None else f"{value:,.{digits}f}"


def ratio(ours: float | None, floor: float | None) -> str:
    return "-" if ours is None or not floor else f"{ours / floor:.1f}x"


def outcome(runs: list[dict[str, Any]]) -> str:
    bad = [r["outcome"] for r in runs if not r["outcome"].startswith("done")]
    return "; ".join(sorted(set(bad))) if bad else f"{len(runs)} done"


Cell = Callable[[list[dict[str, Any]]], str]
"""A column of a step's table: a tree's runs -> its cell."""


def versus_floor(
    trees: dict[tuple[int, str, str], list[dict[str, Any]]],
    floors: dict[tuple[int, str], list[dict[str, float]]],
    step: tuple[str, str],
    key: str,
    digits: int = 0,
    extra: Sequence[tuple[str, Cell]] = (),
) -> None:
    """One step's table (`step`: its rows' name, its figure's heading): each tree's median
    of `key` beside its floor's and their ratio, the `extra` columns ((heading, cell)) before
    the ratio."""
    name, heading = step
    rows = []
    for (count, kind, state), runs in trees.items():
        ours, plain = median_of(runs, key), median_of(floors[(count, kind)], key)
        cells = [f"{name} {count} {kind} {state}", outcome(runs), show(ours, digits)]
        cells += [show(plain, digits), *(column(runs) for _, column in extra)]
        rows.append([*cells, ratio(ours, plain)])
    columns = ["tree", "runs", heading, "floor", *(h for h, _ in extra), "ratio"]
    _harness.print_table(f"{name} (ms, medians):", columns, rows, right=2)


def apps_stop(runs: list[dict[str, Any]]) -> str:
    """The app registrar's stop before the tree's (ms), and the ids it released."""
    return f"{show(median_of(runs, 'app_stop_ms'))} ({show(median_of(runs, 'app_ids'))})"


def restarting(runs: list[dict[str, Any]]) -> str:
    """The p99 of the other managers' calls while one restarts / before it was killed."""
    during, quiet = median_of(runs, "p99_during_ms"), median_of(runs, "p99_quiet_ms")
    return f"{show(during, 1)} / {show(quiet, 1)}"


def report(
    trees: dict[tuple[int, str, str], list[dict[str, Any]]],
    floors: dict[tuple[int, str], list[dict[str, float]]],
) -> None:
    print("## Trees of N managers vs their floors (medians in ms; alternated)")
    compact(trees, floors)
    versus_floor(trees, floors, ("start", "start+calls"), "start_ms")
    versus_floor(
        trees,
        floors,
        ("stop", "sup.stop()"),
        "stop_ms",
        extra=[("the app's stop before it (its ids)", apps_stop)],
    )
    versus_floor(
        trees,
        floors,
        ("restart", "kill to serving"),
        "restart_ms",
        1,
        [
            ("p99 of other calls: restarting / quiet", restarting),
            ("failed", lambda runs: str(sum(r.get("failed_calls", 0) for r in runs))),
        ],
    )
    rows = []
    for (count, kind, state), runs in trees.items():
        pss, plain = median_of(runs, "pss_kib"), median_of(floors[(count, kind)], "pss_kib")
        rows.append(
            (
                f"cost {count} {kind} {state}",
                show(median_of(runs, "threads"), 1),
                show(median_of(runs, "sockets"), 1),
                show(None if pss is None else pss / 1024, 2),
                show(None if plain is None else plain / 1024, 2),
                show(max(r["peak_threads"] for r in runs)),
            )
        )
    _harness.print_table(
        "cost per manager (medians):",
        [
            "tree",
            "threads per manager",
            "sockets per manager",
            "PSS per manager (MiB)",
            "plain child's PSS (MiB)",
            "threads of the tree, peak",
        ],
        rows,
    )
    print(f"\n{_harness.header('at the end')}")


def cell(runs: list[dict[str, Any]] | None, key: str, scale: float = 1.0, digits: int = 0) -> str:
    """One tree's figure for the compact table: its median, or why there is none."""
    if not runs:
        return "-"
    value = median_of(runs, key)
    if value is not None:
        return show(value * scale, digits)
    why = runs[0]["outcome"]
    if why.startswith("done"):  # (a figure it had no step for: `--kills 0`)
        return "-"
    if why.startswith("timeout"):
        return f"> {runs[0].get('bound_s', 0):g} s"
    return "thread cap" if why.startswith("stopped") else "failed"


def compact(
    trees: dict[tuple[int, str, str], list[dict[str, Any]]],
    floors: dict[tuple[int, str], list[dict[str, float]]],
) -> None:
    """The same figures, one row per N and kind: state_dir none / fresh (floor)."""
    rows = []
    for count, kind in sorted({(c, k) for c, k, _ in trees}):
        none, fresh = trees.get((count, kind, "none")), trees.get((count, kind, "fresh"))
        plain = floors[(count, kind)]
        row = [f"{count:,}, {kind}"]
        row += [
            f"{cell(none, key)} / {cell(fresh, key)} ({show(median_of(plain, key))})"
            for key in ("start_ms", "stop_ms", "restart_ms")
        ]
        row.append(f"{cell(none, 'p99_during_ms')} / {cell(fresh, 'p99_during_ms')}")
        row.append(f"{cell(none, 'threads', digits=1)} / {cell(fresh, 'threads', digits=1)}")
        row.append(f"{cell(none, 'pss_kib', 1 / 1024, 2)} / {cell(fresh, 'pss_kib', 1 / 1024, 2)}")
        rows.append(row)
    _harness.print_table(
        _harness.header("state_dir none / fresh (the floor in brackets)"),
        [
            "N, kind",
            "start + a call each (ms)",
            "stop (ms)",
            "kill to serving (ms)",
            "p99 of the others' calls, restarting (ms)",
            "threads per manager",
            "PSS per manager (MiB)",
        ],
        rows,
    )


def plot(
    trees: dict[tuple[int, str, str], list[dict[str, Any]]],
    floors: dict[tuple[int, str], list[dict[str, float]]],
    path: Path,
) -> None:
    """Curves vs N (log-log) of start+calls, stop and kill to serving, each floor dashed."""
    import matplotlib  # noqa: PLC0415 - only with --plot

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    figure, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    steps = [("start+calls", "start_ms"), ("stop", "stop_ms"), ("kill to serving", "restart_ms")]
    configs = sorted({(kind, state) for _, kind, state in trees})
    for axis, (title, key) in zip(axes, steps, strict=True):
        for number, (kind, state) in enumerate(configs):
            counts, values, unfinished = [], [], []
            for (count, k, s), runs in sorted(trees.items()):
                if (k, s) != (kind, state):
                    continue
                value = median_of(runs, key)
                if value is not None:
                    counts.append(count)
                    values.append(value)
                elif runs and "bound_s" in runs[0]:  # (it did not get there: at its bound)
                    unfinished.append((count, runs[0]["bound_s"] * 1000))
            (line,) = axis.plot(counts, values, marker="o", label=f"{kind}, state_dir {state}")
            if unfinished:
                axis.plot(  # (side by side: several stop at the same bound)
                    [c * (1 + 0.06 * number) for c, _ in unfinished],
                    [b for _, b in unfinished],
                    linestyle="none",
                    marker="^",
                    markerfacecolor="none",
                    color=line.get_color(),
                )
        for kind in sorted({kind for _, kind in floors}):
            points = sorted(
                (c, median_of(runs, key)) for (c, k), runs in floors.items() if k == kind
            )
            axis.plot(
                [c for c, _ in points],
                [v for _, v in points],
                linestyle="--",
                marker="x",
                label=f"floor ({'forkserver children' if kind == 'process' else 'pykka actors'})",
            )
        axis.set_xscale("log")
        axis.set_yscale("log")
        axis.set_xticks(sorted({count for count, _, _ in trees}))
        axis.set_xticklabels([f"{count:,}" for count in sorted({count for count, _, _ in trees})])
        axis.minorticks_off()
        axis.set_xlabel("managers (N)")
        axis.set_ylabel("ms (median)")
        axis.set_title(title)
        axis.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7, title="(open triangle: not done within its bound)", title_fontsize=7)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=90)


def main() -> None:
    parser = _harness.options(__doc__, rounds=1)
    parser.add_argument("--counts", type=int, nargs="+", default=[10, 50, 200, 1000])
    parser.add_argument(
        "--kinds", nargs="+", choices=["process", "thread"], default=["process", "thread"]
    )
    parser.add_argument("--state", nargs="+", choices=["none", "fresh"], default=["none", "fresh"])
    parser.add_argument("--kills", type=int, default=3, help="kills per tree (restart)")
    parser.add_argument("--bound", type=float, default=60.0, help="seconds a tree's run may take")
    parser.add_argument(
        "--bound-per-manager", type=float, default=0.3, help="... plus this per manager"
    )
    parser.add_argument(
        "--max-threads",
        type=int,
        default=8000,
        help="a tree whose processes have more threads in all is stopped (pid_max is shared)",
    )
    parser.add_argument(
        "--heartbeat",
        default="0.25",
        help="seconds between a process manager's pings (ManagerSpec.heartbeat; 'off': None)",
    )
    parser.add_argument("--save", type=Path, help="also write the figures to this JSON file")
    parser.add_argument(
        "--load", type=Path, nargs="+", help="measure nothing: report (and plot) saved figures"
    )
    parser.add_argument("--plot", type=Path, help="write the curves to this PNG")
    parser.add_argument("--one", nargs=3, metavar=("N", "KIND", "STATE"), help=argparse.SUPPRESS)
    args = _harness.parse(parser, None)
    if args.one:
        state = None if args.one[2] == "none" else Path(args.one[2])
        heartbeat = None if args.heartbeat == "off" else float(args.heartbeat)
        try:
            one_tree(int(args.one[0]), args.one[1], state, args.kills, args.bound, heartbeat)
        except BaseException as exc:  # (its line, not the last one the exit's stop logs)
            emit(error=f"{type(exc).__name__}: {exc}".splitlines()[0][:200])
            raise
        return
    if args.load:
        trees, floors = {}, {}
        for path in args.load:
            saved = json.loads(path.read_text())
            trees.update({(t["count"], t["kind"], t["state"]): t["runs"] for t in saved["trees"]})
            floors.update({(f["count"], f["kind"]): f["runs"] for f in saved["floors"]})
            print(f"(from {path}: {saved['load']})")
    else:
        trees, floors = measure(args)
    if args.save:
        saved = {
            "trees": [
                {"count": c, "kind": k, "state": s, "runs": r} for (c, k, s), r in trees.items()
            ],
            "floors": [{"count": c, "kind": k, "runs": r} for (c, k), r in floors.items()],
            "load": f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
            f"{_harness.header(_harness.commit())}",
        }
        args.save.write_text(json.dumps(saved, indent=1))
    report(dict(sorted(trees.items())), floors)
    if args.plot:
        plot(trees, floors, args.plot)
        print(f"plot: {args.plot}")


if __name__ == "__main__":
    main()
