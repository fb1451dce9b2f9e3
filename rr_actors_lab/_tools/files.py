"""A file the command line reads from a folder it was given, read within bounds.

```
 path ─os.open(O_NONBLOCK)─► fd ─fstat: a regular file? (a pipe, a device, a folder:
   refused unread, named) ─read(limit + 1)─► bytes (more: refused, "bigger than")
   ─► text (not UTF-8: refused) ─► JSON (not JSON, nested too deeply, a number of
   too many digits: refused)
```

Every refusal is a `RefusedFileError` (a `ConfigError`): one line naming the file and
what it is, so a command says it in one line and exits as it documents; memory and time
stay within the limit whatever the path leads to (`/dev/zero`, a FIFO nobody writes, a
100k-deep JSON array). Shared by `rr-actors replay` and `shrink` (a run directory's
`plan.toml`, `seeds.jsonl`), plans (`load_plan`) and the classroom kit (`.teach.json`).
"""

from __future__ import annotations

import contextlib
import json
import os
import stat
import sys
from collections.abc import Iterator
from typing import Any, BinaryIO

from rr_actors.errors import ConfigError

__all__ = ["RefusedFileError", "open_regular", "read_json", "read_limited", "read_text"]


class RefusedFileError(ConfigError):
    """A file refused unread or read no further: `"<path>: <problem>"`.

    Attributes:
        path: the file, as given.
        problem: what is wrong with it, without the path.
        missing: it does not exist (a broken link included).
    """

    def __init__(
        self, path: str | os.PathLike[str], problem: str, *, missing: bool = False
    ) -> None:
        super().__init__(f"{os.fspath(path)}: {problem}")
        self.path, self.problem, self.missing = os.fspath(path), problem, missing

    def __reduce__(self) -> tuple[Any, ...]:
        return (_refused, (self.path, self.problem, self.missing))


def _refused(path: str, problem: str, missing: bool) -> RefusedFileError:
    return RefusedFileError(path, problem, missing=missing)


@contextlib.contextmanager
def open_regular(path: str | os.PathLike[str]) -> Iterator[BinaryIO]:
    """`path` opened in binary if it is a regular file: opened without blocking (a FIFO
    nobody writes to does not hang it), checked on the descriptor (not raced by a rename).

    Raises:
        RefusedFileError: it cannot be opened, or is not a regular file (what it is, named);
            a read inside the block failed.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except OSError as exc:
        missing = isinstance(exc, FileNotFoundError)
        raise RefusedFileError(path, _cannot(exc), missing=missing) from None
    try:
        mode = os.fstat(fd).st_mode
    except OSError as exc:
        os.close(fd)
        raise RefusedFileError(path, _cannot(exc)) from None
    if not stat.S_ISREG(mode):
        os.close(fd)
        raise RefusedFileError(path, f"not a regular file ({_file_kind(mode)}): refused")
    with os.fdopen(fd, "rb") as file:
        try:
            yield file
        except OSError as exc:
            raise RefusedFileError(path, _cannot(exc)) from None


def read_limited(path: str | os.PathLike[str], limit: int, what: str) -> bytes:
    """The bytes of regular file `path`, at most `limit` of them (`what` it should be, in
    words: "a plan" says `bigger than LIMIT bytes: not a plan`).

    Raises:
        RefusedFileError: as `open_regular`; it holds more than `limit` bytes.
    """
    with open_regular(path) as file:
        data = file.read(limit + 1)
    if len(data) > limit:
        raise RefusedFileError(path, f"bigger than {limit} bytes: not {what}")
    return data


def read_text(path: str | os.PathLike[str], limit: int, what: str) -> str:
    """The UTF-8 text of regular file `path`, at most `limit` bytes of it.

    Raises:
        RefusedFileError: as `read_limited`; it is not UTF-8.
    """
    data = read_limited(path, limit, what)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise RefusedFileError(path, f"is not UTF-8 text ({exc.reason})") from None


def read_json(path: str | os.PathLike[str], limit: int, what: str) -> Any:
    """The JSON value in regular file `path`, at most `limit` bytes of it.

    Raises:
        RefusedFileError: as `read_text`; it is not JSON, is nested too deeply to read
            (Python's recursion limit), or holds a number of more digits than Python
            converts.
    """
    text = read_text(path, limit, what)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        problem = f"not JSON ({exc.msg}, line {exc.lineno} column {exc.colno}): not {what}"
        raise RefusedFileError(path, problem) from None
    except RecursionError:
        raise RefusedFileError(path, f"nested too deeply to read: not {what}") from None
    except ValueError:  # (an integer past Python's limit of digits)
        digits = sys.get_int_max_str_digits()
        raise RefusedFileError(path, f"a number of over {digits} digits: not {what}") from None


def _cannot(exc: OSError) -> str:
    return f"cannot be read ({exc.strerror or exc})"


def _file_kind(mode: int) -> str:
    """What a file that is not a regular one is, in words."""
    for test, kind in (
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISFIFO, "a pipe"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return kind
    return "not a file"
