"""The exercises (package data under `exercises/`) and an exercise's folder.

```
 exercises/NAME/exercise.toml   title, topic, kind (use | protocol), level, seeds, rule
                                (in words), rules (the kit's own, `rules.py`), step (a
                                protocol exercise's), hints, [yours] (what the student
                                may change: `Yours`; the rest is compared, `changed`)
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
from rr_actors_lab._tools.files import RefusedFileError, read_json, read_text

__all__ = [
    "EXERCISES",
    "STATE",
    "Exercise",
    "Yours",
    "changed",
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
fixes one step of the registrar (`rr_actors_lab.teach.STEPS`), in `step.py`."""


PLAN = "plan.toml"
"""The exercise's plan, in the starter and in a student's folder."""

COMPARED_BYTES = 4 * 1024 * 1024
"""The most bytes of a starter's file `changed` reads of a student's copy (a plan's bound,
as `rr-actors replay` reads one)."""

PLAN_PARTS = ("tree", "hosts.resolve")
"""The parts of a plan an exercise may give the student (`Yours.plan`)."""

MANAGER_KEYS_YOURS = frozenset({"restart"})
"""Of a manager's keys under a `[tree]` that is the student's, those that are the student's
too; its name, setup, options, host, isolation and timeouts are the exercise's (a setup that
loads nothing would skip the exercise)."""


@dataclasses.dataclass(frozen=True)
class Yours:
    """What a student may change in an exercise's folder (`[yours]` of `exercise.toml`).

    Everything else of the starter is compared with the shipped one when a folder is
    checked (`changed`): the grade is then about the student's part, run in the world the
    exercise shipped. Files the starter does not have (a module of the student's) are the
    student's.

    Attributes:
        files: starter files that are the student's, whole (`"step.py"`, `"actions.py"`).
        plan: parts of `plan.toml` that are the student's: `"tree"` (the supervisors, their
            strategies and intensities, the children's order, nesting and restart types;
            each manager's other keys are the exercise's), `"hosts.resolve"`.
    """

    files: tuple[str, ...] = ()
    plan: tuple[str, ...] = ()

    def words(self) -> str:
        """`step.py`, `[tree] of plan.toml`, ...: what is the student's, said."""
        parts = [*self.files]
        for part in self.plan:
            table, _, key = part.partition(".")
            parts.append(f"[{table}]{' ' + key if key else ''} of {PLAN}")
        return " and ".join(parts)


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
        yours: what the student may change (the rest is checked as shipped).
        options: a kit rule's settings, by the rule's name (`[holds]`: `rules.holds`'s).
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
    yours: Yours = Yours()
    options: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)

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
        yours=_yours(folder, data.get("yours", {})),
        options={r: dict(data[r]) for r in data.get("rules", ()) if isinstance(data.get(r), dict)},
    )


def _yours(folder: Path, data: dict[str, Any]) -> Yours:
    yours = Yours(tuple(data.get("files", ())), tuple(data.get("plan", ())))
    starter = {p.name for p in (folder / "starter").iterdir()}
    unknown = [f for f in yours.files if f not in starter] + [
        p for p in yours.plan if p not in PLAN_PARTS
    ]
    if not (yours.files or yours.plan) or unknown:  # (a shipped exercise: the tests read each)
        raise ConfigError(f"{folder.name}: [yours] names nothing, or what is not there: {unknown}")
    return yours


def changed(chosen: Exercise, folder: Path) -> str | None:
    """What `folder` changed that is not the student's to change, in one line; `None`: only
    the student's part changed (files the starter does not have are the student's).

    The starter's other files are compared as text (line ends and trailing spaces aside);
    `plan.toml` as TOML data (comments and layout aside), but for `Yours.plan`. Each is
    read within bounds (at most `COMPARED_BYTES`).

    Raises:
        RefusedFileError: one of them is not a regular file (a pipe, a device), is over
            `COMPARED_BYTES` or is not UTF-8 (`"<path>: <problem>"`).
    """
    yours = chosen.yours
    only = f"only {yours.words()} {'is' if len(yours.files) + len(yours.plan) < 2 else 'are'}"
    tail = f"{only} yours to change (`rr-actors teach start {chosen.name} FOLDER` shows it)"
    for name, shipped in chosen.starter().items():
        if name in yours.files:
            continue
        path = folder / name
        if not path.exists():  # (a pipe or a device is there: refused as such, not missing)
            return f"{name} is missing: it is the shipped exercise's; {tail}"
        what = "a plan" if name == PLAN else f"{chosen.name}'s {name}"
        text = read_text(path, COMPARED_BYTES, what)
        if name == PLAN:
            try:
                mine = tomllib.loads(text)
            except tomllib.TOMLDecodeError:
                continue  # (no plan at all: its reading says where, and nothing runs)
            where = _plan_change(tomllib.loads(shipped), mine, yours.plan)
            if where is not None:
                return f"{name}: {where}; {tail}"
        elif _lines(text) != _lines(shipped):
            return f"{name} differs from the shipped exercise; {tail}"
    return None


def _at(data: Any, path: tuple[Any, ...]) -> Any:
    for step in path:
        data = data[step]
    return data


def _lines(text: str) -> list[str]:
    return [line.rstrip() for line in text.strip().splitlines()]


def _plan_change(
    shipped: dict[str, Any], mine: dict[str, Any], parts: tuple[str, ...]
) -> str | None:
    """The first place `mine` differs from `shipped` outside the student's `parts`, said
    (`[[faults]] differs from the shipped exercise`)."""
    shipped, mine = dict(shipped), dict(mine)
    for part in parts:
        table, _, key = part.partition(".")
        if key:  # (one key of a table: the rest of the table is the exercise's)
            for data in (shipped, mine):
                if isinstance(data.get(table), dict):
                    data[table] = {k: v for k, v in data[table].items() if k != key}
            continue
        if table == "tree":
            found = _managers_change(shipped.get("tree", {}), mine.get("tree", {}))
            if found is not None:
                return found
        shipped.pop(table, None)
        mine.pop(table, None)
    path = _difference(shipped, mine, ())
    if path is None:
        return None
    where, missing, added = path
    said = _where(where, _at(shipped if missing or not added else mine, where))
    if missing:
        return f"{said} is missing (the shipped exercise has it)"
    if added:
        return f"{said} is not in the shipped exercise"
    return f"{said} differs from the shipped exercise"


def _managers_change(shipped: dict[str, Any], mine: dict[str, Any]) -> str | None:
    """A `[tree]` that is the student's: its managers must be the exercise's, by name (but
    their `MANAGER_KEYS_YOURS`), wherever the student placed them."""

    def managers(node: Any) -> dict[str, dict[str, Any]]:
        found: dict[str, dict[str, Any]] = {}
        for child in node.get("children", []) if isinstance(node, dict) else []:
            if not isinstance(child, dict):
                continue
            if "children" in child:
                found |= managers(child)
            else:
                name = str(child.get("name"))
                found[name] = {k: v for k, v in child.items() if k not in MANAGER_KEYS_YOURS}
        return found

    theirs, ours = managers(mine), managers(shipped)
    for name, manager in ours.items():
        if name not in theirs:
            return f"[[tree.children]] {name} is missing (the shipped exercise has it)"
        keys = sorted(
            set(manager) ^ set(theirs[name])
            | {k for k in manager if k in theirs[name] and manager[k] != theirs[name][k]}
        )
        if keys:
            return (
                f"[[tree.children]] {name}'s {keys[0]} differs from the shipped exercise "
                f"(a manager's {', '.join(sorted(MANAGER_KEYS_YOURS))} and place are yours)"
            )
    for name in theirs.keys() - ours.keys():
        return f"[[tree.children]] {name} is not in the shipped exercise"
    return None


_Difference = tuple[tuple[Any, ...], bool, bool]
"""Where two TOML values differ (its keys and indexes), missing there, added there."""


def _difference(shipped: Any, mine: Any, where: tuple[Any, ...]) -> _Difference | None:
    if isinstance(shipped, dict) and isinstance(mine, dict):
        for key in [*shipped, *(k for k in mine if k not in shipped)]:
            if key not in mine or key not in shipped:
                return (*where, key), key not in mine, key not in shipped
            found = _difference(shipped[key], mine[key], (*where, key))
            if found is not None:
                return found
        return None
    tables = isinstance(shipped, list) and all(isinstance(t, dict) for t in shipped)
    if tables and isinstance(mine, list) and len(mine) == len(shipped):
        for index, (a, b) in enumerate(zip(shipped, mine, strict=True)):
            found = _difference(a, b, (*where, index))
            if found is not None:
                return found
        return None
    return None if shipped == mine else (where, False, False)


def _where(path: tuple[Any, ...], value: Any) -> str:
    """Where `value` is in a plan, as its TOML says it: `[[workload.calls]] shared`,
    `[[faults]]`, `[workload] rate`, `[hosts]`, `duration`."""
    names = [p for p in path if isinstance(p, str)]
    arrays = any(isinstance(p, int) for p in path)
    if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        return f"[[{'.'.join(names)}]]"
    if isinstance(value, dict) and len(names) == 1:
        return f"[{names[0]}]"
    *tables, key = names
    if not tables:
        return key
    table = ".".join(tables)
    return f"[[{table}]] {key}" if arrays else f"[{table}] {key}"


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
