"""Run the thesis's fault-injected robot mission (chapter 6): `run_mission` and the command line.

A robot (a motor driver and a navigation process) and a LiDAR are loaded through three
managers, each an OS process under one [`Supervisor`][rr_actors.Supervisor]; the robot
drives a path while five faults hit it, each a real SIGKILL:

| fault | what is killed | what the mission does |
|---|---|---|
| F1 | the LiDAR 1 process | hears `FATAL`, stops, substitutes LiDAR 2, continues |
| F2 | the motor driver process | hears `FATAL`, waits for the robot manager's `UPDATE` |
| F3 | the external resource manager | nothing: it restarts and re-adopts its processes |
| F4 | the component manager | nothing: it restarts and restores its catalog |
| F5 | the robot manager | nothing: it restarts and restores its catalog |

At the end everything is unloaded; the mission checks that no process is left and every
catalog is empty, prints a timeline and writes `report.json` and `mission.png`. Run it
with `rr-actors demo` (or `python -m rr_actors_lab.mission`); `--help` lists the options. It
needs Linux.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import errno
import json
import logging
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import rr_actors as rr
from rr_actors import _extras, _log
from rr_actors_lab.mission import netns
from rr_actors_lab.mission.action import Mission
from rr_actors_lab.mission.config import (
    FAULT_WHAT,
    FAULTS,
    HOST_FAULTS,
    MissionConfig,
    MissionError,
    MissionInterruptedError,
    unsupported_platform,
)
from rr_actors_lab.mission.hosts import CERTS, MEMBERS, SYSTEM, RobotObserver, log_file
from rr_actors_lab.mission.netns import TwoHosts
from rr_actors_lab.mission.output import MissionOutput, Progress, make_output, shown, wrap_line
from rr_actors_lab.mission.report import MissionReport

if TYPE_CHECKING:
    from rr_actors._supervision.watching import Page as Observer  # (`observe(sup)`'s)
    from rr_actors_lab import otel

CLOCK_SLACK = 0.05
"""Seconds the page's mission clock may be off before it is set again (`--observe`)."""

CLOCK_LABEL = "mission clock"
"""What the page calls its clock: the story's stamps, since the mission started (`--observe`);
not the *mission time*, a duration (`MissionReport.mission_time_s`)."""

__all__ = [
    "DEFAULT_OUT",
    "OUT_LOCK",
    "add_arguments",
    "config_from_args",
    "lock_out",
    "main",
    "parser",
    "prepare_out",
    "run",
    "run_mission",
]

DEFAULT_OUT = "rr-actors-demo"
"""Where `rr-actors demo` writes, relative to the current directory."""


def prepare_out(path: Path, *, what: str = "out") -> Path:
    """Create the output directory if needed and check that files can be written in it; `path`.

    Args:
        path: the output directory.
        what: how error messages name it (`"--out"` on the command line).

    Raises:
        ConfigError: `path` is a file, cannot be created or written to, or holds a `state/`,
            `bus/` or `certs/` that no mission wrote; the message names it and the cause.
    """
    if path.exists() and not path.is_dir():
        raise rr.ConfigError(f"{what} {str(path)!r} is a file, not a directory")
    _check_not_others(path, what)
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path, prefix=".rr-actors-probe-"):
            pass
    except OSError as exc:
        cause = exc.strerror or exc.__class__.__name__
        raise rr.ConfigError(f"{what} {str(path)!r}: cannot write there ({cause})") from exc
    return path


def _check_not_others(path: Path, what: str) -> None:
    """Refuse a folder whose `state`, `bus` or `certs` (which a mission empties) hold files no
    mission wrote (no `OUT_LOCK`), such as `--out ~`, before anything is removed."""
    if (path / OUT_LOCK).exists():
        return  # a mission's folder: its state/, bus/ and certs/ are a mission's
    for sub in ("state", "bus", "certs"):
        where = path / sub
        if not os.path.lexists(where):
            continue
        try:
            others = not where.is_dir() or any(where.iterdir())
        except OSError as exc:
            raise rr.ConfigError(
                f"{what} {str(path)!r}: cannot read {sub}/ ({exc.strerror or exc})"
            ) from exc
        if others:
            raise rr.ConfigError(
                f"{what} {str(path)!r} holds a {sub}/ that no mission wrote (no {OUT_LOCK} "
                f"there), and the mission empties {sub}/ first: give it another folder"
            )


def run_mission(
    config: MissionConfig,
    out: str | os.PathLike[str],
    *,
    say: Callable[[str], None] = lambda _: None,
    progress: Callable[[Progress], None] = lambda _: None,
    on_supervisor: Callable[[rr.Supervisor], object] | None = None,
    before_fault: Callable[[str, list[str]], object] | None = None,
    on_interrupt: Callable[[float], object] | None = None,
    link: TwoHosts | None = None,
    robot_observer: RobotObserver | None = None,
    step_span: Callable[[str], contextlib.AbstractContextManager[object]] | None = None,
) -> MissionReport:
    """Run the mission and write `report.json` (and `mission.png` if matplotlib is there).

    Args:
        config: what to do.
        out: output directory (created if needed).
        say: receives each line of the story (from the mission's and other threads).
        progress: receives where the mission is, about 50 times a second while it drives.
        on_supervisor: receives the managers' supervisor before it starts (to open its
            observer: `rr_actors_lab.observe.observe(sup)`).
        before_fault: called on the mission's thread before each fault with the fault and
            the processes it involves (one line each), while the robot waits; the fault is
            injected when it returns (`rr-actors demo --step`).
        on_interrupt: called on the mission's thread with the mission time (seconds) of a
            Ctrl-C, before the mission unloads everything and stops its managers.
        link: with `config.hosts == 2`: the two hosts' namespaces (`rr-actors demo --hosts 2`
            runs this in the station's namespace, certificates in `out/certs`).
        robot_observer: with `link`: the robot's host shares its tree with the station's
            observer page, which `on_supervisor` opens.
        step_span: called on the mission's thread with each step's name (`"mission step
            drive"`, ...), the context the step runs in (`otel.root_span` for `--trace`).

    Returns:
        The report.

    Raises:
        MissionError: the mission could not be completed (it still cleaned up), or this
            platform cannot run it (it needs Linux).
        MissionInterruptedError: a Ctrl-C (`KeyboardInterrupt` in the mission's thread)
            ended it; it still cleaned up. No report is written.
        ConfigError: `out` is a file, cannot be created or written to, or another mission
            is running there (`lock_out`).
    """
    reason = unsupported_platform()
    if reason is not None:
        raise MissionError(reason)
    path = prepare_out(Path(out))
    with lock_out(path):  # before the mission empties its state/ and bus/
        report = Mission(
            config,
            path,
            say=say,
            progress=progress,
            on_supervisor=on_supervisor,
            before_fault=before_fault,
            on_interrupt=on_interrupt,
            link=link,
            robot_observer=robot_observer,
            step_span=step_span,
        ).run()
        (path / "report.json").write_text(json.dumps(report.to_dict(), indent=2) + "\n")
        with contextlib.suppress(ImportError):
            from rr_actors_lab.mission.plot import plot  # noqa: PLC0415

            plot(report, path / "mission.png")
    return report


OUT_LOCK = ".demo.lock"
"""The lock file a running mission holds in its output directory."""


@contextlib.contextmanager
def lock_out(path: Path) -> Iterator[None]:
    """Hold an exclusive `flock` on `path/.demo.lock` (with this pid in it) meanwhile.

    A mission empties its folder's `state/` and `bus/`, which would pull them from under
    another mission there; the kernel drops the lock however the process ends.

    Raises:
        ConfigError: another mission holds the lock (the message names its pid and the way
            out: another `--out`).
    """
    import fcntl  # noqa: PLC0415 - POSIX only; the mission needs Linux (checked first)

    fd = os.open(path / OUT_LOCK, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = "unknown"
            with contextlib.suppress(OSError, ValueError):
                holder = str(int(os.pread(fd, 32, 0).decode().strip()))
            raise rr.ConfigError(
                f"{str(path)!r} is in use by another demo (pid {holder}); wait for it to "
                "end, or give this one another folder with --out"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the lock


# -- the command line --------------------------------------------------------------------


DESCRIPTION = (
    "The TeMoto thesis's fault-injected robot mission (chapter 6), on real processes: a "
    "robot drives a path while its LiDAR, its motor driver and each of its three managers "
    "are killed, and recovers from every fault. It tells the story as it happens, then "
    "prints a timeline of the faults. Needs Linux."
)


def parser() -> argparse.ArgumentParser:
    """The `rr-actors demo` command line."""
    p = argparse.ArgumentParser(prog="rr-actors demo", description=DESCRIPTION)
    add_arguments(p)
    return p


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Add the demo's options to `p` (shared by `rr-actors demo` and this module's `main`)."""
    p.add_argument("--fast", action="store_true", help="a run of a few seconds (for CI)")
    p.add_argument(
        "--hosts",
        type=int,
        choices=(1, 2),
        default=1,
        help="2: the robot and the operator station on two hosts (two network namespaces "
        "joined by a veth, mutual TLS), plus F6, the WiFi cut; needs root and `ip`",
    )
    p.add_argument("--inside", default=None, help=argparse.SUPPRESS)  # (--hosts 2's station)
    p.add_argument("--observe-fd", type=int, default=None, help=argparse.SUPPRESS)  # (and its page)
    faults = p.add_mutually_exclusive_group()
    faults.add_argument("--no-faults", action="store_true", help="drive without any fault")
    faults.add_argument(
        "--faults", default=None, help="comma-separated faults to inject (default F1,F2,F3,F4,F5)"
    )
    p.add_argument(
        "--fault-at",
        default=None,
        metavar="F1=0.2,...",
        help="where each fault strikes, as a fraction of the path (between 0 and 1)",
    )
    p.add_argument("--speed", type=float, default=None, help="m/s (default 0.5, fast 2.0)")
    p.add_argument("--distance", type=float, default=None, help="m (default 16, fast 6)")
    p.add_argument("--seed", type=int, default=0, help="seed of the LiDAR noise and jitter")
    p.add_argument(
        "--out",
        default=DEFAULT_OUT,
        help=f"output directory (default {DEFAULT_OUT}/): report.json, mission.png, the "
        "managers' catalogs in state/, the programs' topics in bus/",
    )
    p.add_argument(
        "--isolation", choices=("process", "thread"), default="process", help=argparse.SUPPRESS
    )
    p.add_argument(
        "--quiet",
        action="store_true",
        help="no story and no progress line: print only the timeline and where the report went",
    )
    p.add_argument(
        "--observe",
        action="store_true",
        help="serve the observer's live page (tree, catalogs, dependency graph, statuses) while "
        "the mission runs, on 127.0.0.1; prints its URL (needs the observe extra); with "
        "--hosts 2 the page shows both hosts",
    )
    p.add_argument("--port", type=int, default=0, help="the observer's port (default: a free one)")
    p.add_argument(
        "--trace",
        action="store_true",
        help="make OpenTelemetry spans of the managers' calls, loads and restarts, exported "
        "where the OTEL_* environment variables say (OTEL_TRACES_EXPORTER: default otlp; "
        "console prints them); needs the otel extra",
    )
    p.add_argument(
        "--allow-faults",
        action="store_true",
        help="teaching mode (with --observe): the page's buttons kill, hang and resume managers "
        "and send FATAL, each after a confirmation",
    )
    p.add_argument(
        "--linger",
        type=float,
        default=None,
        metavar="SECONDS",
        help="with --observe: after the mission, keep serving its final state this long "
        "(default: until Ctrl-C; 0: stop with the mission)",
    )
    p.add_argument(
        "--step",
        action="store_true",
        help="classroom mode: before each fault, stop the robot, print the processes involved "
        "and wait for Enter (the waits are left out of every time shown)",
    )


def config_from_args(args: argparse.Namespace) -> MissionConfig:
    """Build the `MissionConfig` the command line asks for.

    Raises:
        ConfigError: an option is invalid.
    """
    changes: dict[str, Any] = {"seed": args.seed, "isolation": args.isolation}
    changes["hosts"] = args.hosts
    if args.hosts == 2:
        changes["faults"] = FAULTS + HOST_FAULTS
    if args.no_faults:
        changes["faults"] = ()
    elif args.faults:
        changes["faults"] = tuple(f.strip().upper() for f in args.faults.split(",") if f.strip())
    if args.speed is not None:
        changes["speed"] = args.speed
    if args.distance is not None:
        changes["distance_m"] = args.distance
    if args.fast:
        base = MissionConfig.fast_two_hosts() if args.hosts == 2 else MissionConfig.fast()
    else:
        base = MissionConfig()
    if args.fault_at:
        points = dict(base.fault_at)
        for item in args.fault_at.split(","):
            key, _, value = item.partition("=")
            try:
                points[key.strip().upper()] = float(value)
            except ValueError:
                raise rr.ConfigError(f"--fault-at: {item!r} is not FAULT=FRACTION") from None
        changes["fault_at"] = points
    return dataclasses.replace(base, **changes)


def main(argv: Sequence[str] | None = None) -> int:
    """`rr-actors demo`: run the mission, print the timeline, write the report.

    Args:
        argv: the arguments without the program name (default: `sys.argv[1:]`).

    Returns:
        0 when the mission completed, every fault was recovered and nothing was left behind;
        1 otherwise; 2 for a bad command line, an unusable output directory or a platform
        other than Linux; 130 after a Ctrl-C (the mission unloaded everything first).
    """
    return run(parser().parse_args(argv))


def _error(message: str) -> None:
    sys.stderr.write(f"rr-actors demo: {message}\n")
    sys.stderr.flush()


def run(args: argparse.Namespace, stream: TextIO | None = None) -> int:  # noqa: PLR0911 - an exit code per outcome
    """Run the mission the parsed `args` ask for (see `add_arguments`); the exit code, as `main`'s.

    Args:
        args: parsed by a parser that `add_arguments` set up.
        stream: where the story and the timeline go (default: standard output); errors go
            to standard error.
    """
    stream = sys.stdout if stream is None else stream
    reason = unsupported_platform()
    if reason is not None:
        _error(reason)
        return 2
    try:
        config = config_from_args(args)
        _check_observe_args(args)
        _check_hosts_args(args)
        out = prepare_out(Path(args.out), what="--out")
    except rr.ConfigError as exc:
        _error(str(exc))
        return 2
    if args.hosts == 2 and args.inside is None:
        return _two_hosts(args, out, stream)
    link = TwoHosts.from_arg(args.inside) if args.inside is not None else None
    robot_observer = (
        RobotObserver(allow_faults=args.allow_faults) if link is not None and args.observe else None
    )
    failure: str | None = None
    report: MissionReport | None = None
    output: MissionOutput = make_output(stream, quiet=args.quiet)
    observers: list[Observer] = []
    try:
        exporting = _exporting(args)
    except rr.ConfigError as exc:
        _error(str(exc))
        return 2
    with (
        output,
        _logging_to(out / LOG),
        _one_interrupt(output) as on_interrupt,
        _closing(observers),
        exporting or contextlib.nullcontext(),
    ):
        hooks = _hooks(args, output, stream, observers, exporting)
        try:
            report = run_mission(
                config,
                out,
                say=output.story,
                progress=_mission_clock(output.progress, observers),
                on_supervisor=hooks[0],
                before_fault=hooks[1],
                on_interrupt=on_interrupt,
                link=link,
                robot_observer=robot_observer,
                step_span=exporting.root_span if exporting is not None else None,
            )
        except KeyboardInterrupt as exc:  # a Ctrl-C: the mission cleaned up (and said so)
            if not isinstance(exc, MissionInterruptedError):  # not while a mission ran
                output.interrupt(None)
            output.end_interrupt(_cleanup_outcome(exc))
            return INTERRUPTED
        except rr.ConfigError as exc:  # the observer could not open (port in use, no extra)
            _error(str(exc))
            return 2
        except MissionError as exc:
            failure = str(exc)
        except OSError as exc:  # the directory became unwritable, or the disk is full
            failure = f"cannot write to {str(out)!r}: {exc}"
        else:
            output.summary(report, _files(out))
        if observers and report is not None:
            _linger(args, observers[0], stream)
    if failure is not None or report is None:
        _error(failure or "the mission did not report")
        return 1
    return 0 if report.ok else 1


LOG = "rr-actors.log"
"""The file in the output directory that rr_actors' WARNINGs and ERRORs go to during a run."""


@contextlib.contextmanager
def _logging_to(path: Path) -> Iterator[None]:
    """Send rr_actors' WARNING and ERROR lines to `path` while it runs (manager processes too).

    The supervisor's WARNING for each deliberate kill would interleave with the story; a
    program that configured logging itself keeps its own configuration.
    """
    logger = logging.getLogger("rr_actors")
    if _log.configured():
        yield
        return
    path.unlink(missing_ok=True)  # (this run's lines only)
    handler = log_file(path)
    logger.addHandler(handler)
    try:
        yield
    finally:
        logger.removeHandler(handler)
        handler.close()


INTERRUPTED = 128 + signal.SIGINT
"""The exit code after a Ctrl-C (130, as a shell reports a command that SIGINT ended)."""


@contextlib.contextmanager
def _one_interrupt(output: MissionOutput) -> Iterator[Callable[[float], None]]:
    """The mission's `on_interrupt`: say so on `output`, and ignore further Ctrl-Cs (a second one
    would cut the unloading short)."""
    previous: list[Any] = []

    def on_interrupt(at_s: float) -> None:
        if threading.current_thread() is threading.main_thread():  # (only it may)
            previous.append(signal.signal(signal.SIGINT, signal.SIG_IGN))
        output.interrupt(at_s)

    try:
        yield on_interrupt
    finally:
        if previous:
            signal.signal(signal.SIGINT, previous[0])


def _cleanup_outcome(exc: KeyboardInterrupt) -> str:
    """How the line after a Ctrl-C ends: what the mission's cleanup did."""
    if not isinstance(exc, MissionInterruptedError):
        return ""
    trouble = []
    if exc.failed_unloads:
        trouble.append(f"{exc.failed_unloads} unload(s) failed")
    if exc.leaked:
        trouble.append(f"{len(exc.leaked)} process(es) were left behind (killed)")
    return "; ".join(trouble) if trouble else "everything unloaded"


def _check_hosts_args(args: argparse.Namespace) -> None:
    """`--hosts 2`: the zenoh extra, root and `ip` (in the first process)."""
    if args.hosts != 2:
        return
    with _extras.needs("zenoh", "--hosts 2"):  # (the certificates, then the carrier)
        from rr_actors._transport.zenoh import net  # noqa: F401, PLC0415
        from rr_actors_lab._tools import certs  # noqa: F401, PLC0415
    reason = netns.unavailable() if args.inside is None else None
    if reason is not None:
        raise rr.ConfigError(reason)


def _check_observe_args(args: argparse.Namespace) -> None:
    """`--observe` has its extra; `--allow-faults`, `--linger` and `--port` go with
    `--observe`; `--linger` is not negative, `--port` a port (checked before anything
    starts)."""
    if not args.observe and args.allow_faults:
        raise rr.ConfigError("--allow-faults needs --observe (its buttons are on the page)")
    if not args.observe and args.linger is not None:
        raise rr.ConfigError("--linger needs --observe (it keeps the page served)")
    if args.observe:
        from rr_actors_lab.observe import require_extra  # noqa: PLC0415 - only --observe needs it

        with _extras.needs("observe", "--observe"):
            require_extra()  # (before the managers start)
    if not args.observe and args.port != 0:
        raise rr.ConfigError("--port needs --observe (it is the observer's port)")
    if not 0 <= args.port <= 65535:
        raise rr.ConfigError(f"--port must be from 0 to 65535, got {args.port}")
    if args.linger is not None and not (args.linger >= 0 and math.isfinite(args.linger)):
        raise rr.ConfigError(f"--linger must be a number of seconds >= 0, got {args.linger}")


@contextlib.contextmanager
def _closing(observers: list[Observer]) -> Iterator[None]:
    """Close the observer (kept serving after its supervisor stopped) however the run ends."""
    try:
        yield
    finally:
        for observer in observers:
            observer.close()


def _mission_clock(
    progress: Callable[[Progress], None], observers: list[Observer]
) -> Callable[[Progress], None]:
    """`progress`, and the page's clock set to the mission's (`elapsed_s` says when 0 s was)."""
    shown = [0.0]

    def tick(where: Progress) -> None:
        progress(where)
        origin = time.time() - where.elapsed_s
        if observers and abs(origin - shown[0]) > CLOCK_SLACK:
            shown[0] = origin
            observers[0].set_clock(origin, CLOCK_LABEL)

    return tick


def _linger(args: argparse.Namespace, observer: Observer, stream: TextIO) -> None:
    """Keep serving the mission's final state: `--linger` seconds, or until Ctrl-C."""
    if args.linger == 0:
        return
    how = "press Ctrl-C to stop" if args.linger is None else f"for {args.linger:g} s"
    with contextlib.suppress(KeyboardInterrupt):  # (a Ctrl-C right after the line is caught too)
        line = f"observer: the mission ended; {observer.url} shows its final state ({how})"
        stream.write(wrap_line(line) + "\n")  # (at words: the URL and its token stay whole)
        stream.flush()
        threading.Event().wait(args.linger)


def _exporting(args: argparse.Namespace) -> otel.Exporting | None:
    """`--trace`: the spans' provider, set up by the `OTEL_*` variables (`None` without).

    Raises:
        ConfigError: the otel extra is missing, or an exporter named is not installed.
    """
    if not args.trace:
        return None
    from rr_actors_lab import otel  # noqa: PLC0415 - only --trace needs it

    return otel.Exporting()


def _hooks(
    args: argparse.Namespace,
    output: MissionOutput,
    stream: TextIO,
    observers: list[Observer],
    exporting: otel.Exporting | None = None,
) -> tuple[Callable[[rr.Supervisor], object] | None, Callable[[str, list[str]], object] | None]:
    """`--observe`, `--trace` and `--step` as the mission's `on_supervisor` and
    `before_fault`."""

    def tell(line: str) -> None:  # shown even with --quiet: it is what these options are for
        if args.quiet:
            stream.write(line + "\n")
            stream.flush()
        else:
            output.story(line)

    def observe(sup: rr.Supervisor) -> None:
        inherited = None  # (--hosts 2: bound on the machine's loopback by the first process)
        if args.observe_fd is not None:
            inherited = socket.socket(fileno=args.observe_fd)
        from rr_actors_lab.observe import observe  # noqa: PLC0415 - its extra's

        observer = observe(
            sup,  # serving after the mission while it lingers; then closed
            port=args.port,
            allow_faults=args.allow_faults,
            keep_serving=True,
            sock=inherited,
        )
        observer.set_clock(time.time(), CLOCK_LABEL)  # (made exact by the first progress)
        observers.append(observer)
        buttons = "; teaching mode: its buttons kill, hang and FATAL" if args.allow_faults else ""
        hosts = ": both hosts, on this machine's loopback" if args.hosts == 2 else ""
        tell(f"observer: {observer.url} (open it in a browser{hosts}{buttons})")

    def step(fault: str, pids: list[str]) -> None:  # the clock stops meanwhile
        with output.hold():  # no progress line over the prompt
            tell(f"next: {fault}, {FAULT_WHAT[fault]}; the robot waits. The processes:")
            for line in pids:
                tell(f"    {line}")
            tell("press Enter to inject it (the mission clock stops while it waits)")
            sys.stdin.readline()  # (at the end of the input: go on at once)

    def on_supervisor(sup: rr.Supervisor) -> None:
        if exporting is not None:
            exporting.trace(sup)  # (closed, its spans exported, when the run ends)
        if args.observe:
            observe(sup)

    traced = args.observe or exporting is not None
    return (on_supervisor if traced else None), (step if args.step else None)


def _files(out: Path) -> list[str]:
    """What the mission wrote where, for the end of the output (paths as `shown`)."""
    where = shown(out)
    plot = (
        f"plot:   {where / 'mission.png'}"
        if (out / "mission.png").exists()
        else "plot:   not drawn: mission.png needs an extra: " + _extras.install_command("demo")
    )
    return [
        f"report: {where / 'report.json'}",
        plot,
        f"state:  {where / 'state'} (rr-actors inspect {shown(_erm_db(out))})",
    ]


# -- two hosts -------------------------------------------------------------------------------


def _station_argv(
    args: argparse.Namespace, out: Path, link: TwoHosts, page: socket.socket | None = None
) -> list[str]:
    """The command line of the station's process: this one's options, where it runs and
    the observer's listening socket it inherits (`page`)."""
    argv = ["--hosts", "2", "--out", str(out.resolve()), "--inside", link.to_arg()]
    argv += ["--seed", str(args.seed), "--isolation", args.isolation]
    for flag in ("fast", "no_faults", "quiet", "step", "observe", "allow_faults", "trace"):
        if getattr(args, flag):
            argv.append("--" + flag.replace("_", "-"))
    if page is not None:
        argv += ["--observe-fd", str(page.fileno())]
    for option in ("faults", "fault_at", "speed", "distance", "linger"):
        value = getattr(args, option)
        if value is not None:
            argv += ["--" + option.replace("_", "-"), str(value)]
    return argv


def make_certs(directory: Path, link: TwoHosts) -> None:
    """A CA and the two hosts' certificates in `directory` (replaced), by `rr-actors certs`'s
    engine: `robot` for the robot's address, `station` for the station's."""
    from rr_actors_lab._tools import certs as certs_tool  # noqa: PLC0415 - needs cryptography

    shutil.rmtree(directory, ignore_errors=True)
    certs_tool.init_ca(directory, SYSTEM)
    robot, station = MEMBERS
    certs_tool.issue_cert(directory, robot, [link.robot_address])
    certs_tool.issue_cert(directory, station, [link.station_address])


def _page_socket(port: int) -> socket.socket:
    """`--hosts 2 --observe`: the observer's listening socket, bound on this machine's loopback
    and inherited by the station's process (a socket stays in the namespace it was made in).

    Raises:
        ConfigError: the observe extra is missing, or the port cannot be listened on.
    """
    from rr_actors_lab.observe import require_extra  # noqa: PLC0415 - only --observe needs it

    require_extra()
    try:
        return socket.create_server(("127.0.0.1", port), backlog=64)
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            raise rr.ConfigError(f"--port {port} on 127.0.0.1 is in use: choose another") from exc
        raise rr.ConfigError(f"--port {port}: cannot listen on 127.0.0.1 ({exc})") from exc


def _two_hosts(args: argparse.Namespace, out: Path, stream: TextIO) -> int:
    """`--hosts 2`: make the namespaces and certificates, run the station's process in its
    namespace (it starts the robot's; it handles Ctrl-C, this one ignores SIGINT), then
    delete everything, however it ended."""
    try:
        page = _page_socket(args.port) if args.observe else None
    except rr.ConfigError as exc:
        _error(str(exc))
        return 2
    try:
        return _two_hosts_with(args, out, stream, page)
    finally:
        if page is not None:
            page.close()  # (the station's process has its own copy)


def _two_hosts_with(
    args: argparse.Namespace, out: Path, stream: TextIO, page: socket.socket | None
) -> int:
    """`_two_hosts`, once the page's socket (if any) is bound."""
    try:
        with lock_out(out):  # (the certificates of a demo running there stay)
            link = TwoHosts.make()
            try:
                make_certs(out / CERTS, link)
            except BaseException:
                link.close()
                raise
    except rr.ConfigError as exc:
        _error(str(exc))
        return 2
    except OSError as exc:
        _error(f"could not make the two hosts: {exc}")
        return 1
    previous = signal.getsignal(signal.SIGINT)
    child: subprocess.Popen[bytes] | None = None
    piped = stream is not sys.stdout
    try:
        command = [
            *link.exec_in(link.station),
            sys.executable,
            "-m",
            "rr_actors_lab.mission",
            *_station_argv(args, out, link, page),
        ]
        child = subprocess.Popen(  # noqa: S603 - ip and this interpreter, no shell
            command,
            stdout=subprocess.PIPE if piped else None,
            pass_fds=() if page is None else (page.fileno(),),
        )
        if page is not None:
            page.close()  # served by the station's process from now on
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # the station's process answers it
        if piped and child.stdout is not None:
            for line in child.stdout:
                stream.write(line.decode(errors="replace"))
                stream.flush()
        code = child.wait()
    except KeyboardInterrupt:  # (before SIGINT was ignored): the station handles it too
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        code = child.wait() if child is not None else INTERRUPTED
    finally:
        link.close()  # kills what is left inside, deletes both namespaces and the veth
        signal.signal(signal.SIGINT, previous)
    return code if code >= 0 else 128 - code


def _erm_db(out: Path) -> Path:
    """The ERM's catalog: `state/erm.db`, or `state/robot/erm.db` across two hosts."""
    robot = out / "state" / "robot" / "erm.db"
    return robot if robot.exists() else out / "state" / "erm.db"
