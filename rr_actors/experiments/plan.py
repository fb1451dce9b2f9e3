"""A plan: the supervision tree, the workload, the faults and the repeats, read from TOML.

    PLAN.toml ──tomllib──► data ──_lines.key_lines──► {key path: line}
                             │
                             └──_Reader (one method per table)──► Plan (frozen dataclasses)
                                  every error: PlanError(file:line: key: what is wrong)

`load_plan(path)` and `parse_plan(text)` validate everything a run needs before anything
starts: unknown keys, types and ranges, setup and factory import paths (imported here,
with their options checked against their signatures), managers named by the workload and
the faults, fault kinds that need a process manager, and every value of `compare`
(each compared value makes one whole plan, validated like the first).

The format is documented in `docs/reference/plan.md`.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import importlib
import inspect
import math
import os
import string
import sys
import tomllib
import typing
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any, Literal, TypeAlias

from rr_actors import events
from rr_actors.config import Backoff
from rr_actors.errors import ConfigError
from rr_actors.experiments._lines import KeyPath, key_lines

__all__ = [
    "FAULT_KINDS",
    "PLACEHOLDERS",
    "CallMix",
    "Compare",
    "FaultPlan",
    "ManagerPlan",
    "Plan",
    "PlanError",
    "SupervisorPlan",
    "Trigger",
    "Workload",
    "import_object",
    "load_plan",
    "parse_plan",
    "search_path",
]

FaultKind = Literal[
    "kill_manager", "kill_resource", "hang_manager", "load_error", "cut_connections"
]

FAULT_KINDS: tuple[FaultKind, ...] = typing.get_args(FaultKind)
"""Every fault kind a plan may name (see `docs/reference/plan.md`)."""

_NEEDS_PROCESS = frozenset({"kill_resource", "hang_manager", "cut_connections"})
"""Fault kinds that act on a manager's OS process (its isolation must be `"process"`)."""

PLACEHOLDERS = frozenset({"key", "client", "run_dir", "pid"})
"""Names a request template may use in its strings: `{key}`, `{client}`, `{run_dir}`, `{pid}`."""

_EVENT_TYPES: dict[str, type[Any]] = {
    cls.__name__: cls for cls in typing.get_args(events.Event) if cls is not events.EventsDropped
}


class PlanError(ConfigError):
    """A plan is invalid: the message names the file, the line, the key and what is wrong.

    Attributes:
        source: the plan's file name (or `"<plan>"` for text without a file).
        line: the 1-based line of the key (0 if the plan has no such key, e.g. a
            missing one at the top).
        key: the key's dotted path, array elements as `[i]` (e.g. `faults[1].target`).
        problem: what is wrong, without the location.
    """

    def __init__(self, source: str, line: int, key: str, problem: str) -> None:
        where = f"{source}:{line}" if line else source
        super().__init__(f"{where}: {key}: {problem}" if key else f"{where}: {problem}")
        self.source = source
        self.line = line
        self.key = key
        self.problem = problem

    def __reduce__(self) -> tuple[Any, ...]:
        return (type(self), (self.source, self.line, self.key, self.problem))


# -- the plan as data -------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ManagerPlan:
    """One manager of the tree: what `ManagerSpec` it becomes in every run.

    Attributes:
        name: the manager's (registrar's) name.
        setup: import path of its `setup(registrar, **options)`, as `"module:function"`.
        options: keyword arguments for `setup`.
        isolation: `"process"` (default in plans) or `"thread"`.
        restart: `"permanent"`, `"transient"` or `"temporary"`.
        heartbeat: seconds between heartbeat pings, or `None` (off).
        heartbeat_timeout: seconds of silence before it counts as hung (`None`: three
            heartbeats).
        shutdown: seconds a clean stop may take before it is killed.
        start_timeout: seconds it may take to restore, set up and serve.
    """

    name: str
    setup: str
    options: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    isolation: Literal["thread", "process"] = "process"
    restart: Literal["permanent", "transient", "temporary"] = "permanent"
    heartbeat: float | None = 0.25
    heartbeat_timeout: float | None = None
    shutdown: float = 5.0
    start_timeout: float = 30.0


@dataclasses.dataclass(frozen=True)
class SupervisorPlan:
    """A supervisor of the tree (the top one is `Plan.tree`).

    Attributes:
        name: its name.
        children: its managers and nested supervisors, in start order.
        strategy: `"one_for_one"`, `"one_for_all"` or `"rest_for_one"`.
        max_restarts: restart intensity: at most this many restarts ...
        period: ... within this many seconds.
        backoff: delay before restarts.
        restart: its restart type in its parent (nested supervisors only).
    """

    name: str
    children: tuple[ManagerPlan | SupervisorPlan, ...]
    strategy: Literal["one_for_one", "one_for_all", "rest_for_one"] = "one_for_one"
    max_restarts: int = 3
    period: float = 5.0
    backoff: Backoff = dataclasses.field(default_factory=Backoff)
    restart: Literal["permanent", "transient", "temporary"] = "permanent"

    def managers(self) -> list[ManagerPlan]:
        """Every manager below this supervisor, depth first, in start order."""
        found: list[ManagerPlan] = []
        for child in self.children:
            found.extend(child.managers() if isinstance(child, SupervisorPlan) else [child])
        return found

    def supervisors(self) -> list[SupervisorPlan]:
        """This supervisor and every nested one, depth first."""
        found = [self]
        for child in self.children:
            if isinstance(child, SupervisorPlan):
                found.extend(child.supervisors())
        return found


@dataclasses.dataclass(frozen=True)
class CallMix:
    """One kind of call the workload makes (an entry of `[[workload.calls]]`).

    Attributes:
        manager: the provider registrar called.
        server: the resource server on it.
        weight: relative frequency of this kind among the workload's calls.
        shared: fraction of these calls that ask for one of `keys` shared requests
            (deduplicated by the provider); the rest ask for a request of their own.
        keys: how many distinct shared requests there are.
        request: the request template (strings may use `{key}`, `{client}`,
            `{run_dir}`; a string that is exactly `"{pid}"` becomes the run process's pid).
        factory: import path of `factory(key, context) -> request` instead of a template.
    """

    manager: str
    server: str
    weight: float = 1.0
    shared: float = 0.5
    keys: int = 4
    request: Any = "{key}"
    factory: str | None = None


@dataclasses.dataclass(frozen=True)
class Workload:
    """What the clients do while faults hit the tree.

    Attributes:
        clients: how many client threads call (each with a consumer registrar).
        rate: calls per second per client, or `None` for as fast as they can.
        arrivals: `"poisson"` (seeded random gaps of mean `1/rate`) or `"fixed"`.
        hold: seconds a client keeps each resource before it unloads it.
        timeout: seconds a call may take, retries through restarts included.
        calls: the mix of calls.
    """

    clients: int = 1
    rate: float | None = 5.0
    arrivals: Literal["poisson", "fixed"] = "poisson"
    hold: float = 0.5
    timeout: float = 5.0
    calls: tuple[CallMix, ...] = ()


@dataclasses.dataclass(frozen=True)
class Trigger:
    """`after = { event = "ChildRestarted", child = "erm", nth = 1 }`: when a fault fires.

    Attributes:
        event: an event type of `rr_actors.events` (e.g. `"ChildRestarted"`).
        match: field values the event must have (e.g. `{"child": "erm"}`).
        nth: the fault fires after the n-th matching event of the run.
    """

    event: str
    match: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    nth: int = 1


@dataclasses.dataclass(frozen=True)
class FaultPlan:
    """One entry of `[[faults]]`: what to do, to whom, and when.

    Exactly one of `at`, `every` and `after` says when.

    Attributes:
        kind: one of `FAULT_KINDS`.
        targets: the managers it may hit (one is picked per injection, seeded); for
            `kill_resource`, whose processes (empty: any process manager's).
        at: fixed times, seconds from the start of the workload.
        every: a fixed interval in seconds, or `(low, high)` for seeded random
            intervals drawn uniformly in between.
        start: with `every`: the first interval starts here (seconds).
        stop: with `every`: no injection at or after this time (default: the duration).
        count: with `every`: at most this many injections.
        after: inject when an event happens (then `delay` seconds later).
        delay: seconds from the trigger event to the injection.
        for_s: how long a hang (or a load error) lasts, in seconds.
        loads: `load_error`: how many loads raise (when `for_s` is not given).
        server: `load_error`: only loads of this server raise (default: any).
        message: `load_error`: the message of the exception the load raises.
    """

    kind: FaultKind
    targets: tuple[str, ...] = ()
    at: tuple[float, ...] = ()
    every: float | tuple[float, float] | None = None
    start: float = 0.0
    stop: float | None = None
    count: int | None = None
    after: Trigger | None = None
    delay: float = 0.0
    for_s: float | None = None
    loads: int = 1
    server: str | None = None
    message: str = "injected load error"


@dataclasses.dataclass(frozen=True)
class Compare:
    """`[compare]`: run the same plan once per value of one setting.

    Attributes:
        setting: the setting's dotted key (`"tree.strategy"`; a child by its name:
            `"tree.children.erm.heartbeat"`; a fault by its index: `"faults.0.every"`).
        values: the values, in the order the runs take them.
    """

    setting: str
    values: tuple[Any, ...]


@dataclasses.dataclass(frozen=True)
class Plan:
    """A whole experiment: validated, ready to run with `rr_actors.experiments.run`.

    Attributes:
        name: the plan's name (the `runs.csv` column `plan`).
        description: free text.
        duration: seconds of workload and faults per run.
        repeat: runs per compared value.
        seed: seed of the first run (run `i` of a value uses `seed + i`).
        recovery_timeout: seconds a run waits at its end for every manager to serve
            again before it unloads what the clients hold.
        tree: the top supervisor.
        state: whether managers keep durable catalogs (a state directory per run).
        workload: the clients.
        faults: the faults.
        compare: the compared setting, or `None`.
        variants: `(value, plan)` per compared value (`((None, self),)` without
            `compare`); each plan has that value applied and `compare` set to `None`.
        source: the file it was read from (`None` for text).
        base_dir: the directory searched first for the plan's import paths (the plan
            file's own), or `None`.
    """

    name: str
    duration: float
    tree: SupervisorPlan
    description: str = ""
    repeat: int = 1
    seed: int = 0
    recovery_timeout: float = 10.0
    state: bool = True
    workload: Workload = Workload(clients=0)
    faults: tuple[FaultPlan, ...] = ()
    compare: Compare | None = None
    variants: tuple[tuple[Any, Plan], ...] = dataclasses.field(
        default=(), repr=False, compare=False
    )
    source: str | None = None
    base_dir: str | None = None

    def managers(self) -> list[ManagerPlan]:
        """Every manager of the tree, depth first, in start order."""
        return self.tree.managers()

    def manager(self, name: str) -> ManagerPlan:
        """The manager called `name`.

        Raises:
            KeyError: no manager of that name.
        """
        for manager in self.managers():
            if manager.name == name:
                return manager
        raise KeyError(name)

    def setting_label(self) -> str:
        """The compared setting's key, or `""` without `compare`."""
        return self.compare.setting if self.compare is not None else ""

    def with_changes(
        self,
        *,
        repeat: int | None = None,
        seed: int | None = None,
        duration: float | None = None,
    ) -> Plan:
        """A copy with another `repeat`, `seed` or `duration` (for every compared value).

        A shorter `duration` drops the faults that would come after the new end.

        Raises:
            ConfigError: a value is out of range.
        """
        if repeat is not None and (isinstance(repeat, bool) or repeat < 1):
            raise ConfigError(f"repeat must be an int >= 1, got {repeat!r}")
        if duration is not None and not (_number(duration) and duration > 0):
            raise ConfigError(f"duration must be a positive number of seconds, got {duration!r}")
        changes: dict[str, Any] = {}
        if repeat is not None:
            changes["repeat"] = repeat
        if seed is not None:
            changes["seed"] = seed
        if duration is not None:
            changes["duration"] = float(duration)
        variants = tuple(
            (value, dataclasses.replace(plan, **changes)) for value, plan in self.variants
        )
        return dataclasses.replace(self, **changes, variants=variants)


# -- reading ------------------------------------------------------------------------------------


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


@contextlib.contextmanager
def search_path(directory: str | None) -> Iterator[None]:
    """Put `directory` first on `sys.path` while the block runs (nothing if `None`)."""
    if directory is None or directory in sys.path:
        yield
        return
    sys.path.insert(0, directory)
    try:
        yield
    finally:
        with contextlib.suppress(ValueError):
            sys.path.remove(directory)


def import_object(path: str, *, base_dir: str | None = None) -> Any:
    """Import `"package.module:attribute"` (the attribute may be dotted) and return it.

    Args:
        path: the import path.
        base_dir: a directory searched first (a plan's own directory), or `None`.

    Raises:
        ConfigError: the path is malformed, the module does not import, or it has no such
            attribute; the message says which.
    """
    module_name, colon, attribute = path.partition(":")
    if not colon or not module_name or not attribute:
        raise ConfigError(f"{path!r} is not an import path of the form 'package.module:name'")
    try:
        with search_path(base_dir):
            target: Any = importlib.import_module(module_name)
    except ImportError as exc:
        raise ConfigError(f"{path!r} does not import: {exc}") from exc
    except Exception as exc:
        raise ConfigError(f"{path!r}: importing {module_name} raised {exc!r}") from exc
    for part in attribute.split("."):
        try:
            target = getattr(target, part)
        except AttributeError:
            raise ConfigError(f"{path!r}: {module_name} has no attribute {attribute!r}") from None
    return target


def _number(value: object) -> bool:
    return (
        isinstance(value, int | float)
        and not isinstance(value, bool)
        and math.isfinite(float(value))
    )


def _dotted(path: KeyPath) -> str:
    text = ""
    for part in path:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else part)
    return text


Table: TypeAlias = dict[str, Any]


class _Reader:
    """Validates plan data, turning every problem into a `PlanError` with its line."""

    def __init__(self, source: str, lines: dict[KeyPath, int], base_dir: str | None) -> None:
        self.source = source
        self.lines = lines
        self.base_dir = base_dir

    # -- locating -------------------------------------------------------------------------

    def error(self, path: KeyPath, problem: str) -> PlanError:
        line = 0
        for end in range(len(path), 0, -1):
            if path[:end] in self.lines:
                line = self.lines[path[:end]]
                break
        return PlanError(self.source, line, _dotted(path), problem)

    def table(self, value: Any, path: KeyPath, known: tuple[str, ...]) -> Table:
        """`value` as a table with only `known` keys (else an error at the first other)."""
        if not isinstance(value, dict):
            raise self.error(path, f"must be a table, got {value!r}")
        for key in value:
            if key not in known:
                raise self.error(
                    (*path, key), f"unknown key; known here: {', '.join(sorted(known))}"
                )
        return value

    # -- typed values ---------------------------------------------------------------------

    def seconds(
        self, table: Table, path: KeyPath, key: str, default: Any, *, zero: bool = False
    ) -> Any:
        value = table.get(key, default)
        if key not in table:
            return value
        if not _number(value) or value < 0 or (value == 0 and not zero):
            kind = "a number of seconds >= 0" if zero else "a positive number of seconds"
            raise self.error((*path, key), f"must be {kind}, got {value!r}")
        return float(value)

    def integer(self, table: Table, path: KeyPath, key: str, default: Any, *, low: int) -> Any:
        value = table.get(key, default)
        if key not in table:
            return value
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise self.error((*path, key), f"must be an integer >= {low}, got {value!r}")
        return value

    def text(self, table: Table, path: KeyPath, key: str, default: Any) -> Any:
        value = table.get(key, default)
        if key in table and not isinstance(value, str):
            raise self.error((*path, key), f"must be a string, got {value!r}")
        return value

    def choice(self, table: Table, path: KeyPath, key: str, default: str, choices: Any) -> Any:
        value = table.get(key, default)
        if value not in choices:
            raise self.error(
                (*path, key), f"must be one of {', '.join(map(repr, choices))}, got {value!r}"
            )
        return value

    def required(self, table: Table, path: KeyPath, key: str) -> Any:
        if key not in table:
            raise self.error(path, f"{key!r} is missing")
        return table[key]

    def name(self, table: Table, path: KeyPath) -> str:
        value = self.required(table, path, "name")
        if (
            not isinstance(value, str)
            or not value
            or any(not (c.isalnum() or c in "_.-") for c in value)
        ):
            raise self.error(
                (*path, "name"),
                f"must be letters, digits, '_', '-' or '.', got {value!r}",
            )
        return value

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
        faults = tuple(
            self.fault(entry, ("faults", index), managers, duration)
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
            if not _number(item):
                raise self.error((*path, key), f"must be a number, got {item!r}")
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
        elif heartbeat is True or not _number(heartbeat) or heartbeat <= 0:
            raise self.error(
                (*path, "heartbeat"),
                f"must be a positive number of seconds or false (off), got {heartbeat!r}",
            )
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

    def importable(self, path: KeyPath, import_path: str) -> Callable[..., Any]:
        try:
            target = import_object(import_path, base_dir=self.base_dir)
        except ConfigError as exc:
            raise self.error(path, str(exc)) from None
        if not callable(target):
            raise self.error(path, f"{import_path!r} is not callable")
        return typing.cast("Callable[..., Any]", target)

    def signature_takes(
        self,
        path: KeyPath,
        function: Callable[..., Any],
        import_path: str,
        args: tuple[Any, ...],
        options: Table,
    ) -> None:
        try:
            signature = inspect.signature(function)
        except (TypeError, ValueError):
            return  # a builtin without a signature: it will tell at run time
        try:
            signature.bind(*args, **options)
        except TypeError as exc:
            raise self.error(path, f"{import_path} cannot be called with these: {exc}") from None

    # -- the workload ---------------------------------------------------------------------

    def workload(self, value: Any, managers: dict[str, ManagerPlan]) -> Workload:
        path: KeyPath = ("workload",)
        table = self.table(value, path, ("clients", "rate", "arrivals", "hold", "timeout", "calls"))
        clients = self.integer(table, path, "clients", 1, low=0)
        rate: Any = table.get("rate", 5.0)
        if rate == "max":
            rate = None
        elif not _number(rate) or rate <= 0:
            raise self.error(
                (*path, "rate"), f'must be calls per second (> 0) or "max", got {rate!r}'
            )
        calls_data = table.get("calls", [])
        if not isinstance(calls_data, list):
            raise self.error((*path, "calls"), "must be an array of tables ([[workload.calls]])")
        if clients and not calls_data:
            raise self.error(path, "'calls' is missing: what do the clients call?")
        calls = tuple(
            self.call(entry, (*path, "calls", index), managers)
            for index, entry in enumerate(calls_data)
        )
        return Workload(
            clients=clients,
            rate=None if rate is None else float(rate),
            arrivals=self.choice(table, path, "arrivals", "poisson", ("poisson", "fixed")),
            hold=self.seconds(table, path, "hold", 0.5, zero=True),
            timeout=self.seconds(table, path, "timeout", 5.0),
            calls=calls,
        )

    def call(self, value: Any, path: KeyPath, managers: dict[str, ManagerPlan]) -> CallMix:
        table = self.table(
            value, path, ("manager", "server", "weight", "shared", "keys", "request", "factory")
        )
        manager = self.required(table, path, "manager")
        if manager not in managers:
            raise self.error(
                (*path, "manager"),
                f"no manager {manager!r} in the tree (managers: {', '.join(managers)})",
            )
        server = self.required(table, path, "server")
        if not isinstance(server, str) or not server:
            raise self.error((*path, "server"), f"must be a server name, got {server!r}")
        weight = table.get("weight", 1.0)
        if not _number(weight) or weight <= 0:
            raise self.error((*path, "weight"), f"must be a positive number, got {weight!r}")
        shared = table.get("shared", 0.5)
        if not _number(shared) or not 0 <= shared <= 1:
            raise self.error((*path, "shared"), f"must be a fraction from 0 to 1, got {shared!r}")
        if "request" in table and "factory" in table:
            raise self.error((*path, "factory"), "give either 'request' or 'factory', not both")
        factory = self.text(table, path, "factory", None)
        if factory is not None:
            function = self.importable((*path, "factory"), factory)
            self.signature_takes((*path, "factory"), function, factory, ("key", None), {})
        request = table.get("request", "{key}")
        self.template(request, (*path, "request"))
        return CallMix(
            manager=manager,
            server=server,
            weight=float(weight),
            shared=float(shared),
            keys=self.integer(table, path, "keys", 4, low=1),
            request=request,
            factory=factory,
        )

    def template(self, value: Any, path: KeyPath) -> None:
        """Check the placeholders of every string in a request template."""
        if isinstance(value, dict):
            for key, item in value.items():
                self.template(item, (*path, key))
        elif isinstance(value, list):
            for index, item in enumerate(value):
                self.template(item, (*path, index))
        elif isinstance(value, str):
            try:
                fields = [f for _, f, _, _ in string.Formatter().parse(value) if f is not None]
            except ValueError as exc:
                raise self.error(path, f"{value!r} is not a valid template: {exc}") from None
            unknown = [f for f in fields if f not in PLACEHOLDERS]
            if unknown:
                raise self.error(
                    path,
                    f"unknown placeholder {{{unknown[0]}}}; known: "
                    + ", ".join(f"{{{p}}}" for p in sorted(PLACEHOLDERS)),
                )

    # -- the faults -----------------------------------------------------------------------

    def fault(
        self, value: Any, path: KeyPath, managers: dict[str, ManagerPlan], duration: float
    ) -> FaultPlan:
        table = self.table(
            value,
            path,
            (
                "kind",
                "target",
                "at",
                "every",
                "start",
                "stop",
                "count",
                "after",
                "delay",
                "for",
                "loads",
                "server",
                "message",
            ),
        )
        if "kind" not in table:
            raise self.error(path, f"'kind' is missing: one of {', '.join(FAULT_KINDS)}")
        kind = self.choice(table, path, "kind", "", FAULT_KINDS)
        targets = self.targets(table, path, kind, managers)
        at, every, after = self.when(table, path, duration)
        start = self.seconds(table, path, "start", 0.0, zero=True)
        stop = self.seconds(table, path, "stop", None)
        if stop is not None and stop <= start:
            raise self.error((*path, "stop"), f"must be after 'start' ({start:g} s)")
        for_s = self.seconds(table, path, "for", None)
        if kind == "hang_manager" and for_s is None:
            raise self.error(path, "'for' is missing: how many seconds the manager stays stopped")
        if "for" in table and kind not in ("hang_manager", "load_error"):
            raise self.error((*path, "for"), f"does not go with kind {kind!r}")
        for key in ("loads", "server", "message"):
            if key in table and kind != "load_error":
                raise self.error((*path, key), "only goes with kind 'load_error'")
        return FaultPlan(
            kind=kind,
            targets=targets,
            at=at,
            every=every,
            start=start,
            stop=stop,
            count=self.integer(table, path, "count", None, low=1),
            after=after,
            delay=self.seconds(table, path, "delay", 0.0, zero=True),
            for_s=for_s,
            loads=self.integer(table, path, "loads", 1, low=1),
            server=self.text(table, path, "server", None),
            message=self.text(table, path, "message", "injected load error"),
        )

    def when(
        self, table: Table, path: KeyPath, duration: float
    ) -> tuple[tuple[float, ...], float | tuple[float, float] | None, Trigger | None]:
        """A fault's `at`, `every` and `after` (exactly one of them is given)."""
        given = [key for key in ("at", "every", "after") if key in table]
        if len(given) != 1:
            problem = "say when: give one of 'at', 'every' or 'after'"
            if given:
                problem = f"give only one of 'at', 'every' or 'after', not {' and '.join(given)}"
            raise self.error(path, problem)
        for key in ("start", "stop", "count"):
            if key in table and "every" not in table:
                raise self.error((*path, key), "only goes with 'every'")
        if "delay" in table and "after" not in table:
            raise self.error((*path, "delay"), "only goes with 'after'")
        if "every" in table:
            return (), self.every(table, path), None
        if "after" in table:
            return (), None, self.trigger(table["after"], (*path, "after"))
        raw = table["at"] if isinstance(table["at"], list) else [table["at"]]
        where = (*path, "at")
        for index, item in enumerate(raw):
            item_path = (*where, index) if isinstance(table["at"], list) else where
            if not _number(item) or item < 0:
                raise self.error(item_path, f"must be seconds >= 0, got {item!r}")
            if item >= duration:
                raise self.error(
                    item_path, f"{item!r} s is not before the end of the run ({duration:g} s)"
                )
        return tuple(float(item) for item in raw), None, None

    def targets(
        self, table: Table, path: KeyPath, kind: str, managers: dict[str, ManagerPlan]
    ) -> tuple[str, ...]:
        value = table.get("target")
        where = (*path, "target")
        if value is None:
            if kind != "kill_resource":
                raise self.error(path, "'target' is missing: which manager (or a list of them)")
            return ()
        names = value if isinstance(value, list) else [value]
        if not names:
            raise self.error(where, "must name at least one manager")
        for index, name in enumerate(names):
            at = (*where, index) if isinstance(value, list) else where
            if name not in managers:
                raise self.error(
                    at, f"no manager {name!r} in the tree (managers: {', '.join(managers)})"
                )
            if kind in _NEEDS_PROCESS and managers[name].isolation != "process":
                raise self.error(
                    at, f"{kind} needs a process manager; {name!r} has isolation 'thread'"
                )
        return tuple(names)

    def every(self, table: Table, path: KeyPath) -> float | tuple[float, float]:
        value = table["every"]
        where = (*path, "every")
        if _number(value):
            if value <= 0:
                raise self.error(where, f"must be a positive number of seconds, got {value!r}")
            return float(value)
        span = self.table(value, where, ("min", "max"))
        low = self.seconds(span, where, "min", None)
        high = self.seconds(span, where, "max", None)
        if low is None or high is None:
            raise self.error(where, "needs both 'min' and 'max' (seconds)")
        if high < low:
            raise self.error((*where, "max"), f"must not be less than min ({low:g} s)")
        return (low, high)

    def trigger(self, value: Any, path: KeyPath) -> Trigger:
        if not isinstance(value, dict):
            raise self.error(
                path, f'must be a table like {{ event = "ChildRestarted" }}, got {value!r}'
            )
        event = self.required(value, path, "event")
        cls = _EVENT_TYPES.get(event) if isinstance(event, str) else None
        if cls is None:
            raise self.error(
                (*path, "event"),
                f"unknown event {event!r}; events: {', '.join(sorted(_EVENT_TYPES))}",
            )
        fields = [f.name for f in dataclasses.fields(cls) if f.name != "at"]
        self.table(value, path, ("event", "nth", *fields))
        match = {k: v for k, v in value.items() if k not in ("event", "nth")}
        return Trigger(event=event, match=match, nth=self.integer(value, path, "nth", 1, low=1))

    # -- compare --------------------------------------------------------------------------

    def compare(self, data: Table) -> Compare | None:
        if "compare" not in data:
            return None
        path: KeyPath = ("compare",)
        table = self.table(data["compare"], path, ("setting", "values"))
        setting = self.required(table, path, "setting")
        if not isinstance(setting, str) or not setting or setting.startswith("compare"):
            raise self.error((*path, "setting"), f"must be a plan key, got {setting!r}")
        values = self.required(table, path, "values")
        if not isinstance(values, list) or not values:
            raise self.error((*path, "values"), "must be a non-empty array")
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
