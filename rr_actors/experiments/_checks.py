"""The typed reads every plan table shares, each failing as a `PlanError` with its line.

`Checks` knows where each key of the plan's text is (`_lines.key_lines`) and turns a
wrong value into `file:line: key: what is wrong`; `reading._Reader` builds the plan's
tables on it.
"""

from __future__ import annotations

import inspect
import typing
from collections.abc import Callable
from typing import Any, TypeAlias

from rr_actors.errors import ConfigError
from rr_actors.experiments._imports import import_object
from rr_actors.experiments._lines import KeyPath
from rr_actors.experiments.plan import MAX_SECONDS, PlanError, is_number

__all__ = ["Checks", "Table", "dotted"]

Table: TypeAlias = dict[str, Any]
"""A TOML table as `tomllib` reads it."""


def dotted(path: KeyPath) -> str:
    text = ""
    for part in path:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else part)
    return text


class Checks:
    """Typed reads of plan values, turning every problem into a `PlanError` with its line."""

    def __init__(self, source: str, lines: dict[KeyPath, int], base_dir: str | None) -> None:
        self.source = source
        self.lines = lines
        self.base_dir = base_dir

    # -- locating -------------------------------------------------------------------------

    def error(self, path: KeyPath, problem: str) -> PlanError:
        line = 0
        for end in range(len(path), 0, -1):
            if path[:end] in self.lines:
                line = self.lines[path[:end]]
                break
        return PlanError(self.source, line, dotted(path), problem)

    def table(self, value: Any, path: KeyPath, known: tuple[str, ...]) -> Table:
        """`value` as a table with only `known` keys (else an error at the first other)."""
        if not isinstance(value, dict):
            raise self.error(path, f"must be a table, got {value!r}")
        for key in value:
            if key not in known:
                raise self.error(
                    (*path, key), f"unknown key; known here: {', '.join(sorted(known))}"
                )
        return value

    # -- typed values ---------------------------------------------------------------------

    def seconds(
        self,
        table: Table,
        path: KeyPath,
        key: str,
        default: Any,
        *,
        zero: bool = False,
        low: float = 0.0,
    ) -> Any:
        """`table[key]` as seconds in `[low, MAX_SECONDS]` (`default` if absent).

        Zero is allowed only with `zero=True`; a `low` above zero is a minimum.
        """
        value = table.get(key, default)
        if key not in table:
            return value
        self.check_seconds(value, (*path, key), zero=zero, low=low)
        return float(value)

    def check_seconds(
        self, value: Any, path: KeyPath, *, zero: bool = False, low: float = 0.0
    ) -> None:
        """Refuse `value` unless it is seconds in `[low, MAX_SECONDS]` (0 only if `zero`)."""
        if not is_number(value) or value < 0 or (value == 0 and not zero):
            kind = "a number of seconds >= 0" if zero else "a positive number of seconds"
            raise self.error(path, f"must be {kind}, got {value!r}")
        if value < low:
            raise self.error(path, f"must be at least {low:g} s, got {value!r}")
        if value > MAX_SECONDS:
            raise self.error(
                path, f"must be at most {MAX_SECONDS:g} s (about 11.6 days), got {value!r}"
            )

    def integer(self, table: Table, path: KeyPath, key: str, default: Any, *, low: int) -> Any:
        value = table.get(key, default)
        if key not in table:
            return value
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise self.error((*path, key), f"must be an integer >= {low}, got {value!r}")
        return value

    def text(self, table: Table, path: KeyPath, key: str, default: Any) -> Any:
        value = table.get(key, default)
        if key in table and not isinstance(value, str):
            raise self.error((*path, key), f"must be a string, got {value!r}")
        return value

    def choice(self, table: Table, path: KeyPath, key: str, default: str, choices: Any) -> Any:
        value = table.get(key, default)
        if value not in choices:
            raise self.error(
                (*path, key), f"must be one of {', '.join(map(repr, choices))}, got {value!r}"
            )
        return value

    def required(self, table: Table, path: KeyPath, key: str) -> Any:
        if key not in table:
            raise self.error(path, f"{key!r} is missing")
        return table[key]

    def name(self, table: Table, path: KeyPath) -> str:
        value = self.required(table, path, "name")
        if (
            not isinstance(value, str)
            or not value
            or any(not (c.isalnum() or c in "_.-") for c in value)
        ):
            raise self.error(
                (*path, "name"),
                f"must be letters, digits, '_', '-' or '.', got {value!r}",
            )
        return value

    def importable(self, path: KeyPath, import_path: str) -> Callable[..., Any]:
        try:
            target = import_object(import_path, base_dir=self.base_dir)
        except ConfigError as exc:
            raise self.error(path, str(exc)) from None
        if not callable(target):
            raise self.error(path, f"{import_path!r} is not callable")
        return typing.cast("Callable[..., Any]", target)

    def signature_takes(
        self,
        path: KeyPath,
        function: Callable[..., Any],
        import_path: str,
        args: tuple[Any, ...],
        options: Table,
    ) -> None:
        try:
            signature = inspect.signature(function)
        except (TypeError, ValueError):
            return  # a builtin without a signature: it will tell at run time
        try:
            signature.bind(*args, **options)
        except TypeError as exc:
            raise self.error(path, f"{import_path} cannot be called with these: {exc}") from None
