"""The supervisors' side of a run (rule `intensity`).

```
 ChildExited (not stopped by the supervisor, its restart type restarts it: counted)
   + SupervisorGaveUp ──► per supervisor, in line order: each counted exit, and whether
   the supervisor gave up at it ──► against OTP's intensity: more than `max_restarts`
   counted exits within `period` s ──► findings
```

A supervisor's events come from its own thread, in the order it decided: a give-up is
decided at the exit it follows (the stops of its children come between them, each a
`ChildExited` marked `stopped`). A supervisor started again counts afresh (OTP): after
its give-up, or where it starts a child a second time (`ChildStarted` again for a name:
a restart is a `ChildRestarted`, so that is a new run of that supervisor, a nested one
restarted by its parent, or its program killed and started again).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence

from rr_actors import events
from rr_actors.experiments._history import Finding, Line

__all__ = ["SLACK_S", "counted", "intensity"]

SLACK_S = 0.01
"""Seconds an exit may lie either side of a window's edge and not be judged: the
supervisor reads its own clock a moment after it stamps `ChildExited.at`."""


def counted(event: events.ChildExited) -> bool:
    """Whether OTP counts `event` against its supervisor's restart intensity: an exit it
    did not cause, of a child its restart type restarts after it (`permanent` always,
    `transient` after an abnormal end; `temporary` never)."""
    if event.stopped:
        return False
    return event.restart == "permanent" or (event.restart == "transient" and not event.normal)


def intensity(history: Sequence[Line]) -> list[Finding]:
    """`intensity`: a supervisor gives up exactly when more than `max_restarts` counted
    exits fall within `period` seconds (OTP), at the exit that makes them so.

    An exit of a line of schema 3 or older (`restart` not known) is not judged, nor one
    that a window's edge holds or leaves out depending on `SLACK_S`. The window starts
    empty again after a give-up and at a new run of the supervisor (a second
    `ChildStarted` of one of its children: see the module's docstring).
    """
    decisions: dict[str, list[tuple[int, events.Event]]] = defaultdict(list)
    for line, event in history:
        judged = isinstance(event, events.ChildExited) and event.restart and counted(event)
        if judged or isinstance(event, (events.SupervisorGaveUp, events.ChildStarted)):
            decisions[event.supervisor].append((line, event))  # type: ignore[union-attr]
    findings: list[Finding] = []
    for supervisor, seen in decisions.items():
        window: list[tuple[float, int]] = []  # (at, line) of the counted exits, in order
        started: set[str] = set()  # the children this run of it started
        for index, (line, event) in enumerate(seen):
            if isinstance(event, events.ChildStarted):
                if event.child in started:  # (a new run of it: it counts afresh)
                    window.clear()
                    started.clear()
                started.add(event.child)
                continue
            if not isinstance(event, events.ChildExited):
                window.clear()  # (a supervisor started again counts afresh)
                continue
            after = seen[index + 1] if index + 1 < len(seen) else None  # (its decision)
            gave_up = after is not None and isinstance(after[1], events.SupervisorGaveUp)
            period, most = event.period, event.max_restarts
            window = [(at, at_line) for at, at_line in window if event.at - at < period + SLACK_S]
            window.append((event.at, line))
            surely = [
                at_line
                for at, at_line in window
                if at_line == line or event.at - at < period - SLACK_S
            ]
            if len(surely) > most and not gave_up:
                lines = tuple(surely[-(most + 1) :])
                findings.append(
                    Finding(
                        "intensity",
                        "violation",
                        f"supervisor {supervisor} did not give up at {event.child}'s exit: "
                        f"{len(surely)} restarts within {period:g} s, more than its "
                        f"max_restarts {most}",
                        lines,
                    )
                )
            elif len(window) <= most and gave_up:
                assert after is not None
                lines = (*(at_line for _, at_line in window), after[0])
                findings.append(
                    Finding(
                        "intensity",
                        "violation",
                        f"supervisor {supervisor} gave up at {event.child}'s exit after "
                        f"{len(window)} restarts within {period:g} s, not more than its "
                        f"max_restarts {most}",
                        lines,
                    )
                )
    return findings
