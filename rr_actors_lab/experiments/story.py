"""A simulated run told step by step, for a classroom (`rr-actors replay RUN --seed S --story`).

```
 history (events.jsonl's text: the events, then the fault lines)
   check.read_runs ─► (line, event) ─► events.text.describe: what happened, in words
   fault lines ─► "kill_manager api: SIGKILL pid 20", before the first event at or
   after its time
   check.check ─► the findings: their lines marked `>>`, each violation told under the
                  last line it points at; a crashed run's `Crashed` line last
 ─► lines: `[  0.300 s] #12  api      pid 3   api exited: killed by SIGKILL (pid 3)`
    (virtual seconds, line number, who, simulated pid); with rich, faults in yellow and
    the violation in red
```
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any, TextIO

from rr_actors import events
from rr_actors.events.text import describe
from rr_actors_lab.experiments import check

__all__ = ["StoryLine", "story", "tell"]


@dataclasses.dataclass(frozen=True)
class StoryLine:
    """One step of a run's story, or a violation told under the steps it points at.

    Attributes:
        line: the history's line number (1 for the first); 0 for a violation's line.
        at_s: virtual seconds from the run's first event.
        who: the registrar, the manager (child events), `"fault"`, or `"violation"`.
        pid: the simulated process's pid (`None`: a fault's or a violation's line).
        text: what happened, in words.
        marked: whether a finding of the checker points at this line.
    """

    line: int
    at_s: float
    who: str
    pid: int | None
    text: str
    marked: bool = False

    def stamp(self) -> str:
        """What comes before the text: `  [   0.300 s] #12    api        pid 3  ` (a
        violation: spaces and `^`)."""
        if self.who == "violation":
            return f"{'':>17}^"
        mark = ">>" if self.marked else "  "
        pid = "" if self.pid is None else f"pid {self.pid}"
        return f"{mark}[{self.at_s:8.3f} s] #{self.line:<5} {self.who:<10} {pid:<7}"

    def plain(self) -> str:
        """The line as text, whole (a pipe or a file: one line a step, to search)."""
        return f"{self.stamp()} {self.text}"


def story(history: str) -> list[StoryLine]:
    """The steps of a run's history, in order, with the checker's violations under them.

    Raises:
        ConfigError: a line of `history` that is not an event or a fault line.
    """
    texts = history.splitlines()
    numbered = check.read_runs(texts)
    seen = [line for lines in numbered.values() for line in lines]
    faults = [(n, json.loads(t)) for n, t in enumerate(texts, 1) if _fault(t)]
    times = [e.at for _, e in seen] + [f["at"] for _, f in faults if f.get("at") is not None]
    start = min(times, default=0.0)
    steps = [_step(number, event, start) for number, event in seen]
    for number, fault in faults:
        at = fault.get("at")
        at = start if at is None else at
        where = next((i for i, s in enumerate(steps) if s.line > 0 and s.at_s >= at - start), None)
        told = _fault_step(number, fault, at - start)
        steps.insert(len(steps) if where is None else where, told)
    verdict = check.check([line for lines in numbered.values() for line in lines])
    marked = {n for f in verdict.findings for n in f.lines}
    steps = [dataclasses.replace(s, marked=s.line in marked) for s in steps]
    for finding in verdict.findings:
        last = max(finding.lines, default=0)
        where = max((i for i, s in enumerate(steps) if s.line == last), default=len(steps) - 1)
        lines = ", ".join(map(str, finding.lines))
        text = f"{finding.kind} [{finding.rule}] {finding.message} (lines {lines})"
        told = StoryLine(0, steps[where].at_s if steps else 0.0, "violation", None, text)
        steps.insert(where + 1, told)
    for number, text in enumerate(texts, 1):
        if '"type": "Crashed"' in text and '"schema"' not in text:
            crash = json.loads(text)
            at = float(crash.get("virtual_s", 0.0))  # (the run's first event: at about 0)
            said = f"{crash.get('error_type')}: {crash.get('message')} (step {crash.get('step')})"
            where = next((i for i, s in enumerate(steps) if s.line > 0 and s.at_s > at), None)
            told = StoryLine(number, at, "crashed", None, said)
            steps.insert(len(steps) if where is None else where, told)
    return steps


def _fault(text: str) -> bool:
    return '"type": "Fault' in text and '"schema"' not in text


def _step(number: int, event: events.Event, start: float) -> StoryLine:
    who = getattr(event, "registrar", None) or getattr(event, "child", None)
    who = who or getattr(event, "supervisor", None) or "-"
    return StoryLine(number, event.at - start, str(who), event.pid, describe(event))


def _fault_step(number: int, fault: dict[str, Any], at_s: float) -> StoryLine:
    target = fault.get("target") or "any"
    if fault.get("type") == "FaultSkipped":
        text = f"{fault.get('kind')} {target} skipped: {fault.get('detail')}"
    else:
        text = f"{fault.get('kind')} {target}: {fault.get('detail')}"
    return StoryLine(number, at_s, "fault", None, text)


def tell(history: str, stream: TextIO) -> None:
    """Write a run's story to `stream`: styled on a terminal with rich, else plain lines."""
    steps = story(history)
    console = _console(stream)
    if console is None:
        stream.write("".join(f"{s.plain()}\n" for s in steps))
        return
    from rich.table import Table  # noqa: PLC0415 - rich is optional
    from rich.text import Text  # noqa: PLC0415

    for step in steps:  # (a long text wraps under itself, not under its stamp, as the demo's)
        style = (
            "bold red"
            if step.who in ("violation", "crashed") or step.marked
            else "yellow"
            if step.who == "fault"
            else ""
        )
        grid = Table.grid(padding=(0, 1))
        grid.add_column(no_wrap=True)
        grid.add_column()
        grid.add_row(Text(step.stamp(), style=style), Text(step.text, style=style))
        console.print(grid)


def _console(stream: TextIO) -> Any:
    if not stream.isatty():
        return None
    try:
        from rich.console import Console  # noqa: PLC0415 - rich is optional
    except ImportError:
        return None
    return Console(file=stream, highlight=False)
