"""Reading a plan: TOML text to a validated `Plan`, every problem a `PlanError` with its line.

    PLAN.toml ─tomllib─► data ─_Reader.decode: table by table into `plan`'s dataclasses, each
    value ─msgspec.convert(value, its field's annotated type)─► Plan ─► the rules between values

`_problem` words msgspec's errors, `_lines.line_of` finds their line. The format is
documented in `docs/reference/plan.md`.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import inspect
import operator
import os
import re
import string
import tomllib
import typing
from dataclasses import MISSING
from pathlib import Path
from typing import Any

import msgspec

from rr_actors.errors import ConfigError
from rr_actors.experiments import plan as schema
from rr_actors.experiments._imports import import_object
from rr_actors.experiments._lines import KeyPath, held, line_of
from rr_actors.experiments.plan import Plan, PlanError

__all__ = ["load_plan", "parse_plan"]

# -- the words of the errors, as data ---------------------------------------------------------
WHAT = {  # what a key must be, where its type alone words it badly (the last key of the path)
    "target": "a manager's name",
    "manager": "a manager's name",
    "setup": "an import path string",
    "name": "letters, digits, '_', '-' or '.'",
    "server": "a server name",
    "heartbeat": "a positive number of seconds or false (off)",
    "rate": f"calls per second (at least {1 / schema.MAX_SECONDS:g}, at most {schema.MAX_RATE:g})"
    ' or "max"',
    "weight": f"a positive number (at most {schema.MAX_RATE:g})",
    "shared": "a fraction from 0 to 1",
    "factor": f"a number from 1 to {schema.MAX_SECONDS:g}",
    "children": "a non-empty array of tables ([[...children]])",
    "setting": "a plan key",
}
PURPOSE = {  # what a missing key is for
    "duration": " (seconds of workload and faults per run)",
    "kind": f": one of {', '.join(schema.FAULT_KINDS)}",
    "target": ": which manager (or a list of them)",
    "for": ": how many seconds the manager stays stopped",
}
TYPES = {"float": "a number", "int": "an integer", "str": "a string", "bool": "true or false"}
TYPES |= {"array": "an array", "object": "a table"}
SECONDS = (schema.Seconds, schema.SecondsOrZero, schema.Interval)
NOT_COMPARED = {  # top-level keys `[compare]` refuses, and why
    "name": "every run of an experiment belongs to one plan",
    "description": "it changes nothing in a run",
    "seed": "each run's seed comes from the top 'seed' and its repeat",
    "repeat": "every compared value runs 'repeat' times",
    "compare": "compare is not a setting of a run",
}
# -- how keys become fields -------------------------------------------------------------------
TOML_KEY = {"targets": "target", "for_s": "for"}  # field -> key, where they differ
NOT_KEYS = ("state", "variants", "source", "base_dir")  # `Plan` fields no key gives
OFF = {"heartbeat": False, "rate": "max"}  # the value that makes the field `None`
HINT = {"initial": schema.SecondsOrZero, "max": schema.SecondsOrZero}  # `Backoff`'s, limited
LISTS = ("at", "target")  # a fault's keys that take one value or an array of them
# -- a fault's keys that only go with another key, or with some kinds ---------------------------
NEEDS_KEY = {"start": "every", "stop": "every", "count": "every", "delay": "after"}
NEEDS_KIND = {"for": ("hang_manager", "load_error"), "loads": ("load_error",)}
NEEDS_KIND |= {"server": ("load_error",), "message": ("load_error",)}


def load_plan(path: str | os.PathLike[str]) -> Plan:
    """Read and validate the plan in the TOML file `path` (its `name` defaults to the stem).

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
    """Validate the plan in the TOML `text` (`source` names it in errors): a variant per value.

    Raises:
        PlanError: the text is not TOML or not a valid plan.
    """
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        line = re.search(r"\(at line (\d+)", str(exc))
        problem = f"is not valid TOML: {exc}"
        raise PlanError(source, int(line[1]) if line else 0, "", problem) from exc
    base_dir = None if source == "<plan>" else os.path.dirname(os.path.abspath(source))
    reader = _Reader(source, text, base_dir)
    base = reader.plan(data, name=name)
    if (compare := base.compare) is None:
        return dataclasses.replace(base, variants=((None, base),))
    variants: list[tuple[Any, Plan]] = []
    for index, value in enumerate(compare.values):
        changed, where = copy.deepcopy(data), ("compare", "values", index)
        container, key = reader.locate(changed, compare.setting, where)
        container[key] = value
        try:
            plan = reader.plan(changed, name=name, variant=True)
            variants.append((value, dataclasses.replace(plan, compare=None)))
        except PlanError as exc:
            problem = f"with {compare.setting} = {_show(value)}: {exc.key}: {exc.problem}"
            raise reader.error(where, problem) from exc
    return dataclasses.replace(variants[0][1], compare=compare, variants=tuple(variants))


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else f"{text[:57]}..."


def _problem(message: str, key: str, value: Any, hint: Any) -> str:
    """msgspec's `message` about `value` of `key` (of type `hint`), in the plan's words."""
    bound = re.fullmatch(r"Expected `(int|float)` ([<>]=?) (\S+)", message)
    typed = re.fullmatch(r"Expected `([^`]*)`, got `\w+`", message)
    what = f"{message[0].lower()}{message[1:]}"  # msgspec's own words, if none of these
    if key in WHAT and not (bound and key == "heartbeat"):
        what = f"must be {WHAT[key]}"
    elif message.startswith("Invalid enum value") or hasattr(hint, "__members__"):
        choices = typing.get_args(hint) or tuple(getattr(hint, "__members__", ()))
        what = f"must be one of {', '.join(map(repr, choices))}"
    elif bound and bound[1] == "int":
        what = f"must be an integer {bound[2]} {bound[3]}"
    elif bound and bound[2] == "<=":
        what = f"must be at most {float(bound[3]):g} s (about {float(bound[3]) / 86400:.1f} days)"
    elif bound:
        zero = {">": "a positive number of seconds", ">=": "seconds >= 0"}[bound[2]]
        what = f"must be {zero if float(bound[3]) == 0 else f'at least {float(bound[3]):g} s'}"
    elif typed:
        kinds = [TYPES.get(kind, kind) for kind in typed[1].split(" | ") if kind != "null"]
        seconds = hint in SECONDS or any(h in SECONDS for h in typing.get_args(hint))
        kinds = [f"{k} of seconds" if seconds and k == "a number" else k for k in kinds]
        what = f"must be {' or '.join(kinds)}"
    return f"{what}, got {_show(value)}"


class _Reader:
    """Reads plan data into a `Plan`, turning every problem into a `PlanError`."""

    def __init__(self, source: str, text: str, base_dir: str | None) -> None:
        self.source, self.text, self.base_dir = source, text, base_dir
        self.data: dict[str, Any] = {}
        self.state, self.managers = True, dict[str, schema.ManagerPlan]()  # of the last plan
        self.hooks = {"tree": self.root, "every": self.every, "after": self.trigger}

    # -- the generic part: where, unknown and missing keys, typed values ---------------------

    def error(self, path: KeyPath, problem: str) -> PlanError:
        """A `PlanError` at the part of `path` written (`at = 1` is checked as `[1]`)."""
        path = held(self.data, path)
        line = line_of(self.text, [path[:end] for end in range(len(path), 0, -1)])
        key = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in path).lstrip(".")
        return PlanError(self.source, line, key, problem)

    def refuse(self, wrong: object, path: KeyPath, problem: str) -> None:
        """A rule: a `PlanError` at `path` if `wrong` is true."""
        if wrong:
            raise self.error(path, problem)

    def table(self, value: Any, path: KeyPath, known: tuple[str, ...]) -> dict[str, Any]:
        """`value` as a table with only `known` keys (else an error at the first other)."""
        self.refuse(not isinstance(value, dict), path, f"must be a table, got {_show(value)}")
        for key in (k for k in value if k not in known):
            raise self.error((*path, key), f"unknown key; known here: {', '.join(sorted(known))}")
        return typing.cast(dict[str, Any], value)

    def check(self, value: Any, hint: Any, path: KeyPath) -> Any:
        """`value` converted to the annotated type `hint` by msgspec, or a `PlanError`."""
        try:
            return msgspec.convert(value, hint)
        except msgspec.ValidationError as exc:
            message, _, inner = str(exc).partition(" - at `$")
            steps = (int(i) if i else k for i, k in re.findall(r"\[(\d+)\]|\.(\w+)", inner))
            path = held(self.data, (*path, *steps))
            key = next((p for p in reversed(path) if isinstance(p, str)), "")
            raise self.error(path, _problem(message, key, self.raw(path), hint)) from None

    def raw(self, path: KeyPath) -> Any:
        data: Any = self.data
        return functools.reduce(operator.getitem, path, data)  # the value as written

    def decode(self, cls: Any, value: Any, path: KeyPath) -> Any:
        """A `cls` (a dataclass of `plan`) from the table `value`, every field checked."""
        hints = typing.get_type_hints(cls, include_extras=True)
        keys = {TOML_KEY.get(f.name, f.name): f for f in dataclasses.fields(cls)}
        table = self.table(value, path, tuple(k for k in keys if k not in NOT_KEYS))
        for key in (k for k, f in keys.items() if f.default is f.default_factory is MISSING):
            self.refuse(key not in table, path, f"{key!r} is missing{PURPOSE.get(key, '')}")
        given = {
            keys[k].name: self.value(k, x, hints[keys[k].name], path) for k, x in table.items()
        }
        try:
            return cls(**given)
        except ConfigError as exc:  # a `Backoff` checks itself: "Backoff.max must ..."
            bad = str(exc).split()[0].removeprefix("Backoff.")
            raise self.error((*path, bad), str(exc)) from None

    def value(self, key: str, item: Any, hint: Any, table: KeyPath) -> Any:
        """`item` of `key` as `hint`: by a hook, or a plan dataclass decoded, else by msgspec."""
        path = (*table, key)
        if key in self.hooks:
            return self.hooks[key](item, path)
        if key in OFF and type(item) is type(OFF[key]) and item == OFF[key]:
            return None
        many = typing.get_origin(hint) is tuple  # an array of tables, or a table
        inner = typing.get_args(hint)[0] if many else hint
        classes = [c for c in typing.get_args(inner) or (inner,) if dataclasses.is_dataclass(c)]
        if not classes:
            item = [item] if key in LISTS and not isinstance(item, list) else item
            return self.check(item, HINT.get(key, hint), path)
        if not many:
            return self.decode(classes[0], item, path)
        items = self.check(item, list[dict[str, Any]], path)  # a supervisor has children:
        return tuple(
            self.decode(classes[-1] if "children" in x else classes[0], x, (*path, i))
            for i, x in enumerate(items)
        )

    def importable(self, path: KeyPath, name: str, call: KeyPath, *args: Any, **kw: Any) -> None:
        """Import `name`; check that it can be called with `args` and `kw` (at `call`)."""
        try:
            target = import_object(name, base_dir=self.base_dir)
        except ConfigError as exc:
            raise self.error(path, str(exc)) from None
        self.refuse(not callable(target), path, f"{name!r} is not callable")
        try:
            inspect.signature(target).bind(*args, **kw)
        except ValueError:
            return  # a builtin without a signature: it will tell at run time
        except TypeError as exc:
            raise self.error(call, f"{name} cannot be called with these: {exc}") from None

    # -- the plan and the rules between its values ---------------------------------------------

    def plan(self, data: dict[str, Any], *, name: str, variant: bool = False) -> Plan:
        self.data = {"name": name, **data}
        plan: Plan = self.decode(Plan, self.data, ())
        source = None if self.source == "<plan>" else self.source
        plan = dataclasses.replace(plan, state=self.state, source=source, base_dir=self.base_dir)
        self.managers = managers = {m.name: m for m in plan.managers()}
        self.tree(plan.tree, ("tree",), set())
        self.calls(plan.workload)
        names = {  # what the fields of an `after` trigger may name
            "supervisor": {s.name for s in plan.tree.supervisors()},
            "child": set(managers) | {s.name for s in plan.tree.supervisors()[1:]},
            "registrar": set(managers) | {f"client-{i}" for i in range(plan.workload.clients)},
        }
        for path, fault in ((("faults", i), f) for i, f in enumerate(plan.faults)):
            self.fault(fault, path, names, plan.duration)
        if plan.compare is not None and not variant:  # a variant's setting has its value
            self.compare(plan.compare)
        return plan

    def root(self, value: Any, path: KeyPath) -> schema.SupervisorPlan:
        """The top supervisor: named "root" unless named, no `restart`, and the plan's `state`."""
        keys = [TOML_KEY.get(f.name, f.name) for f in dataclasses.fields(schema.SupervisorPlan)]
        table = self.table(value, path, (*(k for k in keys if k != "restart"), "state"))
        self.state = self.check(table.get("state", True), bool, (*path, "state"))
        tree = {"name": "root", **{k: v for k, v in table.items() if k != "state"}}
        root: schema.SupervisorPlan = self.decode(schema.SupervisorPlan, tree, path)
        return root

    def tree(self, node: Any, path: KeyPath, seen: set[str]) -> None:
        """The rules of the tree node `node` and its children (`seen`: the names above)."""
        twice = f"the name {node.name!r} is used twice in the tree"
        self.refuse(node.name in seen, (*path, "name"), twice)
        seen.add(node.name)
        empty = isinstance(node, schema.SupervisorPlan) and not node.children
        self.refuse(empty, (*path, "children"), f"must be {WHAT['children']}")
        if isinstance(node, schema.ManagerPlan):
            self.importable((*path, "setup"), node.setup, (*path, "options"), None, **node.options)
        for index, child in enumerate(getattr(node, "children", ())):
            self.tree(child, (*path, "children", index), seen)

    def calls(self, workload: schema.Workload) -> None:
        for index, call in enumerate(workload.calls):
            path = ("workload", "calls", index)
            self.named(call.manager, (*path, "manager"))
            both = "request" in self.raw(path) and call.factory is not None
            self.refuse(both, (*path, "factory"), "give either 'request' or 'factory', not both")
            if call.factory is not None:
                self.importable((*path, "factory"), call.factory, (*path, "factory"), "key", None)
            self.template(call.request, (*path, "request"))
        problem = "'calls' is missing: what do the clients call?"
        self.refuse(workload.clients and not workload.calls, ("workload",), problem)

    def named(self, name: str, path: KeyPath) -> None:
        problem = f"no manager {name!r} in the tree (managers: {', '.join(self.managers)})"
        self.refuse(name not in self.managers, path, problem)

    def template(self, value: Any, path: KeyPath) -> None:
        """Check every string of a request template: a placeholder is only a known name
        (`{key}`, not `{key!r}` or `{client:03d}`), so a template that passes renders."""
        if isinstance(value, dict | list):
            for key, item in value.items() if isinstance(value, dict) else enumerate(value):
                self.template(item, (*path, key))
        if not isinstance(value, str):
            return
        try:
            parsed = [p for p in string.Formatter().parse(value) if p[1] is not None]
        except ValueError as exc:
            raise self.error(path, f"{value!r} is not a valid template: {exc}") from None
        known = ", ".join(f"{{{p}}}" for p in sorted(schema.PLACEHOLDERS))
        for _, field, spec, conversion in parsed:
            bare = f"{value!r}: a placeholder is only a name, like {{{field}}}, without a "
            self.refuse(spec or conversion, path, bare + "conversion ('!r') or a format ('03d')")
            unknown = f"unknown placeholder {{{field}}}; known: {known}"
            self.refuse(field not in schema.PLACEHOLDERS, path, unknown)

    # -- the faults ---------------------------------------------------------------------------

    def fault(self, fault: schema.FaultPlan, path: KeyPath, names: Any, duration: float) -> None:
        """The rules of one `[[faults]]` entry; `names` are the values an `after` may name."""
        table, kind, managers, refuse = self.raw(path), fault.kind, self.managers, self.refuse
        when = [key for key in ("at", "every", "after") if key in table]
        say = f"give only one of 'at', 'every' or 'after', not {' and '.join(when)}"
        say = say if when else "say when: give one of 'at', 'every' or 'after'"
        refuse(len(when) != 1, path, say)
        for key in table:
            needs, kinds = NEEDS_KEY.get(key), NEEDS_KIND.get(key, (kind,))
            refuse(needs and needs not in table, (*path, key), f"only goes with {needs!r}")
            only = f"(only {' or '.join(map(repr, kinds))})"
            refuse(kind not in kinds, (*path, key), f"does not go with kind {kind!r} {only}")
        both = "give either 'for' (seconds) or 'loads' (a number), not both"
        refuse("for" in table and "loads" in table, (*path, "loads"), both)
        for key, item in fault.after.match.items() if fault.after else ():  # or it never fires
            known = ", ".join(sorted(names.get(key, ())))
            problem = f"{item!r} names nothing in this run (it may be: {known})"
            refuse(key in names and item not in names[key], (*path, "after", key), problem)
        # -- whom: the targets
        given = "target" in table
        missing = f"'target' is missing{PURPOSE['target']}"
        refuse(not given and kind != "kill_resource", path, missing)
        threads = all(m.isolation == "thread" for m in managers.values())
        problem = "kill_resource kills resource processes of process managers; every manager of "
        refuse(not given and threads, path, problem + "this tree has isolation 'thread'")
        refuse(given and not fault.targets, (*path, "target"), "must name at least one manager")
        for at, name in (((*path, "target", i), name) for i, name in enumerate(fault.targets)):
            self.named(name, at)  # the element, or the key if it gives one name
            thread = kind in schema.NEEDS_PROCESS and managers[name].isolation != "process"
            refuse(thread, at, f"{kind} needs a process manager; {name!r} has isolation 'thread'")
        # -- when: within the run, not too often
        hang = kind == "hang_manager" and fault.for_s is None
        refuse(hang, path, f"'for' is missing{PURPOSE['for']}")
        none = "must give at least one time (seconds)"
        refuse("at" in table and not fault.at, (*path, "at"), none)
        end = f"the end of the run ({duration:g} s)"
        for index, time in enumerate(fault.at):
            refuse(time >= duration, (*path, "at", index), f"{time!r} s is not before {end}")
        stop, start = duration if fault.stop is None else fault.stop, fault.start
        low = fault.every if isinstance(fault.every, float) else (fault.every or (0.0,))[0]
        most, first = fault.most_injections(duration), f"stop ({stop:g} s)" if fault.stop else end
        never = f"{fault.delay:g} s is not before {end}: it never fires"
        refuse(fault.delay >= duration, (*path, "delay"), never)
        refuse(start >= duration, (*path, "start"), f"{start:g} s is not before {end}")
        refuse(stop <= start, (*path, "stop"), f"must be after 'start' ({start:g} s)")
        after = f"{stop:g} s is after {end}; leave it out to inject until the end"
        refuse(stop > duration, (*path, "stop"), after)
        late = f"the first injection ({start:g} + {low:g} s) would not come before {first}"
        refuse(fault.every is not None and start + low >= stop, (*path, "every"), late)
        often = f"would inject up to {most} times in a run (at most {schema.MAX_INJECTIONS} per "
        often += "fault): give a longer interval, a 'count' or a 'stop'"
        refuse(most > schema.MAX_INJECTIONS, (*path, "every"), often)

    def every(self, every: Any, path: KeyPath) -> Any:
        """`every = 0.5` or `every = { min = 0.5, max = 2 }` (msgspec 0.22 crashes on its type)."""
        if not isinstance(every, dict):
            return None if every is None else self.check(every, schema.Interval, path)
        self.table(every, path, ("min", "max"))
        self.refuse(len(every) != 2, path, "needs both 'min' and 'max' (seconds)")
        low, high = (self.check(every[k], schema.Interval, (*path, k)) for k in ("min", "max"))
        self.refuse(high < low, (*path, "max"), f"must not be less than min ({low:g} s)")
        return low, high

    def trigger(self, value: Any, path: KeyPath) -> schema.Trigger:
        table = f'must be a table like {{ event = "ChildRestarted" }}, got {_show(value)}'
        self.refuse(not isinstance(value, dict), path, table)
        self.refuse("event" not in value, path, "'event' is missing")
        event, known = value["event"], ", ".join(sorted(schema.EVENT_TYPES))
        unknown = not isinstance(event, str) or event not in schema.EVENT_TYPES
        self.refuse(unknown, (*path, "event"), f"unknown event {event!r}; events: {known}")
        hints = typing.get_type_hints(schema.EVENT_TYPES[event])
        self.table(value, path, ("event", "nth", *(f for f in hints if f != "at")))
        fields = (k for k in value if k not in ("event", "nth"))  # a `Status` by its name, too
        match = {key: self.check(value[key], hints[key], (*path, key)) for key in fields}
        nth = self.check(value.get("nth", 1), schema.Count, (*path, "nth"))
        return schema.Trigger(event, match, nth)

    # -- compare ------------------------------------------------------------------------------

    def compare(self, compare: schema.Compare) -> None:
        path, setting, values = ("compare",), compare.setting, compare.values
        why = NOT_COMPARED.get(setting.split(".")[0])
        self.refuse(why, (*path, "setting"), f"{setting!r} cannot be compared: {why}")
        self.refuse(not values, (*path, "values"), "must be a non-empty array")
        for index, item in enumerate(values):
            same = [x for x in values[:index] if type(x) is type(item) and x == item]
            self.refuse(
                same, (*path, "values", index), f"{item!r} is given twice: each value runs once"
            )
        self.locate(self.data, setting, (*path, "setting"))

    def locate(self, data: dict[str, Any], setting: str, where: KeyPath) -> tuple[Any, str | int]:
        """The container and key that `setting` names in `data` (its parent must exist)."""
        node: Any = data
        parts = setting.split(".")
        for n, part in enumerate(parts):
            key: str | int = part
            if isinstance(node, list):  # an element by its name, or by its index
                names = [x.get("name") if isinstance(x, dict) else None for x in node]
                if part not in names and not (part.isdigit() and int(part) < len(node)):
                    raise self.error(where, f"{setting!r}: no element named {part!r}")
                key = names.index(part) if part in names else int(part)
            elif not isinstance(node, dict):
                raise self.error(where, f"{setting!r} does not name a setting of this plan")
            elif part not in node and n < len(parts) - 1:
                raise self.error(where, f"{setting!r}: this plan has no {part!r} there")
            if n == len(parts) - 1:
                return node, key
            node = node[key]
        raise AssertionError("unreachable")
