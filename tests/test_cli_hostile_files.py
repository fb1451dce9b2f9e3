"""`rr-actors check` and `rr-actors events --merge` on files that are not events files.

Whatever the file holds (binary, JSON nested past the parser's stack, an integer of 5,000
digits, a time that is `NaN` or infinite, a `run` that is not a number, a line of 64 MiB,
nothing), or if it is missing or a directory, the command
prints one line naming the file (and the line) and exits with its error code: 2 for
`check`, 1 for `events`. No traceback.
"""

from __future__ import annotations

import io
import json
from collections.abc import Callable
from pathlib import Path

import pytest

from rr_actors import events
from rr_actors.__main__ import main
from rr_actors.events import lines

EVENT = events.to_dict(events.ResourceLoaded("erm", "cam", "r1", "q1", 0.1, at=1.0, pid=2))


def _event_line(**changes: object) -> bytes:
    return (json.dumps({**EVENT, **changes}) + "\n").encode()


FILES: dict[str, tuple[Callable[[Path], None], str, str]] = {
    # name: (how the file is made at the path, what check's error says, what events' says)
    "binary": (
        lambda p: p.write_bytes(_event_line() + b"\xff\xfe\x00\x01\n"),
        "line 2: not UTF-8",
        "line 2: not UTF-8",
    ),
    "nested": (
        lambda p: p.write_bytes(b"[" * 100_000 + b"\n"),
        "line 1: not JSON",
        "line 1: not JSON",
    ),
    "long integer": (  # (Python converts at most 4300 digits: CVE-2020-10735)
        lambda p: p.write_bytes(
            _event_line() + _event_line().replace(b'"pid": 2', b'"pid": 1' + b"0" * 5000)
        ),
        "line 2: not JSON that can be read (a number of more than 4300 digits)",
        "line 2: not JSON that can be read (a number of more than 4300 digits)",
    ),
    **{
        f"{name} at": (
            lambda p, text=text: p.write_bytes(
                _event_line() + _event_line().replace(b'"at": 1.0', b'"at": ' + text)
            ),
            "line 2: ResourceLoaded.at must be a finite number",
            "line 2: ResourceLoaded.at must be a finite number",
        )
        for name, text in (
            ("NaN", b"NaN"),
            ("infinite", b"Infinity"),
            ("minus infinite", b"-Infinity"),
            ("overflowing", b"1e999"),
            ("whole overflowing", b"1" + b"0" * 400),
        )
    },
    "missing": (lambda p: None, "no events.jsonl at", "cannot be read"),
    "directory": (lambda p: p.mkdir(), "no events.jsonl at", "cannot be read"),
}


@pytest.mark.parametrize("kind", sorted(FILES))
@pytest.mark.parametrize(("command", "code"), [("check", 2), ("events", 1)])
def test_a_file_that_cannot_be_read_is_one_line_naming_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], kind: str, command: str, code: int
) -> None:
    make, check_says, events_says = FILES[kind]
    says = check_says if command == "check" else events_says
    path = tmp_path / "events.jsonl"
    make(path)
    argv = ["check", str(path)] if command == "check" else ["events", "--merge", str(path)]

    assert code == main(argv, io.StringIO())

    err = capsys.readouterr().err
    assert (1, True, True) == (len(err.splitlines()), f"{path}" in err, says in err), err


@pytest.mark.parametrize("run", ["one", [1], -1, True])
def test_check_of_a_line_whose_run_is_not_a_run_number_names_the_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], run: object
) -> None:
    path = tmp_path / "events.jsonl"
    path.write_bytes(_event_line(run=0) + _event_line(run=run))

    assert 2 == main(["check", str(path)], io.StringIO())

    assert f"{path} line 2: run must be an int" in capsys.readouterr().err


def test_a_line_over_the_bound_is_refused_naming_it_without_reading_it_whole(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(lines, "MAX_LINE_BYTES", 1000)
    path = tmp_path / "events.jsonl"
    path.write_bytes(_event_line() + b'{"x": "' + b"x" * 5000 + b'"}\n')

    assert 1 == main(["events", "--merge", str(path)], io.StringIO())

    assert f"{path} line 2: longer than 1000 bytes" in capsys.readouterr().err


@pytest.mark.parametrize("text", ["", "\n\n", '{"not": "an event"}\n[1, 2]\n'])
def test_check_of_a_file_without_events_says_so_instead_of_printing_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str
) -> None:
    path = tmp_path / "events.jsonl"
    path.write_text(text)
    out = io.StringIO()

    assert 2 == main(["check", str(path)], out)

    assert ("", True) == (out.getvalue(), f"{path}: no events" in capsys.readouterr().err)


@pytest.mark.parametrize("option", [["--count", "0"], ["--count", "-1"], ["--seconds", "-5"]])
def test_events_with_a_count_or_seconds_that_is_not_positive_is_a_usage_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], option: list[str]
) -> None:
    path = tmp_path / "events.jsonl"
    path.write_bytes(_event_line() + _event_line(hlc=EVENT["hlc"] + 1))

    with pytest.raises(SystemExit) as exited:
        main(["events", "--merge", str(path), *option], io.StringIO())

    assert (2, True) == (exited.value.code, option[0] in capsys.readouterr().err)


@pytest.mark.parametrize(
    ("rows", "says"),
    [
        ({"consumers": [["q1"]]}, "CatalogRestored.consumers: a row of fewer than 3 fields"),
        ({"clients": [["q1", "erm"]]}, "CatalogRestored.clients: a row of fewer than 4 fields"),
        (
            {"resources": [["r1", "cam", "loaded", "x" * 5000]]},
            "CatalogRestored.resources: a digest that is not a whole number",
        ),
    ],
)
def test_check_of_a_catalog_row_it_cannot_read_names_the_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], rows: dict[str, object], says: str
) -> None:
    restored = events.to_dict(events.CatalogRestored("erm", (), (), (), at=1.0, pid=2))
    path = tmp_path / "events.jsonl"
    path.write_bytes(_event_line() + (json.dumps({**restored, **rows}) + "\n").encode())

    assert 2 == main(["check", str(path)], io.StringIO())

    err = capsys.readouterr().err
    assert (1, True) == (len(err.splitlines()), f"{path} line 2: {says}" in err), err
