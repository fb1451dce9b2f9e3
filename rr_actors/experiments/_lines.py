"""The line of a key in a TOML text, for a plan's errors (`tomllib` gives no positions).

A key's line is the first line at which the text up to there (closed by a bracket or quotes
if it stops inside an array or a string) holds it, found by bisection (a 20,000-line plan
takes a few parses): `[[tree.children]]` on line 3 is `("tree", "children", 0)` -> 3, and
its `name = "erm"` on line 4 `("tree", "children", 0, "name")` -> 4.
"""

from __future__ import annotations

import tomllib
from collections.abc import Iterator
from typing import Any

__all__ = ["KeyPath", "held", "key_lines", "line_of"]

KeyPath = tuple[str | int, ...]  # a path into the data: table keys and array indices


def line_of(text: str, paths: list[KeyPath]) -> int:
    """The 1-based line of the first of `paths` (most specific first) in `text`; 0 if none."""
    rows = text.splitlines(keepends=True)
    for path in paths:
        low, high = 1, len(rows) + 1  # the line is in [low, high]; high: not in the text
        while low < high:
            middle = (low + high) // 2
            low, high = (low, middle) if _holds(rows[:middle], path) else (middle + 1, high)
        if low <= len(rows):
            return low
    return 0


def key_lines(text: str) -> dict[KeyPath, int]:
    """Every key, table and array element of `text` (valid TOML), with its line."""

    def paths(node: Any, path: KeyPath) -> Iterator[KeyPath]:
        if isinstance(node, dict | list):
            for key, child in node.items() if isinstance(node, dict) else enumerate(node):
                yield (*path, key)
                yield from paths(child, (*path, key))

    return {path: line_of(text, [path]) for path in paths(tomllib.loads(text), ())}


def held(data: Any, path: KeyPath) -> KeyPath:
    """The longest start of `path` that `data` has."""
    for n, key in enumerate(path):
        keys = (
            data if isinstance(data, dict) else range(len(data)) if isinstance(data, list) else ()
        )
        if key not in keys:
            return path[:n]
        data = data[key]
    return path


def _holds(rows: list[str], path: KeyPath) -> bool:
    """Whether the data of `rows`, closed if cut inside a value, has a value at `path`."""
    for closer in ("", "]", "]]", "]]]", '"""', "'''", '"""]', "''']"):
        try:
            return held(tomllib.loads(f"{''.join(rows)}\n{closer}"), path) == path
        except tomllib.TOMLDecodeError:
            continue
    return False
