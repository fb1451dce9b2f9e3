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

__all__ = ["KeyPath", "key_lines"]

KeyPath = tuple[str | int, ...]  # a path into the data: table keys and array indices

_CLOSERS = ("", "]", "]]", "]]]", '"""', "'''")  # what may end a prefix cut inside a value


def key_lines(text: str) -> dict[KeyPath, int]:
    """Map every key, table and array element of `text` (valid TOML) to its 1-based line."""
    lines: dict[KeyPath, int] = {}
    rows = text.splitlines(keepends=True)
    for line in range(1, len(rows) + 1):
        prefix = "".join(rows[:line])
        for closer in _CLOSERS:
            try:
                data = tomllib.loads(f"{prefix}\n{closer}")
            except tomllib.TOMLDecodeError:
                continue
            for path in _paths(data, ()):
                lines.setdefault(path, line)
            break
    return lines


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
