"""`run(plan)`: every run of an experiment in a fresh run process, and what they leave in `out`.

run(plan) ── validate everything (plan, out, platform, --observe) ── nothing started yet
   for repeat r, for each compared value v (interleaved: slow periods spread over all):
      run process (python -m ..._child, RR_ACTORS_EXPERIMENT=<token> in its env)
        ── runner.execute ──► result.pickle, events.jsonl
      the run's processes still alive: leaks (killed)
      out/: events.jsonl, faults.csv appended; runs.csv rewritten (union of columns)
   plots (matplotlib, imported on a thread meanwhile): recovery.png, timeline.png
Ctrl-C (or SIGTERM, SIGHUP): the run process is told to stop, every process of the run
        is killed, the finished runs stay written and plotted, the work directory goes.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import logging
import os
import pickle
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import rr_actors as rr
from rr_actors.errors import ConfigError, RrError
from rr_actors_lab.experiments import _procs
from rr_actors_lab.experiments._netns import cannot_make_hosts
from rr_actors_lab.experiments.plan import SIMULATION_KINDS, Plan, PlanError
from rr_actors_lab.experiments.reading import load_plan
from rr_actors_lab.experiments.results import Results, RunResult, show_value
from rr_actors_lab.experiments.runner import RunSpec
from rr_actors_lab.observe import require_extra

__all__ = [
    "OUTPUT_FILES",
    "ExperimentError",
    "ExperimentInterruptedError",
    "Progress",
    "handling_signals",
    "prepare_out",
    "run",
    "unsupported_platform",
]

logger = logging.getLogger("rr_actors.experiments")

OUTPUT_FILES = (
    "events.jsonl",
    "runs.csv",
    "faults.csv",
    "recovery.png",
    "timeline.png",
    "plan.toml",
)
"""The files an experiment writes in its output directory (`--force` replaces these)."""

ONLY_SIMULATED_WHY = {
    "kill_program": ": a real run's program is the run process itself, which records the "
    "run (its tree, its clients and its events): killed, the run would end with it",
}
"""Why a fault kind only the simulation injects is not run for real, where it is not the
simulation's reach alone (a `PlanError`'s tail)."""

STOP_TIMEOUT = 20.0
"""Seconds an interrupted run process gets to stop its tree before it is killed."""

SWEEP_GRACE = 3.0
"""Seconds the processes of a finished run get to exit before they count as leaked."""


class ExperimentError(RrError):
    """A run process failed (a bug, or a setup that crashed it; its stderr is quoted), or
    the output directory could not be written (a full disk: its files still agree)."""


class ExperimentInterruptedError(KeyboardInterrupt):
    """The experiment was interrupted (Ctrl-C); every process it started was stopped.

    A `KeyboardInterrupt`, not an `RrError`: the user stopped it, nothing failed, and an
    `except Exception` around `run` must not swallow it. Catch it by name for the runs.

    Attributes:
        results: the runs that finished before the interruption (also written to `out`).
        signum: the signal: `SIGINT` (Ctrl-C), `SIGTERM` or `SIGHUP` (its terminal hung up).
    """

    def __init__(self, results: Results, signum: int = signal.SIGINT) -> None:
        super().__init__(f"interrupted after {len(results.runs)} finished run(s)")
        self.results = results
        self.signum = signum


class _Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised in the main thread: stopped as a Ctrl-C is (nothing left
    behind). `signum` is the signal."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


_STOPPING = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))
"""The signals that stop an experiment as a Ctrl-C does (no SIGHUP on Windows)."""


@dataclasses.dataclass(frozen=True)
class Progress:
    """Where an experiment is (given to `run`'s `progress` callback about 10 times a second).

    Attributes:
        run: the number of the run under way (1, 2, ...).
        runs: how many runs the experiment has.
        setting: the compared setting (`""` without `compare`).
        value: the value of this run.
        seed: the seed of this run.
        elapsed_s: seconds since this run's process started.
        duration_s: the plan's duration.
        finished: the result, once the run has finished (then `elapsed_s` stops).
    """

    run: int
    runs: int
    setting: str
    value: Any
    seed: int
    elapsed_s: float
    duration_s: float
    finished: RunResult | None = None


def unsupported_platform() -> str | None:
    """Why experiments cannot run here, or `None` if they can (they need Linux: pidfds, /proc)."""
    if hasattr(os, "pidfd_open") and Path("/proc/self/environ").exists():
        return None
    return f"experiments need Linux (pidfds and /proc); this is {sys.platform}"


def prepare_out(path: Path, *, force: bool, what: str = "out") -> Path:
    """Make `path` ready for an experiment's files, or refuse before anything starts.

    Args:
        path: the output directory (created if missing).
        force: replace the files an experiment writes (`OUTPUT_FILES`) in a non-empty `path`.
        what: how error messages name it (`"--out"` on the command line).

    Raises:
        ConfigError: `path` is a file, cannot be written, or is not empty without `force`.
    """
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{what} {str(path)!r} is a file, not a directory")
    if path.is_dir() and any(path.iterdir()) and not force:
        raise ConfigError(
            f"{what} {str(path)!r} exists and is not empty; choose another directory, or "
            "force it (--force, force=True) to replace the experiment files in it"
        )
    try:
        path.mkdir(parents=True, exist_ok=True)
        for name in OUTPUT_FILES:
            (path / name).unlink(missing_ok=True)
        with tempfile.NamedTemporaryFile(dir=path, prefix=".rr-actors-probe-"):
            pass
    except OSError as exc:
        cause = exc.strerror or type(exc).__name__
        raise ConfigError(f"{what} {str(path)!r}: cannot write there ({cause})") from exc
    return path


def _runs(plan: Plan) -> Iterator[tuple[int, int, Any, Plan, int]]:
    """`(run, repeat, value, plan, seed)` in the order they run: values interleaved."""
    number = 0
    for repeat in range(1, plan.repeat + 1):
        for value, variant in plan.variants:
            number += 1
            yield number, repeat, value, variant, plan.seed + repeat - 1


def run(
    plan: Plan | str | os.PathLike[str],
    *,
    out: str | os.PathLike[str] | None = None,
    repeat: int | None = None,
    seed: int | None = None,
    duration: float | None = None,
    force: bool = False,
    observe: bool = False,
    record_events: bool = True,
    progress: Callable[[Progress], None] | None = None,
    on_observe: Callable[[int, str], None] | None = None,
    trace: bool = False,
) -> Results:
    """Run every run of an experiment, each in a fresh run process; return the results.

    Repeat `r` of every compared value uses the seed `seed + r - 1` (values in turn within a
    repeat), so compared values meet the same fault schedule. Everything is validated before
    the first run starts.

    Args:
        plan: a `Plan`, or the path of a plan file.
        out: directory for `events.jsonl`, `runs.csv`, `faults.csv`, `recovery.png`,
            `timeline.png` and `plan.toml`; `None`: write nothing.
        repeat: runs per compared value instead of the plan's `repeat`.
        seed: the seed of the first repeat instead of the plan's `seed`.
        duration: seconds per run instead of the plan's (later faults are dropped).
        force: replace the experiment files in a non-empty `out`.
        observe: serve the live observer page of each run (`Supervisor.observe`).
        record_events: subscribe to the tree (every metric from events needs it); off only
            to measure its cost.
        progress: called with a `Progress` about 10 times a second (on this thread).
        on_observe: called with `(run, url)` when a run's observer page is up.
        trace: make OpenTelemetry spans of each run's tree (`rr_actors_lab.otel.Exporting`, in
            the run process; the `OTEL_*` environment variables say where they go).

    Returns:
        The results of every run.

    Raises:
        PlanError: the plan is invalid (names the file, line and key), or has a fault
            kind that only a simulation injects.
        ConfigError: an override is out of range, `out` is not usable (or not empty
            without `force`), this platform cannot run experiments (or `[hosts]` without
            root), or the extra `observe` or `trace` need (or an `OTEL_TRACES_EXPORTER`
            exporter) is not installed.
        ExperimentError: a run process failed; the runs finished before it are kept.
        ExperimentInterruptedError: Ctrl-C; every process of the experiment was stopped,
            the runs finished so far are kept (its `results`).
    """
    if not isinstance(plan, Plan):
        plan = load_plan(plan)
    plan = plan.with_changes(repeat=repeat, seed=seed, duration=duration)
    for index, fault in enumerate(plan.faults):
        if fault.kind in SIMULATION_KINDS:
            raise PlanError(
                plan.source or "<plan>",
                0,
                f"faults[{index}].kind",
                f"{fault.kind!r} is only on the simulation (rr-actors experiment --simulate)"
                + ONLY_SIMULATED_WHY.get(fault.kind, ""),
            )
    reason = unsupported_platform()
    if reason is None and any(p.hosts is not None for _, p in plan.variants):
        reason = cannot_make_hosts()
    if reason is not None:
        raise ConfigError(reason)
    if observe:
        require_extra()
    if trace:  # (checked here, before any run: its provider is the run process's)
        from rr_actors_lab import otel  # noqa: PLC0415 - only tracing needs it

        otel.provider_from_environment().shutdown()
    out_path = prepare_out(Path(out), force=force) if out is not None else None
    if out_path is not None and plan.source is not None:
        try:
            shutil.copyfile(plan.source, out_path / "plan.toml")
        except OSError as exc:
            (out_path / "plan.toml").unlink(missing_ok=True)
            raise ExperimentError(f"cannot write to {out_path}/ ({exc.strerror})") from exc
    return _Experiment(
        plan, out_path, record_events, observe, progress, on_observe, trace=trace
    ).run()


class _Experiment:
    """The loop over the runs, with the files it appends to."""

    def __init__(
        self,
        plan: Plan,
        out: Path | None,
        record_events: bool,
        observe: bool,
        progress: Callable[[Progress], None] | None,
        on_observe: Callable[[int, str], None] | None,
        *,
        trace: bool = False,
    ) -> None:
        self.plan = plan
        self.trace = trace
        self.out = out
        self.record_events = record_events
        self.observe = observe
        self.progress = progress or (lambda _: None)
        self.on_observe = on_observe or (lambda _run, _url: None)
        self.finished: list[RunResult] = []
        self.current: _Current | None = None  # the run under way, from before its start
        self.total = plan.repeat * len(plan.variants)

    def run(self) -> Results:
        if self.out is not None:
            _import_plot_soon()
        work: Path | None = None
        try:
            with _terminating_as_interrupt():
                work = Path(tempfile.mkdtemp(prefix="rr-experiment-"))
                self._all(work)
        except KeyboardInterrupt as exc:
            with _ignoring_signals():  # a second Ctrl-C must not cut the cleanup or plots short
                self._interrupted()
                results = self._results(interrupted=True)
                self._plot(results)
            signum = exc.signum if isinstance(exc, _Terminated) else signal.SIGINT
            raise ExperimentInterruptedError(results, signum) from None
        except ExperimentError:
            self._plot(self._results(interrupted=False))  # what finished before it
            raise
        finally:
            if work is not None:
                with _ignoring_signals():  # (no longer `_Terminated`: it would cut this short)
                    shutil.rmtree(work, ignore_errors=True)
        results = self._results(interrupted=False)
        self._plot(results)
        return results

    def _all(self, work: Path) -> None:
        """Every run, in order, each in its own directory under `work`."""
        for number, repeat, value, variant, seed in _runs(self.plan):
            spec = RunSpec(
                plan=variant,
                setting=self.plan.setting_label(),
                value=value,
                run=number,
                repeat=repeat,
                seed=seed,
                record_events=self.record_events,
                observe=self.observe,
                trace=self.trace,
                token=f"{os.getpid()}-{uuid.uuid4().hex[:12]}",
            )
            result = self._one(spec, work / f"run-{number}")
            self.progress(self._progress(spec, result.duration_s, result))

    def _interrupted(self) -> None:
        """After a Ctrl-C: stop the run under way, kill its processes (by token), keep it if it
        ended."""
        current = self.current
        if current is None:
            return
        if current.process is not None:
            _stop(current.process)
        leftover = _procs.processes_with(current.token)
        _procs.kill(leftover)
        if current.process is not None and current.process.returncode == 0 and not current.kept:
            with contextlib.suppress(ExperimentError, OSError, pickle.UnpicklingError):
                self._keep(current, self._collect(current, 0, len(leftover)))
        self.current = None

    def _keep(self, current: _Current, result: RunResult) -> None:
        """A finished run: into the results and the output files (all of them, or none)."""
        self.finished.append(result)
        try:
            self._write(result, current.run_dir)
        except OSError as exc:
            self.finished.pop()
            raise ExperimentError(
                f"cannot write to {self.out}/ ({exc.strerror or exc}): run {result.run} was "
                f"not added; the files hold the {len(self.finished)} run(s) before it"
            ) from exc
        current.kept = True

    def _results(self, *, interrupted: bool) -> Results:
        return Results(self.plan, tuple(self.finished), self.out, interrupted)

    def _progress(self, spec: RunSpec, elapsed: float, result: RunResult | None) -> Progress:
        return Progress(
            run=spec.run,
            runs=self.total,
            setting=self.plan.setting_label(),
            value=spec.value,
            seed=spec.seed,
            elapsed_s=elapsed,
            duration_s=spec.plan.duration,
            finished=result,
        )

    # -- one run process --------------------------------------------------------------------

    def _one(self, spec: RunSpec, run_dir: Path) -> RunResult:
        current = self.current = _Current(spec, run_dir)
        run_dir.mkdir(parents=True)
        (run_dir / "spec.pickle").write_bytes(pickle.dumps(spec))
        env = {**os.environ, _procs.TOKEN_VARIABLE: spec.token}
        # The run process imports this very rr_actors, installed or not.
        package_root = str(Path(rr.__file__).resolve().parent.parent)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [package_root, env.get("PYTHONPATH")]))
        started = time.monotonic()
        argv = [
            sys.executable,
            "-m",
            "rr_actors_lab.experiments._child",
            str(run_dir),
            str(os.getpid()),
        ]
        with (run_dir / "stderr.txt").open("wb") as stderr:
            process = current.process = subprocess.Popen(  # noqa: S603 - our own module
                argv,
                env=env,
                stdout=subprocess.PIPE,
                stderr=stderr,
                start_new_session=True,  # Ctrl-C is ours to handle: we stop it cleanly
            )
        reader = threading.Thread(
            target=self._read_stdout, args=(spec.run, process), name="rr-run-out", daemon=True
        )
        reader.start()
        while True:
            try:
                code = process.wait(timeout=0.1)
                break
            except subprocess.TimeoutExpired:
                self.progress(self._progress(spec, time.monotonic() - started, None))
        reader.join(5.0)
        if not reader.is_alive() and process.stdout is not None:
            process.stdout.close()
        leftover = _procs.wait_gone(_procs.processes_with(spec.token), SWEEP_GRACE)
        _procs.kill(leftover)
        result = self._collect(current, code, len(leftover))
        self._keep(current, result)
        self.current = None
        return result

    def _collect(self, current: _Current, code: int, leaked: int) -> RunResult:
        """The result a run process left, with `leaked` more leaked processes."""
        spec, run_dir = current.spec, current.run_dir
        result_file = run_dir / "result.pickle"
        if code != 0 or not result_file.exists():
            tail = (run_dir / "stderr.txt").read_text(errors="replace")[-3000:]
            raise ExperimentError(f"run {spec.run} failed (exit code {code}):\n{tail}")
        result: RunResult = pickle.loads(result_file.read_bytes())
        if leaked:
            result = dataclasses.replace(result, leaked_processes=result.leaked_processes + leaked)
        return result

    def _read_stdout(self, run_number: int, process: subprocess.Popen[bytes]) -> None:
        assert process.stdout is not None
        import json  # noqa: PLC0415

        for raw in process.stdout:
            with contextlib.suppress(ValueError, TypeError):
                message = json.loads(raw)
                if isinstance(message, dict) and "observe" in message:
                    self.on_observe(run_number, str(message["observe"]))

    # -- files ----------------------------------------------------------------------------

    def _write(self, result: RunResult, run_dir: Path) -> None:
        """Add a run to the files; if a write fails, cut them back so they hold the same runs."""
        if self.out is None:
            return
        appended = [self.out / "events.jsonl", self.out / "faults.csv"]
        sizes = [path.stat().st_size if path.exists() else None for path in appended]
        try:
            with (
                (run_dir / "events.jsonl").open("rb") as source,
                appended[0].open("ab") as target,
            ):
                shutil.copyfileobj(source, target)
            _append_csv(appended[1], fault_rows(result))
            _write_csv(self.out / "runs.csv", [run.row() for run in self.finished])
        except OSError:
            for path, size in zip(appended, sizes, strict=True):
                with contextlib.suppress(OSError):  # cutting a file back needs no space
                    if size is None:
                        path.unlink(missing_ok=True)
                    else:
                        os.truncate(path, size)
            raise

    def _plot(self, results: Results) -> None:
        if self.out is None or not results.runs:
            return
        try:
            from rr_actors_lab.experiments import plot  # noqa: PLC0415
        except ImportError:
            logger.warning("plots not drawn: matplotlib is not installed")
            return
        for draw, name in (
            (plot.plot_recovery, "recovery.png"),
            (plot.plot_timeline, "timeline.png"),
        ):
            try:
                draw(results, self.out / name)
            except OSError as exc:  # a full disk: no half-written figure
                (self.out / name).unlink(missing_ok=True)
                logger.warning("%s not drawn: %s", name, exc.strerror or exc)


def _import_plot_soon() -> None:
    """Import the plot module (matplotlib: 1-3 s) on a thread of its own while the runs go."""

    def load() -> None:
        with contextlib.suppress(ImportError):
            from rr_actors_lab.experiments import plot  # noqa: F401, PLC0415

    threading.Thread(target=load, name="rr-import-plot", daemon=True).start()


@dataclasses.dataclass
class _Current:
    """The run under way: what `_interrupted` needs to stop it and to keep it if it ended."""

    spec: RunSpec
    run_dir: Path
    process: subprocess.Popen[bytes] | None = None  # None until it is started
    kept: bool = False  # its result is in `finished` and the files

    @property
    def token(self) -> str:
        """The value of `RR_ACTORS_EXPERIMENT` that marks the run's processes."""
        return self.spec.token


def fault_rows(result: RunResult) -> list[dict[str, Any]]:
    """The faults of a run as rows of `faults.csv`."""
    rows = []
    for fault in result.faults:
        late = fault.late_s
        rows.append(
            {
                "run": result.run,
                "setting": result.setting,
                "value": "" if result.value is None else show_value(result.value),
                "seed": result.seed,
                "fault": fault.fault,
                "n": fault.n,
                "kind": fault.kind,
                "target": fault.target or "",
                "scheduled_s": _blank(fault.scheduled_s),
                "injected_s": _blank(fault.injected_s),
                "late_ms": "" if late is None else round(late * 1e3, 3),
                "skipped": fault.skipped,
                "recovery_s": _blank(fault.recovery_s),
                **(
                    {"fail_s": _blank(fault.fail_s), "heal_s": _blank(fault.heal_s)}
                    if result.hosts
                    else {}
                ),
                "detail": fault.detail,
            }
        )
    return rows


def _blank(value: float | None) -> float | str:
    return "" if value is None else round(value, 6)


def _write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    """Write `path` anew: every row under the union of their columns (a new one after its left
    neighbour)."""
    columns: list[str] = []
    for row in rows:
        keys = list(row)
        for index, key in enumerate(keys):
            if key not in columns:
                after = next((k for k in keys[index + 1 :] if k in columns), None)
                columns.insert(columns.index(after) if after else len(columns), key)
    partial = path.with_name(path.name + ".tmp")
    try:
        with partial.open("w", newline="", encoding="utf-8") as file:
            writer = csv.DictWriter(file, fieldnames=columns, restval="")
            writer.writeheader()
            writer.writerows(rows)
    except OSError:
        partial.unlink(missing_ok=True)
        raise
    partial.replace(path)


def _append_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    if not rows:
        return
    new = not path.exists()
    with path.open("a", newline="", encoding="utf-8") as file:
        writer = csv.DictWriter(file, fieldnames=list(rows[0]), extrasaction="ignore")
        if new:
            writer.writeheader()
        writer.writerows(rows)


def _stop(process: subprocess.Popen[bytes]) -> None:
    """Tell a run process to stop; kill it if it has not within `STOP_TIMEOUT` seconds."""
    if process.poll() is not None:
        return
    with contextlib.suppress(ProcessLookupError):
        process.send_signal(signal.SIGTERM)
    try:
        process.wait(STOP_TIMEOUT)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


@contextlib.contextmanager
def handling_signals(
    numbers: tuple[int, ...], handler: Callable[[int, Any], Any] | int
) -> Iterator[None]:
    """`handler` (a function of the signal's number and frame, or `signal.SIG_IGN`) for
    each of `numbers` while the block runs, the handlers before it put back at its end.
    Python runs signal handlers on the main thread only: elsewhere nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {number: signal.signal(number, handler) for number in numbers}
    try:
        yield
    finally:
        for number, before in previous.items():
            signal.signal(number, before)


def _ignoring_signals() -> contextlib.AbstractContextManager[None]:
    """A second Ctrl-C (or a SIGTERM, a SIGHUP) must not cut the cleanup short (main
    thread only)."""
    return handling_signals((signal.SIGINT, *_STOPPING), signal.SIG_IGN)


def _terminating_as_interrupt() -> contextlib.AbstractContextManager[None]:
    """SIGTERM or SIGHUP raises `_Terminated` (a `KeyboardInterrupt`) so the run's processes and
    work directory are cleaned up (main thread only)."""

    def terminated(signum: int, _frame: object) -> None:
        raise _Terminated(signum)

    return handling_signals(_STOPPING, terminated)
