"""Reading a plan's `[[faults]]`: each fault's kind, targets, and when it comes.

Part of `reading._Reader`; every problem is a `PlanError` with its line (`_checks`).
"""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Mapping
from typing import Any

from rr_actors._types import Status
from rr_actors.experiments._checks import Checks, Table
from rr_actors.experiments._lines import KeyPath
from rr_actors.experiments.plan import (
    EVENT_TYPES,
    FAULT_KINDS,
    MAX_INJECTIONS,
    MIN_EVERY,
    NEEDS_PROCESS,
    FaultPlan,
    ManagerPlan,
    Trigger,
    is_number,
)

__all__ = ["FaultChecks"]


class FaultChecks(Checks):
    """Reads one `[[faults]]` entry: kind, targets, `at`/`every`/`after`, and its trigger."""

    def fault(
        self,
        value: Any,
        path: KeyPath,
        managers: dict[str, ManagerPlan],
        duration: float,
        names: Mapping[str, frozenset[str]],
    ) -> FaultPlan:
        """One `[[faults]]` entry; `names` are the values an `after` field may name."""
        table = self.table(
            value,
            path,
            (
                "kind",
                "target",
                "at",
                "every",
                "start",
                "stop",
                "count",
                "after",
                "delay",
                "for",
                "loads",
                "server",
                "message",
            ),
        )
        if "kind" not in table:
            raise self.error(path, f"'kind' is missing: one of {', '.join(FAULT_KINDS)}")
        kind = self.choice(table, path, "kind", "", FAULT_KINDS)
        targets = self.targets(table, path, kind, managers)
        at, every, after = self.when(table, path, duration, names)
        start, stop = self.span(table, path, every, duration)
        for_s = self.seconds(table, path, "for", None)
        if kind == "hang_manager" and for_s is None:
            raise self.error(path, "'for' is missing: how many seconds the manager stays stopped")
        if "for" in table and kind not in ("hang_manager", "load_error"):
            raise self.error((*path, "for"), f"does not go with kind {kind!r}")
        for key in ("loads", "server", "message"):
            if key in table and kind != "load_error":
                raise self.error((*path, key), "only goes with kind 'load_error'")
        if "for" in table and "loads" in table:
            raise self.error(
                (*path, "loads"), "give either 'for' (seconds) or 'loads' (a number), not both"
            )
        delay = self.seconds(table, path, "delay", 0.0, zero=True)
        if delay >= duration:
            raise self.error(
                (*path, "delay"),
                f"{delay:g} s is not before the end of the run ({duration:g} s): it never fires",
            )
        fault = FaultPlan(
            kind=kind,
            targets=targets,
            at=at,
            every=every,
            start=start,
            stop=stop,
            count=self.integer(table, path, "count", None, low=1),
            after=after,
            delay=delay,
            for_s=for_s,
            loads=self.integer(table, path, "loads", 1, low=1),
            server=self.text(table, path, "server", None),
            message=self.text(table, path, "message", "injected load error"),
        )
        most = fault.most_injections(duration)
        if most > MAX_INJECTIONS:
            raise self.error(
                (*path, "every"),
                f"would inject up to {most} times in a run (at most {MAX_INJECTIONS} per "
                "fault): give a longer interval, a 'count' or a 'stop'",
            )
        return fault

    def span(
        self,
        table: Table,
        path: KeyPath,
        every: float | tuple[float, float] | None,
        duration: float,
    ) -> tuple[float, float | None]:
        """`start` and `stop` of an `every` fault, refused if no injection could come."""
        start = self.seconds(table, path, "start", 0.0, zero=True)
        stop = self.seconds(table, path, "stop", None)
        if start >= duration:
            raise self.error(
                (*path, "start"),
                f"{start:g} s is not before the end of the run ({duration:g} s)",
            )
        if stop is not None and stop <= start:
            raise self.error((*path, "stop"), f"must be after 'start' ({start:g} s)")
        if stop is not None and stop > duration:
            raise self.error(
                (*path, "stop"),
                f"{stop:g} s is after the end of the run ({duration:g} s); leave it out to "
                "inject until the end",
            )
        if every is not None:
            low = every if isinstance(every, float) else every[0]
            end = duration if stop is None else stop
            if start + low >= end:
                raise self.error(
                    (*path, "every"),
                    f"the first injection ({start:g} + {low:g} s) would not come before "
                    f"{'stop' if stop is not None else 'the end of the run'} ({end:g} s)",
                )
        return start, stop

    def when(
        self,
        table: Table,
        path: KeyPath,
        duration: float,
        names: Mapping[str, frozenset[str]],
    ) -> tuple[tuple[float, ...], float | tuple[float, float] | None, Trigger | None]:
        """A fault's `at`, `every` and `after` (exactly one of them is given)."""
        given = [key for key in ("at", "every", "after") if key in table]
        if len(given) != 1:
            problem = "say when: give one of 'at', 'every' or 'after'"
            if given:
                problem = f"give only one of 'at', 'every' or 'after', not {' and '.join(given)}"
            raise self.error(path, problem)
        for key in ("start", "stop", "count"):
            if key in table and "every" not in table:
                raise self.error((*path, key), "only goes with 'every'")
        if "delay" in table and "after" not in table:
            raise self.error((*path, "delay"), "only goes with 'after'")
        if "every" in table:
            return (), self.every(table, path), None
        if "after" in table:
            return (), None, self.trigger(table["after"], (*path, "after"), names)
        raw = table["at"] if isinstance(table["at"], list) else [table["at"]]
        where = (*path, "at")
        if not raw:
            raise self.error(where, "must give at least one time (seconds)")
        for index, item in enumerate(raw):
            item_path = (*where, index) if isinstance(table["at"], list) else where
            if not is_number(item) or item < 0:
                raise self.error(item_path, f"must be seconds >= 0, got {item!r}")
            if item >= duration:
                raise self.error(
                    item_path, f"{item!r} s is not before the end of the run ({duration:g} s)"
                )
        return tuple(float(item) for item in raw), None, None

    def targets(
        self, table: Table, path: KeyPath, kind: str, managers: dict[str, ManagerPlan]
    ) -> tuple[str, ...]:
        value = table.get("target")
        where = (*path, "target")
        if value is None:
            if kind != "kill_resource":
                raise self.error(path, "'target' is missing: which manager (or a list of them)")
            if not any(m.isolation == "process" for m in managers.values()):
                raise self.error(
                    path,
                    "kill_resource kills resource processes of process managers; every "
                    "manager of this tree has isolation 'thread'",
                )
            return ()
        names = value if isinstance(value, list) else [value]
        if not names:
            raise self.error(where, "must name at least one manager")
        for index, name in enumerate(names):
            at = (*where, index) if isinstance(value, list) else where
            if not isinstance(name, str):
                raise self.error(at, f"must be a manager's name, got {name!r}")
            if name not in managers:
                raise self.error(
                    at, f"no manager {name!r} in the tree (managers: {', '.join(managers)})"
                )
            if kind in NEEDS_PROCESS and managers[name].isolation != "process":
                raise self.error(
                    at, f"{kind} needs a process manager; {name!r} has isolation 'thread'"
                )
        return tuple(names)

    def every(self, table: Table, path: KeyPath) -> float | tuple[float, float]:
        value = table["every"]
        where = (*path, "every")
        if not isinstance(value, dict):
            self.check_seconds(value, where, low=MIN_EVERY)
            return float(value)
        span = self.table(value, where, ("min", "max"))
        low = self.seconds(span, where, "min", None, low=MIN_EVERY)
        high = self.seconds(span, where, "max", None, low=MIN_EVERY)
        if low is None or high is None:
            raise self.error(where, "needs both 'min' and 'max' (seconds)")
        if high < low:
            raise self.error((*where, "max"), f"must not be less than min ({low:g} s)")
        return (low, high)

    def trigger(self, value: Any, path: KeyPath, names: Mapping[str, frozenset[str]]) -> Trigger:
        if not isinstance(value, dict):
            raise self.error(
                path, f'must be a table like {{ event = "ChildRestarted" }}, got {value!r}'
            )
        event = self.required(value, path, "event")
        cls = EVENT_TYPES.get(event) if isinstance(event, str) else None
        if cls is None:
            raise self.error(
                (*path, "event"),
                f"unknown event {event!r}; events: {', '.join(sorted(EVENT_TYPES))}",
            )
        fields = [f.name for f in dataclasses.fields(cls) if f.name != "at"]
        self.table(value, path, ("event", "nth", *fields))
        hints = typing.get_type_hints(cls)
        match = {
            key: self.match_value(item, hints[key], (*path, key), names.get(key))
            for key, item in value.items()
            if key not in ("event", "nth")
        }
        return Trigger(event=event, match=match, nth=self.integer(value, path, "nth", 1, low=1))

    def match_value(
        self, value: Any, kind: Any, path: KeyPath, known: frozenset[str] | None
    ) -> Any:
        """An `after` field's value, of the field's type; a name must be one in `known`.

        A value of another type, or a name nobody in the run has, would never match: the
        fault would silently never fire.
        """
        if kind is Status:
            if value not in Status.__members__:
                raise self.error(
                    path, f"must be one of {', '.join(Status.__members__)}, got {value!r}"
                )
            return Status[value]
        if kind is str and not isinstance(value, str):
            raise self.error(path, f"must be a string, got {value!r}")
        if kind is int and (isinstance(value, bool) or not isinstance(value, int)):
            raise self.error(path, f"must be an integer, got {value!r}")
        if kind is float and not is_number(value):
            raise self.error(path, f"must be a number, got {value!r}")
        if known is not None and value not in known:
            raise self.error(
                path, f"{value!r} names nothing in this run (it may be: {', '.join(sorted(known))})"
            )
        return value
