"""Where each key of a TOML file is: the line of every key path, for a plan's errors.

`tomllib` gives the data but no positions. A key's line is the first line at which the
text up to there (closed by a bracket or quotes if it stops inside an array or a string)
holds it: `[[tree.children]]` on line 3 is `("tree", "children", 0)` -> 3, and its
`name = "erm"` on line 4 `("tree", "children", 0, "name")` -> 4.
"""

from __future__ import annotations

import tomllib
from collections.abc import Iterator
from typing import Any

__all__ = ["KeyPath", "key_lines", "line_of"]

KeyPath = tuple[str | int, ...]  # a path into the data: table keys and array indices

_CLOSERS = ("", "]", "]]", "]]]", '"""', "'''")  # what may end a prefix cut inside a value


EXACT_LINES = 200
"""Up to this many lines, every key's line is found by reading each prefix (quadratic);
beyond, one key's line is found by bisection (`line_of`), so a long plan's error still
comes within a second."""


def key_lines(text: str) -> dict[KeyPath, int]:
    """Map every key, table and array element of `text` (valid TOML) to its 1-based line."""
    lines: dict[KeyPath, int] = {}
    rows = text.splitlines(keepends=True)
    for line in range(1, len(rows) + 1):
        data = _prefix(rows, line)
        for path in _paths(data or {}, ()):
            lines.setdefault(path, line)
    return lines


def line_of(text: str, paths: list[KeyPath]) -> int:
    """The line of the first of `paths` (most specific first) that `text` holds; 0 if none.

    Exact for short texts (`key_lines`); by bisection over the prefixes for long ones.
    """
    rows = text.splitlines(keepends=True)
    if len(rows) <= EXACT_LINES:
        lines = key_lines(text)
        return next((lines[p] for p in paths if p in lines), 0)
    whole = _prefix(rows, len(rows)) or {}
    for path in paths:
        if not _holds(whole, path):
            continue
        low, high = 1, len(rows)
        while low < high:
            middle = (low + high) // 2
            if _holds(_prefix(rows, middle) or {}, path):
                high = middle
            else:
                low = middle + 1
        return low
    return 0


def _prefix(rows: list[str], line: int) -> dict[str, Any] | None:
    """The data of the first `line` rows, closed if cut inside a value; None if unreadable."""
    prefix = "".join(rows[:line])
    for closer in _CLOSERS:
        try:
            return tomllib.loads(f"{prefix}\n{closer}")
        except tomllib.TOMLDecodeError:
            continue
    return None


def _holds(data: Any, path: KeyPath) -> bool:
    node = data
    for key in path:
        in_table = isinstance(node, dict) and key in node
        in_array = isinstance(node, list) and isinstance(key, int) and 0 <= key < len(node)
        if in_table or in_array:
            node = node[key]
        else:
            return False
    return True


def _paths(node: Any, path: KeyPath) -> Iterator[KeyPath]:
    items = (
        node.items()
        if isinstance(node, dict)
        else enumerate(node)
        if isinstance(node, list)
        else ()
    )
    for key, child in items:
        yield (*path, key)
        yield from _paths(child, (*path, key))
