"""Where each key of a TOML file is: the line of every key path, for a plan's errors.

`tomllib` gives the data but no positions. One regular expression splits the text (that
`tomllib` accepted) into tokens, and a small walk records the line of every key, table
header and array element, addressed as in the data: `[[tree.children]]` on line 3 is
`("tree", "children", 0)` -> 3, its `name = "erm"` `("tree", "children", 0, "name")` -> 4.
"""

from __future__ import annotations

import re

__all__ = ["KeyPath", "key_lines"]

KeyPath = tuple[str | int, ...]  # a path into the data: table keys and array indices

_TOKEN = re.compile(
    r'(?P<s>"""(?:[^\\]|\\[\s\S])*?"""(?!")|\'\'\'[\s\S]*?\'\'\'(?!\')'
    r'|"(?:[^"\\\n]|\\.)*"|\'[^\'\n]*\')|(?P<c>#[^\n]*)|(?P<p>[\n\[\]{}=,.])'
    r"|(?P<w>[^\s\[\]{}=,.#\"']+)"
)


def key_lines(text: str) -> dict[KeyPath, int]:
    """Map every key, table and array element of `text` (valid TOML) to its 1-based line."""
    tokens, line = [], 1
    for match in _TOKEN.finditer(text):
        if match.lastgroup != "c":
            tokens.append((match.group(), line))
        line += match.group().count("\n")
    return _Walk([*tokens, ("", line)]).lines


class _Walk:
    """One pass over the tokens, from the top: headers, `key = value`, nested values."""

    def __init__(self, tokens: list[tuple[str, int]]) -> None:
        self.tokens, self.i, self.lines = tokens, 0, dict[KeyPath, int]()
        arrays: dict[KeyPath, int] = {}  # arrays of tables: the index of their last element
        table: KeyPath = ()
        while self.skip("\n") != "":
            if self.peek() != "[":
                self.pair(table)
                continue
            line, double = self.tokens[self.i][1], self.tokens[self.i + 1][0] == "["
            self.i += 1 + double
            parts, resolved = self.key(), []
            for n, part in enumerate(parts):
                resolved.append(part)
                if double and n == len(parts) - 1:
                    arrays[tuple(resolved)] = arrays.get(tuple(resolved), -1) + 1
                    self.lines.setdefault(tuple(resolved), line)
                if tuple(resolved) in arrays:
                    resolved.append(arrays[tuple(resolved)])
            table = tuple(resolved)
            self.lines.setdefault(table, line)
            self.i += 1 + double

    def peek(self) -> str:
        return self.tokens[self.i][0]

    def skip(self, *tokens: str) -> str:
        while self.peek() in tokens and self.peek() != "":
            self.i += 1
        return self.peek()

    def key(self) -> KeyPath:
        parts = [self.peek()]
        while self.tokens[self.i + 1][0] == ".":
            self.i += 2
            parts.append(self.peek())
        self.i += 1
        return tuple(p[1:-1] if p[0] in "\"'" else p for p in parts)

    def pair(self, table: KeyPath) -> None:
        line, path = self.tokens[self.i][1], table + self.key()
        self.lines.setdefault(path, line)
        self.i += 1  # "="
        self.value(path)

    def value(self, path: KeyPath) -> None:
        opening = self.peek()
        if opening not in ("[", "{"):
            while self.peek() not in (",", "]", "}", "\n", ""):
                self.i += 1  # a scalar: a string, or words and dots (1.5, dates)
            return
        self.i, index = self.i + 1, 0
        while self.skip("\n", ",") not in ("]", "}"):
            if opening == "{":
                self.pair(path)
            else:
                self.lines.setdefault((*path, index), self.tokens[self.i][1])
                self.value((*path, index))
                index += 1
        self.i += 1
