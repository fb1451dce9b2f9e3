"""Requests whose `repr` misbehaves: what a registrar shows of a request must stop nothing."""

from __future__ import annotations

from typing import Any


class HangsWhenShown:
    """A request whose `repr` blocks until `gate` (an event) is set, at most 30 s; each
    `repr` first appends 1 to `shown` (a list, when given)."""

    def __init__(self, gate: Any, shown: Any = None) -> None:
        self.gate = gate
        self.shown = shown

    def __eq__(self, other: object) -> bool:
        return isinstance(other, HangsWhenShown)

    def __hash__(self) -> int:
        return 1

    def __repr__(self) -> str:
        if self.shown is not None:
            self.shown.append(1)
        self.gate.wait(30)
        return "HangsWhenShown()"


class ExitsWhenShown:
    """A request whose `repr` raises `SystemExit`."""

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ExitsWhenShown)

    def __hash__(self) -> int:
        return 2

    def __repr__(self) -> str:
        raise SystemExit("shown")


class CreatesAFile:
    """Unpickling it would create the file `path` (a str): what a hostile message or backup
    would run; it must never be unpickled."""

    def __init__(self, path: str) -> None:
        self.path = path

    def __reduce__(self) -> tuple[Any, ...]:
        return (open, (self.path, "w"))
