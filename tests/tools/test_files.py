"""A file the command line reads, read within bounds (`rr_actors_lab._tools.files`): a FIFO,
a device, a folder refused unread and named; a file past its limit, not UTF-8, not JSON or
nested too deeply refused in one line (issue 68 item 3)."""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import pytest

from rr_actors.errors import ConfigError
from rr_actors_lab._tools import files


@pytest.mark.parametrize(
    ("make", "kind"),
    [
        (os.mkfifo, "a pipe"),
        (lambda p: p.symlink_to("/dev/zero"), "a character device"),
        (Path.mkdir, "a directory"),
    ],
    ids=["fifo", "dev-zero", "folder"],
)
def test_what_is_not_a_regular_file_is_refused_unread_and_named(
    tmp_path: Path, make: object, kind: str
) -> None:
    path = tmp_path / "f"
    make(path)  # type: ignore[operator]

    with pytest.raises(files.RefusedFileError) as caught:
        files.read_text(path, 100, "a plan")  # (a FIFO nobody writes to: not waited on)

    assert f"{path}: not a regular file ({kind}): refused" == str(caught.value)
    assert (str(path), False) == (caught.value.path, caught.value.missing)
    assert isinstance(caught.value, ConfigError)


def test_a_missing_file_is_said_missing(tmp_path: Path) -> None:
    with pytest.raises(files.RefusedFileError) as caught:
        files.read_limited(tmp_path / "nothing", 10, "a plan")

    assert caught.value.missing
    assert "cannot be read (No such file or directory)" == caught.value.problem


def test_a_file_past_its_limit_is_refused_after_reading_the_limit_and_one_byte(
    tmp_path: Path,
) -> None:
    path = tmp_path / "big"
    with path.open("wb") as file:
        file.truncate(1 << 30)  # (sparse: a GiB that takes no disk)

    with pytest.raises(files.RefusedFileError, match=r"big: bigger than 1000 bytes: not a plan$"):
        files.read_limited(path, 1000, "a plan")
    assert b"x" * 1000 == (path.write_bytes(b"x" * 1000), files.read_limited(path, 1000, "a"))[1]


@pytest.mark.parametrize(
    ("data", "problem"),
    [
        (b"\xff", "is not UTF-8 text (invalid start byte)"),
        (b"{", "not JSON (Expecting property name enclosed in double quotes, line 1 column 2)"),
        (b"[" * 20_000 + b"]" * 20_000, "nested too deeply to read"),
        (b"9" * 5000, "a number of over 4300 digits"),
    ],
    ids=["not UTF-8", "not JSON", "too deep", "a huge integer"],
)
def test_json_that_cannot_be_read_is_refused_in_one_line(
    tmp_path: Path, data: bytes, problem: str
) -> None:
    path = tmp_path / "state.json"
    path.write_bytes(data)

    with pytest.raises(files.RefusedFileError) as caught:
        files.read_json(path, 64 * 1024, "a state file")

    assert caught.value.problem.startswith(problem)
    assert 1 == len(str(caught.value).splitlines())


def test_a_refusal_survives_pickling_with_its_fields(tmp_path: Path) -> None:
    refused = files.RefusedFileError(tmp_path / "x", "a problem", missing=True)

    again = pickle.loads(pickle.dumps(refused))

    assert (str(refused), again.path, again.problem, again.missing) == (
        str(again), str(tmp_path / "x"), "a problem", True,
    )  # fmt: skip
