"""Where an experiment's wall time goes: every phase of every run, and of every restart.

    python benchmarks/experiment_phases.py PLAN [--repeat 2] [--duration S] [--out DIR]

Runs `rr_actors_lab.experiments.run(PLAN)` in this process with timestamps around its phases:
here (the run process's start and wait, the sweep for leaked processes, the files, the
plots), in each run process (started through this file, `--child`, which wraps the
runner's steps before it runs `_child.main`) and in each manager (its setup is wrapped:
unpickling it, importing the plan's setup module, running it). Every timestamp is wall
clock (`time.time()`), appended as a JSON line to one trace file, so that they line up
with the events the run records (`events.jsonl`: a kill's `FaultInjected`, the
supervisor's `ChildExited`, the new incarnation's `CatalogRestored`, `ChildRestarted`).

It measures any tree that has `rr_actors_lab.experiments` (run it with `PYTHONPATH=TREE`);
a step a tree lacks is left out of its table. Not a timed test: it prints a table.
"""

from __future__ import annotations

import argparse
import atexit
import collections
import functools
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import _harness

_TRACE = "RR_PHASES_TRACE"
_T_MAIN = time.time()  # this file's first line: the interpreter is up, nothing imported


def _note(what: str, start: float, end: float, **extra: Any) -> None:
    path = os.environ.get(_TRACE)
    if not path:
        return
    line = json.dumps({"what": what, "start": start, "end": end, "pid": os.getpid(), **extra})
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
    try:
        os.write(fd, (line + "\n").encode())
    finally:
        os.close(fd)


def _timed(owner: Any, name: str, what: str | None = None) -> None:
    """Wrap `owner.name` so that each call notes its start and end as `what`."""
    original = getattr(owner, name, None)
    if original is None:
        return

    @functools.wraps(original)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        start = time.time()
        try:
            return original(*args, **kwargs)
        finally:
            _note(what or name, start, time.time())

    setattr(owner, name, wrapper)


# -- in each manager ------------------------------------------------------------------------


def phased_setup(inner: bytes, module: str, base_dir: str | None, registrar: Any) -> None:
    """A manager's setup, timed: unpickle the real one, import its module, run it."""
    entered = time.time()
    import cloudpickle  # noqa: PLC0415 - the manager has it (preloaded)

    setup = cloudpickle.loads(inner)
    unpickled = time.time()
    if base_dir is not None and base_dir not in sys.path:
        sys.path.insert(0, base_dir)
    __import__(module)
    imported = time.time()
    setup(registrar)
    name = registrar.name
    _note("manager: unpickle setup (imports)", entered, unpickled, manager=name)
    _note("manager: import the setup's module", unpickled, imported, manager=name)
    _note("manager: run the setup", imported, time.time(), manager=name)


# -- in each run process ----------------------------------------------------------------------


def _child(argv: list[str]) -> int:
    _note("run: interpreter start", float(os.environ.get("RR_PHASES_SPAWNED", _T_MAIN)), _T_MAIN)
    ended = [0.0]
    # registered first, so it runs last: threads joined and every other atexit done
    atexit.register(lambda: _note("run: exit (threads, atexit)", ended[0], time.time()))
    start = time.time()
    import cloudpickle  # noqa: PLC0415

    from rr_actors_lab.experiments import _child as child  # noqa: PLC0415
    from rr_actors_lab.experiments import runner  # noqa: PLC0415

    _note("run: imports", start, time.time())
    import rr_actors as rr  # noqa: PLC0415
    from rr_actors._core import queues  # noqa: PLC0415
    from rr_actors_lab.experiments import inject, workload  # noqa: PLC0415

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    original_spec = runner._child_spec

    def child_spec(child_plan: Any, base_dir: str | None) -> Any:
        spec = original_spec(child_plan, base_dir)
        if isinstance(spec, rr.ManagerSpec) and spec.setup is not None:
            module = child_plan.setup.partition(":")[0]
            inner = cloudpickle.dumps(spec.setup)
            setup = functools.partial(phased_setup, inner, module, base_dir)
            import dataclasses  # noqa: PLC0415

            spec = dataclasses.replace(spec, setup=setup)
        return spec

    runner._child_spec = child_spec
    for owner, name, what in (
        (runner, "build_tree", "run: build the tree"),
        (rr.Supervisor, "start", "run: start the tree"),
        (inject.Injector, "start", "run: t0 (injector started)"),
        (runner, "wait_all_serving", "run: wait until every manager serves"),
        (workload.Client, "stop", "run: a client unloads and stops"),
        (runner, "count_entries", "run: count catalog entries"),
        (rr.Supervisor, "flush_events", "run: flush events"),
        (rr.Supervisor, "stop", "run: stop the tree"),
        (queues.Subscription, "wait_delivered", "run: deliver queued events"),
        (runner._EventLog, "write", "run: write events.jsonl"),
        (runner, "_leaked", "run: look for leaked processes"),
        (runner, "_result", "run: metrics"),
        (runner, "_checked", "run: verdict (check.py)"),
    ):
        _timed(owner, name, what)
    original_stop = inject.Injector.stop
    stopped: set[int] = set()

    def injector_stop(self: Any, *args: Any, **kwargs: Any) -> Any:
        if id(self) not in stopped:  # the first stop ends the plan's duration
            stopped.add(id(self))
            _note("run: duration ends", time.time(), time.time())
        return original_stop(self, *args, **kwargs)

    inject.Injector.stop = injector_stop
    started = time.time()
    try:
        return child.main(argv)
    finally:
        ended[0] = time.time()
        _note("run: execute and write result", started, ended[0])


# -- here -------------------------------------------------------------------------------------


def _parent(args: argparse.Namespace) -> None:
    import subprocess  # noqa: PLC0415

    from rr_actors_lab.experiments import _procs, experiment  # noqa: PLC0415

    trace = Path(args.out) / "phases.jsonl"
    trace.unlink(missing_ok=True)
    os.environ[_TRACE] = str(trace)
    real_popen = subprocess.Popen

    class Popen(real_popen):  # type: ignore[misc,valid-type]
        def __init__(self, argv: list[str], *a: Any, **kw: Any) -> None:
            if argv[1:3] == ["-m", "rr_actors_lab.experiments._child"]:  # the run process
                argv = [argv[0], __file__, "--child", *argv[3:]]
                kw["env"] = {**kw.get("env", os.environ), "RR_PHASES_SPAWNED": repr(time.time())}
            super().__init__(argv, *a, **kw)

        def wait(self, timeout: float | None = None) -> int:
            code = super().wait(timeout)
            _note("experiment: run process seen exited", time.time(), time.time())
            return code

    experiment.subprocess.Popen = Popen  # type: ignore[misc]
    _timed(experiment._Experiment, "_one", "experiment: one run (all of it)")
    _timed(_procs, "wait_gone", "experiment: wait for the run's processes")
    _timed(_procs, "processes_with", "experiment: find the run's processes")
    _timed(experiment._Experiment, "_keep", "experiment: append the run's files")
    _timed(experiment._Experiment, "_plot", "experiment: plots")
    _timed(experiment._Experiment, "_collect", "experiment: read the result")
    try:
        from rr_actors_lab.experiments import plot  # noqa: PLC0415
    except ImportError:
        pass
    else:
        _timed(plot, "plot_recovery", "experiment: draw recovery.png")
        _timed(plot, "plot_timeline", "experiment: draw timeline.png")
    from rr_actors_lab.experiments import plans  # noqa: PLC0415

    plan = plans.find(args.plan) or args.plan
    started = time.time()
    experiment.run(
        plan, out=Path(args.out) / "out", repeat=args.repeat, duration=args.duration, force=True
    )
    _note("experiment: all", started, time.time())
    report(trace, Path(args.out) / "out" / "events.jsonl")


def _restarts(events_path: Path) -> list[dict[str, float]]:
    """Per restart after a kill: kill -> seen exited -> restored -> serving (seconds)."""
    rows = []
    by_run: dict[int, list[dict[str, Any]]] = collections.defaultdict(list)
    for line in events_path.read_text().splitlines():
        event = json.loads(line)
        by_run[event.get("run", 0)].append(event)
    for seen in by_run.values():
        seen.sort(key=lambda e: e.get("at") or 0.0)
        for exited in (e for e in seen if e["type"] == "ChildExited"):
            child, at = exited["child"], exited["at"]
            kill = max(
                (
                    e["at"]
                    for e in seen
                    if e["type"] == "FaultInjected"
                    and e.get("at")
                    and e["at"] <= at
                    and e.get("target") == child
                ),
                default=None,
            )
            restored = next(
                (
                    e
                    for e in seen
                    if e["type"] == "CatalogRestored" and e["registrar"] == child and e["at"] > at
                ),
                None,
            )
            back = next(
                (
                    e
                    for e in seen
                    if e["type"] == "ChildRestarted" and e["child"] == child and e["at"] > at
                ),
                None,
            )
            if back is None or restored is None or restored["at"] > back["at"]:
                continue
            rows.append(
                {
                    "kill to exit seen": at - kill if kill is not None and at - kill < 1 else None,
                    "exit seen to restored": restored["at"] - at,
                    "restored to serving": back["at"] - restored["at"],
                    "restart_s": back["restart_s"],
                    "child": child,
                    "serving": back["at"],
                }
            )
    return rows


def report(trace: Path, events_path: Path) -> None:
    """Print the phases (sum over runs, per run, count) and the restarts' split."""
    notes = [json.loads(line) for line in trace.read_text().splitlines()]
    sums: dict[str, list[float]] = collections.defaultdict(list)
    for note in notes:
        sums[note["what"]].append(note["end"] - note["start"])
    # the plan's duration: from t0 to its end, per run
    t0s = sorted(n["end"] for n in notes if n["what"] == "run: t0 (injector started)")
    ends = sorted(n["start"] for n in notes if n["what"] == "run: duration ends")
    sums["run: the plan's duration (t0 to its end)"] = [
        e - s for s, e in zip(t0s, ends, strict=False)
    ]
    total = sums.pop("experiment: all", [0.0])[0]
    rows = [
        (what, f"{sum(v):.2f}", len(v), f"{_harness.median(v) * 1e3:.1f}")
        for what, v in sorted(sums.items())
    ]
    rows.append(("experiment: all", f"{total:.2f}", "", ""))
    print(_harness.table(("phase", "sum s", "n", "median ms"), rows))
    rows = _restarts(events_path)
    if not rows:
        return
    print(f"\nrestarts: {len(rows)}")
    managers = [n for n in notes if n["what"].startswith("manager:")]
    for key in ("kill to exit seen", "exit seen to restored", "restored to serving", "restart_s"):
        values = [r[key] for r in rows if r[key] is not None]
        if values:
            print(
                f"  {key:40} median {_harness.median(values) * 1e3:8.1f} ms, "
                f"sum {sum(values):6.2f} s (n {len(values)})"
            )
    for what in sorted({n["what"] for n in managers}):
        values = [n["end"] - n["start"] for n in managers if n["what"] == what]
        print(
            f"  {what:40} median {_harness.median(values) * 1e3:8.1f} ms, "
            f"sum {sum(values):6.2f} s (n {len(values)}, starts included)"
        )


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        sys.exit(_child(sys.argv[2:]))
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("plan")
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--duration", type=float, default=None, help="seconds per run")
    parser.add_argument("--out", help="directory for the trace and the experiment's files")
    args = parser.parse_args()
    if args.out is None:
        args.out = tempfile.mkdtemp(prefix="experiment-phases-")
        print(f"(files in {args.out})")
    Path(args.out).mkdir(parents=True, exist_ok=True)
    _parent(args)


if __name__ == "__main__":
    main()
