"""What `rr-actors demo` shows: the story as it happens, a live progress line, the timeline.

Two renderers with one interface (`MissionOutput`), chosen once by `make_output`:
`RichOutput` on a terminal with `rich` (`pip install 'rr-actors[demo]'`): the story
scrolls above a live progress line never wider than the terminal, other processes'
standard error goes above it too (`stderr.StderrLines`), then the timeline fits the
terminal; `PlainOutput` elsewhere: lines wrapped at words to 80 columns, no progress line.

`--quiet` keeps only the timeline and the report's paths. While `--step` waits for Enter
(`hold`), the progress line is taken down. After a Ctrl-C (`interrupt`) both show
`interrupted at 8.0 s: unloading...`, ended by `end_interrupt`; the story is dropped.
"""

from __future__ import annotations

import contextlib
import dataclasses
import textwrap
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, Protocol, TextIO

from rr_actors_lab.mission.report import MissionReport, TimelineRow, timeline_rows
from rr_actors_lab.mission.stderr import StderrLines

if TYPE_CHECKING:
    from rich.console import Console
    from rich.live import Live
    from rich.table import Table

__all__ = [
    "WIDTH",
    "MissionOutput",
    "PlainOutput",
    "Progress",
    "RichOutput",
    "make_output",
    "progress_table",
    "shown",
    "timeline",
    "timeline_table",
    "wrap_line",
]

HEADERS = ("fault", "what", "injected at", "detected", "recovered", "robot stopped")
"""The timeline's columns; "detected" and "recovered" count from the injection."""


@dataclasses.dataclass(frozen=True)
class Progress:
    """Where the mission is, for the live progress line.

    Attributes:
        elapsed_s: seconds since the mission started.
        distance_m: distance driven, metres.
        goal_m: length of the path, metres.
        moving: whether the robot is moving.
        status: the fault being recovered from (`""` if none).
    """

    elapsed_s: float
    distance_m: float
    goal_m: float
    moving: bool
    status: str


class MissionOutput(Protocol):
    """Where the demo's output goes. `story` and `progress` may be called from any thread."""

    def __enter__(self) -> MissionOutput: ...

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None: ...

    def story(self, line: str) -> None:
        """Show one line of the story."""

    def progress(self, progress: Progress) -> None:
        """Show where the mission is (the latest call wins)."""

    def summary(self, report: MissionReport, files: Sequence[str]) -> None:
        """Show the timeline and the totals, then `files` (what was written where)."""

    def hold(self) -> contextlib.AbstractContextManager[None]:
        """Show nothing live meanwhile (while the terminal waits for the user's input)."""

    def interrupt(self, at_s: float | None) -> None:
        """A Ctrl-C: take down what is live, drop the story from now on, start one line.

        Args:
            at_s: the mission time of the Ctrl-C (seconds); `None` when no mission ran
                (the line is then `interrupted`).
        """

    def end_interrupt(self, outcome: str) -> None:
        """End the line `interrupt` started with `outcome` (what the cleanup did)."""


WIDTH = 80
"""The widest a plain line is (a pipe, a file): the story wraps at words under its text."""


def wrap_line(line: str, width: int = WIDTH) -> str:
    """`line` wrapped at words to `width` columns; a story line `[  1.23 s] ...` wraps
    under its text, not its stamp. A word longer than a line (a path, a URL) stays whole."""
    stamp, bracket, _ = line.partition("] ")
    indent = " " * (len(stamp) + 2) if line.startswith("[") and bracket else "    "
    lines = textwrap.wrap(
        line, width, subsequent_indent=indent, break_long_words=False, break_on_hyphens=False
    )
    return "\n".join(lines) if lines else line


def shown(path: Path) -> Path:
    """`path` as the user would type it: relative to the working directory when it is
    under it (`--hosts 2` hands the station's process an absolute `--out`)."""
    try:
        return path.resolve().relative_to(Path.cwd().resolve())
    except (ValueError, OSError):  # elsewhere, or the working directory is gone
        return path


def _interrupted(at_s: float | None) -> str:
    return "interrupted" if at_s is None else f"interrupted at {at_s:.1f} s: unloading..."


def _ended(outcome: str) -> str:
    return f" {outcome}" if outcome else ""


def _seconds(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f} s"


def _cells(row: TimelineRow) -> tuple[str, ...]:
    return (
        row.label,
        row.what,
        _seconds(row.at_s),
        _seconds(row.detected_after_s),
        _seconds(row.recovered_after_s),
        _seconds(row.robot_stopped_s),
    )


def _notes(report: MissionReport) -> list[str]:
    notes = []
    if report.faults:
        notes.append("detected, recovered: seconds after the injection")
    if report.unplanned_restarts:
        notes.append("-: a manager exit no fault caused; recovered: its restart took")
    return notes


def _totals(report: MissionReport) -> list[str]:
    paused = (
        [
            f"paused for Enter {len(report.pauses_s)} time(s), {report.paused_s:.2f} s in all "
            "(left out of every time)"
        ]
        if report.pauses_s
        else []
    )
    return [
        f"mission time {report.mission_time_s:.2f} s (the drive; without stops "
        f"{report.nominal_time_s:.2f} s), distance {report.distance_m:.2f} m",
        *paused,
        f"leaked processes: {report.leaked_processes}; catalog entries left: "
        f"{report.catalog_entries_left}",
    ]


def timeline(report: MissionReport) -> str:
    """The report as a plain-text table (at most 80 columns), then the totals.

    One row per injected fault and per unplanned manager restart (`timeline_rows`);
    "detected" and "recovered" count seconds from the injection.
    """
    rows = [HEADERS, *(_cells(row) for row in timeline_rows(report))]
    if len(rows) == 1:
        return "\n".join(_totals(report))
    widths = [max(len(r[i]) for r in rows) for i in range(len(HEADERS))]
    lines = [
        "  ".join(
            cell.ljust(width) if i < 2 else cell.rjust(width)
            for i, (cell, width) in enumerate(zip(row, widths, strict=True))
        ).rstrip()
        for row in rows
    ]
    lines.insert(1, "  ".join("-" * width for width in widths))
    lines.extend(f"({note})" for note in _notes(report))
    return "\n".join([*lines, "", *_totals(report)])


class PlainOutput:
    """Plain lines on a stream: the story (unless quiet) and the timeline; no progress line.

    Args:
        stream: where to write (standard output, a pipe, a file).
        quiet: drop the story.
    """

    def __init__(self, stream: TextIO, *, quiet: bool = False) -> None:
        self.stream = stream
        self.quiet = quiet
        self._lock = threading.Lock()  # lines from several threads must not run together
        self._interrupted = False

    def __enter__(self) -> PlainOutput:
        return self

    def __exit__(self, *_: object) -> None:
        return None

    def _write(self, text: str) -> None:
        with self._lock:
            self.stream.write(text)
            self.stream.flush()

    def story(self, line: str) -> None:
        """Write one line of the story (unless quiet, or after a Ctrl-C)."""
        if not (self.quiet or self._interrupted):
            self._write(wrap_line(line) + "\n")

    def progress(self, progress: Progress) -> None:
        """Nothing: a progress line needs a terminal to redraw it in place."""

    @contextlib.contextmanager
    def hold(self) -> Iterator[None]:
        """Nothing to hold: plain output has nothing live."""
        yield

    def interrupt(self, at_s: float | None) -> None:
        """Drop the story from now on; write the start of the line (even when quiet)."""
        self._interrupted = True
        self._write(_interrupted(at_s))

    def end_interrupt(self, outcome: str) -> None:
        """End the line with `outcome`."""
        self._write(_ended(outcome) + "\n")

    def summary(self, report: MissionReport, files: Sequence[str]) -> None:
        """Write the timeline, the totals and `files`."""
        shown = [wrap_line(line) for line in [*timeline(report).split("\n"), "", *files]]
        self._write("\n" + "\n".join(shown) + "\n")


# -- rich ----------------------------------------------------------------------------------


def progress_table(progress: Progress) -> Table:
    """The live progress line as a one-row grid that fits any width (the status gets cut)."""
    from rich.progress_bar import ProgressBar  # noqa: PLC0415 - rich is optional
    from rich.table import Table  # noqa: PLC0415

    grid = Table.grid(padding=(0, 1), expand=True)
    grid.add_column(justify="right", no_wrap=True, width=8)
    grid.add_column(no_wrap=True, width=20)
    grid.add_column(justify="right", no_wrap=True, width=len(f"{progress.goal_m:5.2f}") * 2 + 3)
    grid.add_column(no_wrap=True, width=7)
    grid.add_column(no_wrap=True, overflow="ellipsis", ratio=1)  # gets what is left
    grid.add_row(
        f"{progress.elapsed_s:6.2f} s",
        ProgressBar(total=progress.goal_m, completed=progress.distance_m, width=20),
        f"{progress.distance_m:5.2f}/{progress.goal_m:.2f} m",
        "moving" if progress.moving else "stopped",
        progress.status,
    )
    return grid


def timeline_table(report: MissionReport) -> Table:
    """The timeline as a `rich` table; it wraps its headers to fit narrow terminals."""
    from rich import box  # noqa: PLC0415 - rich is optional
    from rich.table import Table  # noqa: PLC0415

    table = Table(
        box=box.SIMPLE_HEAD,
        show_edge=False,
        pad_edge=False,
        collapse_padding=True,
        caption_justify="left",
    )
    for i, header in enumerate(HEADERS):
        table.add_column(header, justify="left" if i < 2 else "right", no_wrap=i != 1)
    for row in timeline_rows(report):
        table.add_row(*_cells(row))
    table.caption = "\n".join(_notes(report)) or None
    return table


class RichOutput:
    """A terminal, through `rich`: the story above a live progress line, a fitted table.

    Args:
        console: the `rich` console (its width is the terminal's).
        quiet: drop the story and the progress line.
    """

    def __init__(self, console: Console, *, quiet: bool = False) -> None:
        self.console = console
        self.quiet = quiet
        self._live: Live | None = None
        self._held = False
        self._interrupted = False
        self._stderr: StderrLines | None = None

    def __enter__(self) -> RichOutput:
        from rich.live import Live  # noqa: PLC0415 - rich is optional

        self._stderr = StderrLines.open(self.console.file, self._written)
        if not self.quiet:
            # transient: the progress line is gone when the mission ends; the story stays.
            self._live = Live(
                console=self.console,
                transient=True,
                refresh_per_second=10,
                redirect_stdout=False,
                redirect_stderr=False,
            )
            self._live.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._stop_live()
        if self._stderr is not None:
            self._stderr.close()
            self._stderr = None

    def _stop_live(self) -> None:
        if self._live is not None:
            self._live.stop()
            self._live = None

    def _print(self, renderable: Any) -> None:
        self.console.print(renderable, markup=False, highlight=False, emoji=False)

    def _written(self, line: str) -> None:
        """A line written to standard error (any process of the demo): above the live
        line, wrapped at words to the terminal's width (a word longer stays whole)."""
        self.console.print(
            wrap_line(line, self.console.width),
            markup=False,
            highlight=False,
            emoji=False,
            soft_wrap=True,  # (wrapped already: rich neither wraps nor crops it again)
        )

    def story(self, line: str) -> None:
        """Print one line of the story above the progress line (unless quiet).

        A line stamped `[  1.23 s] ...` that is too long for the terminal wraps under its
        text, not under its stamp.
        """
        if self.quiet or self._interrupted:
            return
        stamp, bracket, text = line.partition("] ")
        if not (line.startswith("[") and bracket):
            self._print(line)
            return
        from rich.table import Table  # noqa: PLC0415 - rich is optional

        grid = Table.grid(padding=(0, 1))
        grid.add_column(no_wrap=True)
        grid.add_column()
        grid.add_row(stamp + "]", text)
        self._print(grid)

    def progress(self, progress: Progress) -> None:
        """Redraw the progress line (at most 10 times a second)."""
        live = self._live
        if live is not None and not self._held:
            live.update(progress_table(progress))

    @contextlib.contextmanager
    def hold(self) -> Iterator[None]:
        """Take the progress line down meanwhile (a prompt and its typing show); put it back."""
        live = self._live
        if live is None:
            yield
            return
        self._held = True
        live.stop()
        try:
            yield
        except BaseException:  # a Ctrl-C at the prompt: the mission ends, no line comes back
            self._live = None
            raise
        live.start()
        self._held = False

    def interrupt(self, at_s: float | None) -> None:
        """Remove the progress line, drop the story, print the start of the line.

        It starts at the beginning of the terminal's line, over the `^C` the terminal
        may have echoed there.
        """
        self._interrupted = True
        self._stop_live()
        self.console.file.write("\r")
        self.console.print(_interrupted(at_s), end="", markup=False, highlight=False)
        self.console.file.flush()

    def end_interrupt(self, outcome: str) -> None:
        """End the line with `outcome`."""
        self._print(_ended(outcome))

    def summary(self, report: MissionReport, files: Sequence[str]) -> None:
        """Remove the progress line; print the timeline, the totals and `files`."""
        self._stop_live()
        self._print("")
        if report.faults or report.unplanned_restarts:
            self._print(timeline_table(report))
            self._print("")
        for line in [*_totals(report), "", *files]:
            self._print(line)


def make_output(stream: TextIO, *, quiet: bool = False) -> MissionOutput:
    """`RichOutput` if `stream` is a terminal and `rich` is installed, else `PlainOutput`."""
    if stream.isatty():
        try:
            from rich.console import Console  # noqa: PLC0415 - rich is optional
        except ImportError:
            pass
        else:
            return RichOutput(Console(file=stream), quiet=quiet)
    return PlainOutput(stream, quiet=quiet)
