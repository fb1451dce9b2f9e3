"""The exercises (package data under `exercises/`) and an exercise's folder.

```
 exercises/NAME/exercise.toml   title, topic, kind (use | protocol), level, seeds, rule
                                (in words), rules (the kit's own, `rules.py`), step (a
                                protocol exercise's), hints
 exercises/NAME/README.md       the story, the rule, what to change
 exercises/NAME/starter/        the files a student starts from (plan.toml among them)
 exercises/NAME/solution/       the files the solution changes (the others: the starter's)
 exercises/NAME/wrong/          a wrong answer a student may write (optional): the files
                                it changes, for a teacher (the tests check it fails)
 a student's folder             README.md, the starter's files, .teach.json: the
                                exercise's name and the hints shown
```
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import reprlib
import tomllib
from pathlib import Path
from typing import Any

from rr_actors.errors import ConfigError
from rr_actors_lab._tools.files import RefusedFileError, read_json

__all__ = [
    "EXERCISES",
    "STATE",
    "Exercise",
    "exercise",
    "exercises",
    "folder_exercise",
    "next_hint",
    "solution_files",
    "start",
]

EXERCISES = Path(__file__).parent / "exercises"
"""Where the shipped exercises are: one folder each."""

STATE = ".teach.json"
"""The file in a student's folder that names its exercise and counts the hints shown."""

STATE_LIMIT = 64 * 1024
"""The most bytes of a folder's `STATE` read (its name and a count: a few dozen bytes)."""

KINDS = ("use", "protocol")
"""`use`: the student writes code or a plan as a user would; `protocol`: the student
fixes one step of the registrar (`rr_actors_lab.teach.replaced_step`)."""


@dataclasses.dataclass(frozen=True)
class Exercise:
    """One exercise, as its `exercise.toml` says.

    Attributes:
        name: its folder's name (what `start` takes).
        title: one line.
        topic: what it is about (a few words).
        kind: `"use"` or `"protocol"` (`KINDS`).
        level: 1 (first steps) to 3.
        seeds: how many seeds a check runs (1 to this).
        rule: the rule it is about, in words (what a failing check prints first).
        rules: the kit's own rules checked besides the checker's (`rules.RULES`).
        step: a protocol exercise's step (`rr_actors_lab.teach.STEPS`, `step.py`'s function of
            that name); `None` for a use exercise.
        hints: the hints, in the order `hint` gives them.
        folder: the exercise's folder in the package.
        most_restarts_per_s: the highest `max_restarts / period` a supervisor of the plan
            may have (it must stop a crash loop soon enough); `None`: any.
    """

    name: str
    title: str
    topic: str
    kind: str
    level: int
    seeds: int
    rule: str
    rules: tuple[str, ...]
    step: str | None
    hints: tuple[str, ...]
    folder: Path
    most_restarts_per_s: float | None = None

    def starter(self) -> dict[str, str]:
        """The starter's files: name to text."""
        return _files(self.folder / "starter")

    def solution(self) -> dict[str, str]:
        """The solution's files (the starter's, with those the solution changes)."""
        return {**self.starter(), **_files(self.folder / "solution")}

    def wrong(self) -> dict[str, str]:
        """A wrong answer's files (the starter's, with those it changes); `{}`: none shipped."""
        if not (self.folder / "wrong").is_dir():
            return {}
        return {**self.starter(), **_files(self.folder / "wrong")}

    def readme(self) -> str:
        """The README's text."""
        return (self.folder / "README.md").read_text(encoding="utf-8")


def _files(folder: Path) -> dict[str, str]:
    return {
        p.name: p.read_text(encoding="utf-8")
        for p in sorted(folder.iterdir())
        if p.is_file() and p.suffix in (".py", ".toml")
    }


def _read(folder: Path) -> Exercise:
    data: dict[str, Any] = tomllib.loads((folder / "exercise.toml").read_text(encoding="utf-8"))
    kind = data["kind"]
    if kind not in KINDS:  # (a shipped exercise: the tests read every one)
        raise ConfigError(f"{folder.name}: kind {kind!r} is not one of {KINDS}")
    return Exercise(
        name=folder.name,
        title=data["title"],
        topic=data["topic"],
        kind=kind,
        level=int(data["level"]),
        seeds=int(data["seeds"]),
        rule=" ".join(data["rule"].split()),
        rules=tuple(data.get("rules", ())),
        step=data.get("step"),
        hints=tuple(" ".join(h.split()) for h in data["hints"]),
        folder=folder,
        most_restarts_per_s=data.get("most_restarts_per_s"),
    )


def exercises() -> list[Exercise]:
    """The shipped exercises, by level then name."""
    found = [_read(p) for p in EXERCISES.iterdir() if (p / "exercise.toml").is_file()]
    return sorted(found, key=lambda e: (e.level, e.name))


def exercise(name: str) -> Exercise:
    """The shipped exercise `name`.

    Raises:
        ConfigError: no such exercise (the message names the closest ones, and `list`).
    """
    known = {e.name: e for e in exercises()}
    if name in known:
        return known[name]
    close = difflib.get_close_matches(name, list(known), n=2, cutoff=0.5)
    said = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
    raise ConfigError(
        f"no exercise {name!r}{said} (`rr-actors teach list` lists them: "
        f"{', '.join(sorted(known))})"
    )


def start(name: str, folder: Path | None) -> tuple[Exercise, Path]:
    """Write exercise `name`'s README and starter files into `folder` (default: ./NAME).

    Returns:
        The exercise and the folder written.

    Raises:
        ConfigError: no such exercise; `folder` exists and is not empty.
    """
    chosen = exercise(name)
    target = Path(name) if folder is None else folder
    if target.exists() and (not target.is_dir() or any(target.iterdir())):
        raise ConfigError(
            f"{target} exists and is not an empty folder: choose another one "
            f"(`rr-actors teach start {name} FOLDER`)"
        )
    target.mkdir(parents=True, exist_ok=True)
    (target / "README.md").write_text(chosen.readme(), encoding="utf-8")
    for file, text in chosen.starter().items():
        (target / file).write_text(text, encoding="utf-8")
    _save(target, {"exercise": chosen.name, "hints_shown": 0})
    return chosen, target


def folder_exercise(folder: Path) -> tuple[Exercise, dict[str, Any]]:
    """The exercise of a student's folder and its state (`STATE`).

    Raises:
        ConfigError: `folder` is not an exercise's folder (no `STATE` file, or one that
            does not name a shipped exercise); its `STATE` is not a regular file, holds more
            than `STATE_LIMIT` bytes, is not JSON or is nested too deeply (the message
            names it; nothing more is read).
    """
    path = folder / STATE
    try:
        state = read_json(path, STATE_LIMIT, "an exercise's state file")
    except RefusedFileError as exc:
        if not exc.missing:
            raise
        raise ConfigError(
            f"{folder} is not an exercise's folder (it has no {STATE}): start one with "
            "`rr-actors teach start NAME FOLDER`"
        ) from None
    if not isinstance(state, dict) or not isinstance(state.get("exercise"), str):
        shown = reprlib.repr(state)
        raise ConfigError(f"{path} is not an exercise's state file: no exercise's name in {shown}")
    return exercise(state["exercise"]), state


def next_hint(folder: Path) -> tuple[Exercise, int, str | None]:
    """The next hint of `folder`'s exercise, remembered as shown in its `STATE`.

    Returns:
        The exercise, the hint's number (1 first) and its text; past the last one: the
        number of hints and `None`.

    Raises:
        ConfigError: as `folder_exercise`.
    """
    chosen, state = folder_exercise(folder)
    shown = state.get("hints_shown", 0)
    if isinstance(shown, bool) or not isinstance(shown, int) or shown < 0:
        raise ConfigError(f"{folder / STATE}: hints_shown is not a count: {reprlib.repr(shown)}")
    if shown >= len(chosen.hints):
        return chosen, len(chosen.hints), None
    state["hints_shown"] = shown + 1
    _save(folder, state)
    return chosen, shown + 1, chosen.hints[shown]


def solution_files(chosen: Exercise) -> dict[str, str]:
    """The files the solution changes, name to text (what a teacher shows)."""
    return _files(chosen.folder / "solution")


def _save(folder: Path, state: dict[str, Any]) -> None:
    (folder / STATE).write_text(json.dumps(state, indent=2) + "\n", encoding="utf-8")
