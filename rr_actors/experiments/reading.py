"""Reading a plan: TOML text to a validated `Plan`, every problem a `PlanError` with its line.

    PLAN.toml ──tomllib──► data ──_lines.key_lines──► {key path: line}
                             │
                             └──_Reader (one method per table)──► Plan (frozen dataclasses)
                                  every error: PlanError(file:line: key: what is wrong)

`load_plan(path)` and `parse_plan(text)` validate everything a run needs before anything
starts: unknown keys, types and ranges, setup and factory import paths (imported here,
with their options checked against their signatures), managers named by the workload and
the faults, fault kinds that need a process manager, and every value of `compare`
(each compared value makes one whole plan, validated like the first). The typed reads
every table shares (seconds, integers, choices, import paths) are in `_checks`; the
plan's data classes in `plan`.

The format is documented in `docs/reference/plan.md`.
"""

from __future__ import annotations

import copy
import dataclasses
import os
import tomllib
from pathlib import Path
from typing import Any

from rr_actors.config import Backoff
from rr_actors.errors import ConfigError
from rr_actors.experiments._checks import Table
from rr_actors.experiments._lines import KeyPath, key_lines
from rr_actors.experiments._read_faults import FaultChecks
from rr_actors.experiments._read_workload import WorkloadChecks
from rr_actors.experiments.plan import (
    Compare,
    ManagerPlan,
    Plan,
    PlanError,
    SupervisorPlan,
    is_number,
)

__all__ = ["load_plan", "parse_plan"]


NOT_COMPARED = {
    "name": "every run of an experiment belongs to one plan",
    "description": "it changes nothing in a run",
    "seed": "each run's seed comes from the top 'seed' and its repeat",
    "repeat": "every compared value runs 'repeat' times",
    "compare": "compare is not a setting of a run",
}
"""Top-level keys `[compare]` refuses, and why (the experiment reads them from the top plan)."""


def load_plan(path: str | os.PathLike[str]) -> Plan:
    """Read and validate the plan in the TOML file `path`.

    Args:
        path: the plan file.

    Returns:
        The plan; its `name` defaults to the file's stem.

    Raises:
        PlanError: the file cannot be read, is not TOML, or is not a valid plan; the
            message names the file, the line and the key.
    """
    source = os.fspath(path)
    try:
        text = Path(source).read_text(encoding="utf-8")
    except OSError as exc:
        raise PlanError(source, 0, "", f"cannot be read ({exc.strerror or exc})") from exc
    except UnicodeDecodeError as exc:
        raise PlanError(source, 0, "", f"is not UTF-8 text ({exc.reason})") from exc
    return parse_plan(text, source=source, name=Path(source).stem)


def parse_plan(text: str, *, source: str = "<plan>", name: str = "plan") -> Plan:
    """Validate the plan in the TOML `text`.

    Args:
        text: the TOML document.
        source: how error messages name it (a file name).
        name: the plan's name if the text has no `name` key.

    Returns:
        The plan, with one variant per compared value.

    Raises:
        PlanError: the text is not TOML or not a valid plan.
    """
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        line = _decode_line(str(exc))
        raise PlanError(source, line, "", f"is not valid TOML: {exc}") from exc
    lines = key_lines(text)
    base_dir = None if source == "<plan>" else os.path.dirname(os.path.abspath(source))
    reader = _Reader(source, lines, base_dir)
    compare = reader.compare(data)
    base = reader.plan(data, name=name)
    if compare is None:
        return dataclasses.replace(base, variants=((None, base),))
    variants: list[tuple[Any, Plan]] = []
    for index, value in enumerate(compare.values):
        changed = copy.deepcopy(data)
        reader.apply(changed, compare.setting, value, ("compare", "values", index))
        try:
            variant = reader.plan(changed, name=name)
        except PlanError as exc:
            raise reader.error(
                ("compare", "values", index),
                f"with {compare.setting} = {value!r}: {exc.key}: {exc.problem}",
            ) from exc
        variants.append((value, variant))
    return dataclasses.replace(variants[0][1], compare=compare, variants=tuple(variants))


def _decode_line(message: str) -> int:
    marker = "(at line "
    if marker in message:
        tail = message.split(marker, 1)[1]
        digits = tail.split(",", 1)[0].split(")", 1)[0]
        if digits.isdigit():
            return int(digits)
    return 0


class _Reader(WorkloadChecks, FaultChecks):
    """Validates plan data table by table, turning every problem into a `PlanError`.

    The tree and `compare` are read here, the workload and the faults by its bases.
    """

    # -- the plan -------------------------------------------------------------------------

    def plan(self, data: Table, *, name: str) -> Plan:
        top = self.table(
            data,
            (),
            (
                "name",
                "description",
                "duration",
                "repeat",
                "seed",
                "recovery_timeout",
                "tree",
                "workload",
                "faults",
                "compare",
            ),
        )
        plan_name = self.text(top, (), "name", name)
        duration = self.seconds(top, (), "duration", None)
        if duration is None:
            raise self.error((), "'duration' is missing (seconds of workload and faults per run)")
        seed = top.get("seed", 0)
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise self.error(("seed",), f"must be an integer, got {seed!r}")
        tree, state = self.tree(self.required(top, (), "tree"))
        managers = {m.name: m for m in tree.managers()}
        workload = self.workload(top.get("workload", {"clients": 0}), managers)
        faults_data = top.get("faults", [])
        if not isinstance(faults_data, list):
            raise self.error(("faults",), "must be an array of tables ([[faults]])")
        nested = frozenset(s.name for s in tree.supervisors()[1:])
        names = {  # what the fields of an `after` trigger may name
            "supervisor": frozenset(s.name for s in tree.supervisors()),
            "child": frozenset(managers) | nested,
            "registrar": frozenset(managers)
            | frozenset(f"client-{i}" for i in range(workload.clients)),
        }
        faults = tuple(
            self.fault(entry, ("faults", index), managers, duration, names)
            for index, entry in enumerate(faults_data)
        )
        return Plan(
            name=plan_name,
            description=self.text(top, (), "description", ""),
            duration=duration,
            repeat=self.integer(top, (), "repeat", 1, low=1),
            seed=seed,
            recovery_timeout=self.seconds(top, (), "recovery_timeout", 10.0),
            tree=tree,
            state=state,
            workload=workload,
            faults=faults,
            source=None if self.source == "<plan>" else self.source,
            base_dir=self.base_dir,
        )

    def tree(self, value: Any) -> tuple[SupervisorPlan, bool]:
        path: KeyPath = ("tree",)
        table = self.table(
            value,
            path,
            ("name", "strategy", "max_restarts", "period", "backoff", "state", "children"),
        )
        state = table.get("state", True)
        if not isinstance(state, bool):
            raise self.error((*path, "state"), f"must be true or false, got {state!r}")
        table = {"name": "root", **table}
        table.pop("state", None)
        top = self.supervisor(table, path, top=True)
        seen: dict[str, KeyPath] = {}
        self.unique_names(top, path, seen)
        return top, state

    def unique_names(self, sup: SupervisorPlan, path: KeyPath, seen: dict[str, KeyPath]) -> None:
        for index, child in enumerate(sup.children):
            child_path = (*path, "children", index)
            if child.name in seen or child.name == sup.name:
                raise self.error(
                    (*child_path, "name"), f"the name {child.name!r} is used twice in the tree"
                )
            seen[child.name] = child_path
            if isinstance(child, SupervisorPlan):
                self.unique_names(child, child_path, seen)

    def supervisor(self, table: Table, path: KeyPath, *, top: bool = False) -> SupervisorPlan:
        known = ("name", "strategy", "max_restarts", "period", "backoff", "children")
        self.table(table, path, known if top else (*known, "restart"))
        children = self.required(table, path, "children")
        if not isinstance(children, list) or not children:
            raise self.error(
                (*path, "children"), "must be a non-empty array of tables ([[...children]])"
            )
        parsed: list[ManagerPlan | SupervisorPlan] = []
        for index, child in enumerate(children):
            child_path = (*path, "children", index)
            if not isinstance(child, dict):
                raise self.error(child_path, f"must be a table, got {child!r}")
            if "children" in child:
                parsed.append(self.supervisor(child, child_path))
            else:
                parsed.append(self.manager(child, child_path))
        return SupervisorPlan(
            name=self.name(table, path),
            children=tuple(parsed),
            strategy=self.choice(
                table,
                path,
                "strategy",
                "one_for_one",
                ("one_for_one", "one_for_all", "rest_for_one"),
            ),
            max_restarts=self.integer(table, path, "max_restarts", 3, low=0),
            period=self.seconds(table, path, "period", 5.0),
            backoff=self.backoff(table.get("backoff"), (*path, "backoff")),
            restart=self.choice(
                table, path, "restart", "permanent", ("permanent", "transient", "temporary")
            ),
        )

    def backoff(self, value: Any, path: KeyPath) -> Backoff:
        if value is None:
            return Backoff()
        table = self.table(value, path, ("initial", "factor", "max", "jitter"))
        for key, item in table.items():
            if not is_number(item):
                raise self.error((*path, key), f"must be a number, got {item!r}")
            if key in ("initial", "max"):
                self.check_seconds(item, (*path, key), zero=True)
        try:
            return Backoff(**{key: float(item) for key, item in table.items()})
        except ConfigError as exc:
            field = str(exc).split(" ", 1)[0].removeprefix("Backoff.")
            key = field if field in table else ""
            raise self.error((*path, key) if key else path, str(exc)) from None

    def manager(self, table: Table, path: KeyPath) -> ManagerPlan:
        self.table(
            table,
            path,
            (
                "name",
                "setup",
                "options",
                "isolation",
                "restart",
                "heartbeat",
                "heartbeat_timeout",
                "shutdown",
                "start_timeout",
            ),
        )
        name = self.name(table, path)
        setup = self.required(table, path, "setup")
        if not isinstance(setup, str):
            raise self.error((*path, "setup"), f"must be an import path string, got {setup!r}")
        options = table.get("options", {})
        if not isinstance(options, dict):
            raise self.error((*path, "options"), f"must be a table, got {options!r}")
        function = self.importable((*path, "setup"), setup)
        self.signature_takes((*path, "options"), function, setup, (None,), options)
        heartbeat = table.get("heartbeat", 0.25)
        if heartbeat is False:
            heartbeat = None
        elif heartbeat is True or not is_number(heartbeat) or heartbeat <= 0:
            raise self.error(
                (*path, "heartbeat"),
                f"must be a positive number of seconds or false (off), got {heartbeat!r}",
            )
        else:
            self.check_seconds(heartbeat, (*path, "heartbeat"))
        return ManagerPlan(
            name=name,
            setup=setup,
            options=options,
            isolation=self.choice(table, path, "isolation", "process", ("process", "thread")),
            restart=self.choice(
                table, path, "restart", "permanent", ("permanent", "transient", "temporary")
            ),
            heartbeat=None if heartbeat is None else float(heartbeat),
            heartbeat_timeout=self.seconds(table, path, "heartbeat_timeout", None),
            shutdown=self.seconds(table, path, "shutdown", 5.0),
            start_timeout=self.seconds(table, path, "start_timeout", 30.0),
        )

    # -- compare --------------------------------------------------------------------------

    def compare(self, data: Table) -> Compare | None:
        if "compare" not in data:
            return None
        path: KeyPath = ("compare",)
        table = self.table(data["compare"], path, ("setting", "values"))
        setting = self.required(table, path, "setting")
        if not isinstance(setting, str) or not setting:
            raise self.error((*path, "setting"), f"must be a plan key, got {setting!r}")
        if setting.split(".")[0] in NOT_COMPARED:
            raise self.error(
                (*path, "setting"),
                f"{setting!r} cannot be compared: {NOT_COMPARED[setting.split('.')[0]]}",
            )
        values = self.required(table, path, "values")
        if not isinstance(values, list) or not values:
            raise self.error((*path, "values"), "must be a non-empty array")
        for index, item in enumerate(values):
            if any(type(item) is type(other) and item == other for other in values[:index]):
                raise self.error(
                    (*path, "values", index), f"{item!r} is given twice: each value runs once"
                )
        self.locate(data, setting, (*path, "setting"))
        return Compare(setting=setting, values=tuple(values))

    def locate(self, data: Table, setting: str, where: KeyPath) -> tuple[Any, str | int]:
        """The container and key that `setting` names in `data` (its parent must exist)."""
        parts = setting.split(".")
        node: Any = data
        for part in parts[:-1]:
            node = self.step(node, part, setting, where)
        last = parts[-1]
        if isinstance(node, list):
            return node, self.index(node, last, setting, where)
        if not isinstance(node, dict):
            raise self.error(where, f"{setting!r} does not name a setting of this plan")
        return node, last

    def step(self, node: Any, part: str, setting: str, where: KeyPath) -> Any:
        if isinstance(node, dict):
            if part not in node:
                raise self.error(where, f"{setting!r}: this plan has no {part!r} there")
            return node[part]
        if isinstance(node, list):
            return node[self.index(node, part, setting, where)]
        raise self.error(where, f"{setting!r} does not name a setting of this plan")

    def index(self, node: list[Any], part: str, setting: str, where: KeyPath) -> int:
        for index, item in enumerate(node):
            if isinstance(item, dict) and item.get("name") == part:
                return index
        if part.isdigit() and int(part) < len(node):
            return int(part)
        raise self.error(where, f"{setting!r}: no element named {part!r}")

    def apply(self, data: Table, setting: str, value: Any, where: KeyPath) -> None:
        container, key = self.locate(data, setting, where)
        container[key] = value
