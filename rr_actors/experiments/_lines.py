"""Where each key of a TOML file is: a small scanner that maps key paths to line numbers.

`tomllib` gives the data but no positions, and a plan's errors must name the line. This
scanner walks the text once more, after `tomllib` accepted it (so it never sees invalid
TOML), and records the line of every key, table header and array element:

    [tree]                       ("tree",)                          -> 1
    strategy = "one_for_one"     ("tree", "strategy")               -> 2
    [[tree.children]]            ("tree", "children", 0)            -> 3
    name = "erm"                 ("tree", "children", 0, "name")    -> 4
    options = { rate = 2 }       ("tree", "children", 0, "options", "rate") -> 5

Array elements are addressed by their index, as in the data `tomllib` returns, so a
validator that walks the data can ask for the line of the path it is at.
"""

from __future__ import annotations

__all__ = ["KeyPath", "key_lines"]

KeyPath = tuple[str | int, ...]
"""A path into the data: table keys (`str`) and array indices (`int`)."""

_BARE = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_-")


class _Scanner:
    """One pass over valid TOML text, recording `KeyPath -> line` (1-based)."""

    def __init__(self, text: str) -> None:
        self.text = text
        self.i = 0
        self.line = 1
        self.lines: dict[KeyPath, int] = {}
        self.arrays: dict[KeyPath, int] = {}  # arrays of tables: index of the last element

    # -- characters ----------------------------------------------------------------------

    def peek(self, ahead: int = 0) -> str:
        j = self.i + ahead
        return self.text[j] if j < len(self.text) else ""

    def advance(self, n: int = 1) -> None:
        for _ in range(n):
            if self.peek() == "\n":
                self.line += 1
            self.i += 1

    def skip_blank(self, *, newlines: bool) -> None:
        """Skip spaces and tabs (and line breaks and comments with `newlines`)."""
        while self.i < len(self.text):
            ch = self.peek()
            if ch in " \t\r" or (newlines and ch == "\n"):
                self.advance()
            elif ch == "#" and newlines:
                while self.i < len(self.text) and self.peek() != "\n":
                    self.advance()
            else:
                return

    # -- grammar -------------------------------------------------------------------------

    def scan(self) -> dict[KeyPath, int]:
        table: KeyPath = ()
        while True:
            self.skip_blank(newlines=True)
            if self.i >= len(self.text):
                return self.lines
            if self.peek() == "[":
                table = self.header()
            else:
                line = self.line
                path = table + self.key()
                self.lines.setdefault(path, line)
                self.skip_blank(newlines=False)
                self.advance()  # "="
                self.value(path)

    def header(self) -> KeyPath:
        line = self.line
        double = self.peek(1) == "["
        self.advance(2 if double else 1)
        parts = self.key()
        self.skip_blank(newlines=False)
        self.advance(2 if double else 1)
        resolved: list[str | int] = []
        for n, part in enumerate(parts):
            resolved.append(part)
            last = n == len(parts) - 1
            key = tuple(resolved)
            if double and last:
                self.arrays[key] = self.arrays.get(key, -1) + 1
                self.lines.setdefault(key, line)
                resolved.append(self.arrays[key])
            elif key in self.arrays:
                resolved.append(self.arrays[key])
        path = tuple(resolved)
        self.lines.setdefault(path, line)
        return path

    def key(self) -> tuple[str, ...]:
        """A dotted key (bare or quoted parts); stops before `=` or `]`."""
        parts: list[str] = []
        while True:
            self.skip_blank(newlines=False)
            ch = self.peek()
            if ch in "\"'":
                parts.append(self.string())
            else:
                start = self.i
                while self.peek() in _BARE and self.peek():
                    self.advance()
                parts.append(self.text[start : self.i])
            self.skip_blank(newlines=False)
            if self.peek() != ".":
                return tuple(parts)
            self.advance()

    def string(self) -> str:
        """A string of any of TOML's four kinds; returns its text (escapes left as they are)."""
        quote = self.peek()
        if self.text.startswith(quote * 3, self.i):
            self.advance(3)
            start = self.i
            while not self.text.startswith(quote * 3, self.i):
                if quote == '"' and self.peek() == "\\":
                    self.advance()
                self.advance()
            end = self.i
            self.advance(3)
            while self.peek() == quote:  # up to two quotes may end the content
                self.advance()
                end += 1
            return self.text[start:end]
        self.advance()
        start = self.i
        while self.peek() != quote:
            if quote == '"' and self.peek() == "\\":
                self.advance()
            self.advance()
        end = self.i
        self.advance()
        return self.text[start:end]

    def value(self, path: KeyPath) -> None:
        self.skip_blank(newlines=False)
        ch = self.peek()
        if ch == "{":
            self.advance()
            while True:
                self.skip_blank(newlines=True)
                if self.peek() == "}":
                    self.advance()
                    return
                if self.peek() == ",":
                    self.advance()
                    continue
                line = self.line
                inner = path + self.key()
                self.lines.setdefault(inner, line)
                self.skip_blank(newlines=False)
                self.advance()  # "="
                self.value(inner)
        elif ch == "[":
            self.advance()
            index = 0
            while True:
                self.skip_blank(newlines=True)
                if self.peek() == "]":
                    self.advance()
                    return
                if self.peek() == ",":
                    self.advance()
                    continue
                self.lines.setdefault((*path, index), self.line)
                self.value((*path, index))
                index += 1
        elif ch in "\"'":
            self.string()
        else:
            while self.i < len(self.text) and self.peek() not in ",]}#\n":
                self.advance()


def key_lines(text: str) -> dict[KeyPath, int]:
    """Map every key, table and array element of `text` to its 1-based line.

    Args:
        text: a TOML document that `tomllib` parses (invalid TOML gives meaningless lines).

    Returns:
        `{path: line}`, e.g. `{("tree", "children", 0, "name"): 4}`.
    """
    return _Scanner(text).scan()
