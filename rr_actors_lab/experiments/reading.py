"""Reading a plan: TOML text to a validated `Plan`, every problem a `PlanError` with its line.

    PLAN.toml ─tomllib─► data ─_Reader.shape: what TOML spells its own way (`at = 1`,
    `rate = "max"`, `heartbeat = false`, `every`, `after`, `backoff`)─► data in the shapes of
    `plan`'s types ─msgspec.convert: every key, type and limit─► Plan ─► the rules between values
    any step refuses a key path ─► _Reader.error: the part of it the plan wrote (`held`),
    its line (`line_of`) ─► PlanError(source, line, key, problem)

`tomllib` gives no positions, so a key's line is found by bisection: the first line at
which the text up to there (closed by a bracket or quotes) holds it. The format:
`docs/reference/plan.md`.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import functools
import importlib
import inspect
import operator
import os
import re
import string
import sys
import tomllib
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import msgspec
import msgspec.inspect as mi
from msgspec import UNSET

from rr_actors._transport.resolve import RESOLVE_STRATEGIES
from rr_actors.errors import ConfigError
from rr_actors_lab._tools.files import RefusedFileError, read_text
from rr_actors_lab.experiments import plan as schema
from rr_actors_lab.experiments import plans as shipped_plans
from rr_actors_lab.experiments.plan import Plan, PlanError

__all__ = ["PLAN_LIMIT", "import_object", "load_plan", "parse_plan"]

PLAN_LIMIT = 4 * 1024 * 1024
"""The most bytes of a plan file read (a plan is a page of TOML: a bigger file is not one;
`load_plan`, and a run directory's copy that `replay` and `shrink` read)."""

KeyPath = tuple[str | int, ...]  # a path into the data: table keys and array indices

WHAT = {  # what a key must be, where its type alone words it badly (the last key of the path)
    "target": "a manager's name",
    "manager": "a manager's name",
    "name": "letters, digits, '_', '-' or '.'",
    "heartbeat": "a positive number of seconds or false (off)",
    "rate": f"calls per second (at least {1 / schema.MAX_SECONDS:g}, at most {schema.MAX_RATE:g})"
    ' or "max"',
    "weight": f"a positive number (at most {schema.MAX_RATE:g})",
    "shared": "a fraction from 0 to 1",
    "again": "a fraction from 0 to 1",
    "cancel": "a fraction from 0 to 1",
    "jitter": "a fraction from 0 to 1",
    "factor": f"a number from 1 to {schema.MAX_SECONDS:g}",
}  # any other number is seconds
PURPOSE = {  # what a missing key is for
    "duration": " (seconds of workload and faults per run)",
    "kind": f": one of {', '.join(schema.FAULT_KINDS)}",
    "target": ": which manager (or a list of them)",
    "for": ": how many seconds the manager stays stopped",
    "for_hosts": ": how many seconds it lasts",
    "target_hosts": ": which host (or a list of them)",
    "link": ': the two hosts whose link goes down, link = ["a", "b"]',
    "hosts": ': the hosts cut from the rest, hosts = ["b"]',
}
TYPES = {"float": "a number", "int": "an integer", "str": "a string", "bool": "true or false"}
TYPES |= {"array": "an array", "object": "a table"}
NOT_KEYS = ("state", "stop", "variants", "source", "base_dir")  # `Plan` fields no top key gives
NOT_COMPARED = {  # top-level keys `[compare]` refuses, and why
    "name": "every run of an experiment belongs to one plan",
    "description": "it changes nothing in a run",
    "seed": "each run's seed comes from the top 'seed' and its repeat",
    "repeat": "every compared value runs 'repeat' times",
    "compare": "compare is not a setting of a run",
}
KEYS = [f.name for f in dataclasses.fields(Plan) if f.init and f.name not in NOT_KEYS]
# -- a fault's keys that only go with another key, or with some kinds ---------------------------
NEEDS_KEY = {"start": "every", "stop": "every", "count": "every", "delay": "after"}
NEEDS_KIND: dict[str, tuple[str, ...]] = {
    "for": ("hang_manager", "load_error", "cut", "partition", "freeze", "partition_serving")
}
NEEDS_KIND["for"] += ("duplicate_delivery", "split_brain", "deaf_manager")
NEEDS_KIND |= {"loads": ("load_error",), "link": ("cut",), "hosts": ("partition",)}
NEEDS_KIND |= {"server": ("load_error",), "message": ("load_error",)}
NEEDS_KIND |= {"how": ("corrupt_backup",)}


def import_object(path: str, *, base_dir: str | None = None) -> Any:
    """Import `"package.module:attribute"` (the attribute may be dotted), `base_dir` first:
    a plan's import paths, while it is read and again in the run and manager processes.

    Raises:
        ConfigError: the path is malformed, the module does not import (it raised, or
            exited; a `KeyboardInterrupt` goes through), or it has no such attribute.
    """
    module_name, colon, attribute = path.partition(":")
    if not colon or not module_name or not attribute:
        raise ConfigError(f"{path!r} is not an import path of the form 'package.module:name'")
    added = base_dir if base_dir is not None and base_dir not in sys.path else None
    if added is not None:  # first on `sys.path` while it imports
        sys.path.insert(0, added)
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ConfigError(f"{path!r} does not import: {exc}") from exc
    except (Exception, SystemExit) as exc:  # a module that calls sys.exit() on import, too
        raise ConfigError(f"{path!r}: importing {module_name} raised {exc!r}") from exc
    finally:
        if added is not None and added in sys.path:
            sys.path.remove(added)
    try:
        return functools.reduce(getattr, attribute.split("."), module)
    except AttributeError:
        raise ConfigError(f"{path!r}: {module_name} has no attribute {attribute!r}") from None


def load_plan(path: str | os.PathLike[str]) -> Plan:
    """Read and validate the plan in the TOML file `path` (its `name` defaults to the stem).

    Raises:
        PlanError: the file cannot be read, is not a regular file (a pipe, a device),
            holds more than `PLAN_LIMIT` bytes, is not TOML, or is not a valid plan; the
            message names the file, the line and the key.
    """
    source = os.fspath(path)
    try:
        text = read_text(source, PLAN_LIMIT, "a plan")
    except RefusedFileError as exc:
        problem = exc.problem
        if exc.missing and Path(source).parent == Path():
            hint = _did_you_mean(Path(source).stem, shipped_plans.shipped())
            problem += f"{hint} (a shipped plan: plans.find() finds it)" if hint else ""
        raise PlanError(source, 0, "", problem) from exc
    return parse_plan(text, source=source, name=Path(source).stem)


def parse_plan(
    text: str, *, source: str = "<plan>", name: str = "plan", base_dir: str | None = None
) -> Plan:
    """Validate the plan in the TOML `text` (`source` names it in errors): a variant per value.

    Args:
        text: the plan's TOML.
        source: its file's name (errors name it).
        name: the plan's name unless it gives one.
        base_dir: the folder searched first for its import paths (default: `source`'s;
            a run directory's copy gives the original file's).

    Raises:
        PlanError: the text is not TOML or not a valid plan.
    """
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        line = re.search(r"\(at line (\d+)", str(exc))
        problem = f"is not valid TOML: {exc}"
        raise PlanError(source, int(line[1]) if line else 0, "", problem) from exc
    except RecursionError:  # (tomllib recurses per nested array or table)
        raise PlanError(source, 0, "", "is not a plan: nested too deeply to read") from None
    except ValueError:  # (an integer past Python's limit of digits)
        digits = sys.get_int_max_str_digits()
        problem = f"is not a plan: a number of over {digits} digits"
        raise PlanError(source, 0, "", problem) from None
    if base_dir is None and source != "<plan>":
        base_dir = os.path.dirname(os.path.abspath(source))
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


def _type_at(info: Any, steps: KeyPath, data: Any) -> Any:
    """The type (of `msgspec.inspect`) at `steps` of `data` decoded as `info`: of a union, the
    member `data` takes there (a tagged one by its tag; at a wrong tag, the tags allowed)."""
    for step in (*steps, None):
        if isinstance(info, mi.UnionType):
            members: list[Any] = [t for t in info.types if t != mi.NoneType()]
            tags = {t.tag: t for t in members if getattr(t, "tag", None) is not None}
            field = next((t.tag_field for t in tags.values()), None)
            if field is not None and step == field:
                return mi.LiteralType(tuple(tags))
            given = data.get(field) if isinstance(data, dict) else None
            info = tags.get(given, members[0])
        if step is None:
            return info
        fields = {f.encode_name: f.type for f in getattr(info, "fields", ())}
        info, data = fields[step] if isinstance(step, str) else info.item_type, data[step]
    raise AssertionError("unreachable")


def _allowed(message: str, info: Any, key: str) -> str:
    """What a value of `key` must be, from msgspec's `message` and the type `info` it refused."""
    bound = re.fullmatch(r"Expected `(\w+)` (of length )?([<>]=?) (\S+)", message)
    typed = re.fullmatch(r"Expected `([^`]*)`, got `\w+`", message)
    op, number = (bound[3], float(bound[4])) if bound else ("", 0.0)
    if isinstance(info, mi.LiteralType | mi.EnumType):
        values = info.values if isinstance(info, mi.LiteralType) else tuple(info.cls.__members__)
        what = f"one of {', '.join(map(repr, values))}"
    elif bound and bound[2]:  # a length: `min_length=1` (an array, a name) or `max_length`
        empty = op == ">=" and bound[4] == "1"
        what = (
            f"a non-empty {TYPES[bound[1]].split()[-1]}"
            if empty
            else f"{TYPES[bound[1]]} of length {op} {bound[4]}"
        )
    elif key in WHAT and not (bound and key == "heartbeat"):
        what = WHAT[key]
    elif bound and bound[1] == "int":
        what = f"an integer {op} {bound[4]}"
    elif bound and op == "<=":
        what = f"at most {number:g} s (about {number / 86400:.1f} days)"
    elif bound:
        zero = {">": "a positive number of seconds", ">=": "seconds >= 0"}[op]
        what = f"at least {number:g} s" if number else zero
    elif typed:
        kinds = [TYPES.get(kind, kind) for kind in typed[1].split(" | ") if kind != "null"]
        what = " or ".join(f"{k} of seconds" if k == "a number" else k for k in kinds)
    else:
        words = message.split(maxsplit=1)[0].isalpha()  # msgspec's own, or a check's
        return f"{message[0].lower()}{message[1:]}" if words else message
    return f"must be {what}"


def _did_you_mean(name: object, known: Iterable[str]) -> str:
    """`"; did you mean 'duration'?"` for the known name closest to a mistyped `name`, or `""`."""
    close = difflib.get_close_matches(name, list(known), n=1) if isinstance(name, str) else []
    return f"; did you mean {close[0]!r}?" if close else ""


def _unknown_key(key: object, known: Iterable[str]) -> str:
    """The problem of an unknown key: the closest known key, then every key known there."""
    names = sorted(known)
    hint = _did_you_mean(key, names)
    return f"unknown key{hint}{' ' if hint else '; '}known here: {', '.join(names)}"


class _Reader:
    """Reads plan data into a `Plan`, turning every problem into a `PlanError`."""

    def __init__(self, source: str, text: str, base_dir: str | None) -> None:
        self.source, self.text, self.base_dir = source, text, base_dir
        self.data: dict[str, Any] = {}
        self.managers = dict[str, schema.ManagerPlan]()  # of the last plan
        self.hosts: schema.HostsPlan | None = None  # of the last plan

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

    def raw(self, path: KeyPath) -> Any:
        data: Any = self.data
        return functools.reduce(operator.getitem, path, data)  # the value as written

    def check(self, value: Any, hint: Any, path: KeyPath) -> Any:
        """`value` (at `path`) decoded as the type `hint` by msgspec, or a `PlanError`."""
        try:
            return msgspec.convert(value, hint)
        except msgspec.ValidationError as exc:
            message, _, inner = str(exc).partition(" - at `$")
            steps = tuple(int(i) if i else k for i, k in re.findall(r"\[(\d+)\]|\.(\w+)", inner))
            at, info = (*path, *steps), _type_at(mi.type_info(hint), steps, value)
            key = re.fullmatch(
                r"Object (?:contains unknown|missing required) field `(\w+)`", message
            )
            if key and message.startswith("Object missing"):
                problem = f"{key[1]!r} is missing{PURPOSE.get(key[1], '')}"
            elif key:
                at = (*at, key[1])
                problem = _unknown_key(key[1], (f.encode_name for f in info.fields))
            else:
                at = held(self.data, at)
                last = next((p for p in reversed(at) if isinstance(p, str)), "")
                problem = f"{_allowed(message, info, last)}, got {_show(self.raw(at))}"
                if isinstance(info, mi.LiteralType | mi.EnumType):  # a mistyped name
                    known = (
                        [m.value for m in info.cls]
                        if isinstance(info, mi.EnumType)
                        else info.values
                    )
                    problem += _did_you_mean(self.raw(at), map(str, known))
            raise self.error(at, problem) from None

    # -- what TOML spells its own way, in the shapes of `plan`'s types --------------------------

    def shape(self, data: dict[str, Any]) -> dict[str, Any]:
        """A copy of the plan's `data` in the shapes msgspec decodes into a `Plan`."""
        for key in (k for k in data if k not in KEYS):
            raise self.error((key,), _unknown_key(key, KEYS))
        data = copy.deepcopy(data)
        if isinstance(tree := data.get("tree"), dict):  # the top: `state`, `stop`, no `restart`
            known = {f.encode_name for f in msgspec.structs.fields(schema.SupervisorPlan)}
            keys = sorted(known - {"restart"} | {"state", "stop"})
            top = f"unknown key; known here: {', '.join(keys)}"
            self.refuse("restart" in tree, ("tree", "restart"), top)
            data["state"] = self.check(tree.pop("state", True), bool, ("tree", "state"))
            stop = tree.pop("stop", "reverse")
            self.refuse(
                stop not in ("reverse", "parallel"),
                ("tree", "stop"),
                f'must be "reverse" or "parallel", got {stop!r}',
            )
            data["stop"] = stop
            data["tree"] = self.node({"name": "root", **tree}, ("tree",))
        if isinstance(workload := data.get("workload"), dict) and workload.get("rate") == "max":
            workload["rate"] = None
        for index, fault in _tables(data, "faults"):
            path = ("faults", index)
            fault |= {k: [fault[k]] for k in ("at", "target") if type(fault.get(k, [])) is not list}
            every = self.check(
                fault.get("every"), schema.Every | schema.Interval | None, (*path, "every")
            )
            fault["every"] = (every.min, every.max) if isinstance(every, schema.Every) else every
            if "after" in fault:  # `after = { event = "ChildRestarted", child = "db" }`
                after = self.check(fault["after"], schema.AFTER, (*path, "after"))
                match = {k: v for k, v in msgspec.structs.asdict(after).items() if v is not UNSET}
                nth = match.pop("nth")
                fault["after"] = schema.Trigger(event=type(after).__name__, match=match, nth=nth)
        return data

    def node(self, node: dict[str, Any], path: KeyPath) -> dict[str, Any]:
        """A tree node tagged for msgspec, `heartbeat = false` as None, `backoff` checked."""
        node["_node"] = "supervisor" if "children" in node or path == ("tree",) else "manager"
        if node.get("heartbeat") is False:
            node["heartbeat"] = None
        if "backoff" in node:  # `Backoff` takes any number: the plan's limits, unknown keys
            self.check(node["backoff"], schema.BackoffPlan, (*path, "backoff"))
        for index, child in _tables(node, "children"):
            self.node(child, (*path, "children", index))
        return node

    # -- the plan and the rules between its values ---------------------------------------------

    def plan(self, data: dict[str, Any], *, name: str, variant: bool = False) -> Plan:
        self.data = {"name": name, **data}
        plan: Plan = self.check(self.shape(self.data), Plan, ())
        source = None if self.source == "<plan>" else self.source
        plan = dataclasses.replace(plan, source=source, base_dir=self.base_dir)
        self.managers = managers = {m.name: m for m in plan.managers()}
        self.hosts = plan.hosts
        if plan.hosts is not None:
            for index, host in enumerate(plan.hosts.names):
                twice = f"the host {host!r} is named twice"
                self.refuse(host in plan.hosts.names[:index], ("hosts", "names", index), twice)
            self.resolve(plan.hosts.resolve)
        last = plan.seed + plan.repeat - 1  # the seed of the last repeat (`runs.csv`, `--seed`)
        problem = f"with repeat = {plan.repeat}, the last run's seed {last} is past 64 bits"
        self.refuse(last > schema.MAX_SEED, ("seed",), problem)
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

    def resolve(self, name: str) -> None:
        """`[hosts]`'s `resolve`: a named strategy, or a function of two `Claimant`s."""
        if name not in RESOLVE_STRATEGIES:
            self.importable(("hosts", "resolve"), name, ("hosts", "resolve"), None, None)

    def tree(self, node: Any, path: KeyPath, seen: set[str]) -> None:
        """The rules of the tree node `node` and its children (`seen`: the names above)."""
        twice = f"the name {node.name!r} is used twice in the tree"
        self.refuse(node.name in seen, (*path, "name"), twice)
        seen.add(node.name)
        if isinstance(node, schema.ManagerPlan):
            self.importable((*path, "setup"), node.setup, (*path, "options"), None, **node.options)
            if node.host is not None:
                self.host(node.host, (*path, "host"))
        for index, child in enumerate(getattr(node, "children", ())):
            self.tree(child, (*path, "children", index), seen)

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
        idle = "cancels only awaited calls: give 'awaited' (how many a client awaits at once)"
        self.refuse(workload.cancel > 0 and not workload.awaited, ("workload", "cancel"), idle)

    def host(self, name: str, path: KeyPath) -> None:
        """`name` must be a host of `[hosts]`."""
        hosts = self.hosts
        self.refuse(hosts is None, path, "names a host, but the plan has no [hosts] table")
        assert hosts is not None
        hint, listed = _did_you_mean(name, hosts.names), ", ".join(hosts.names)
        known = f"no host {name!r} in [hosts]{hint} (hosts: {listed})"
        self.refuse(name not in hosts.names, path, known)

    def named(self, name: str, path: KeyPath) -> None:
        hint, listed = _did_you_mean(name, self.managers), ", ".join(self.managers)
        problem = f"no manager {name!r} in the tree{hint} (managers: {listed})"
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
        table, kind, refuse = self.raw(path), fault.kind, self.refuse
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
        if kind in schema.HOST_KINDS:
            self.host_fault(fault, path, table)
        elif kind == "kill_program":
            whole = "does not go with kind 'kill_program' (it kills the run's whole program)"
            refuse("target" in table, (*path, "target"), whole)
        else:
            self.whom(fault, path, table)
        # -- when: within the run, not too often
        hang = kind == "hang_manager" and fault.for_s is None
        refuse(hang, path, f"'for' is missing{PURPOSE['for']}")
        cut = kind in ("partition_serving", "split_brain", "deaf_manager") and fault.for_s is None
        refuse(cut, path, f"'for' is missing{PURPOSE['for_hosts']}")
        lasting = kind in ("cut", "partition", "freeze") and fault.for_s is None
        refuse(lasting, path, f"'for' is missing{PURPOSE['for_hosts']}")
        self.when(fault, path, duration)

    def host_fault(self, fault: schema.FaultPlan, path: KeyPath, table: dict[str, Any]) -> None:
        """Whom a fault between hosts hits: hosts of `[hosts]`, never the run's own router."""
        kind, refuse = fault.kind, self.refuse
        refuse(self.hosts is None, path, f"{kind} acts between hosts: the plan has no [hosts]")
        assert self.hosts is not None
        names, home = self.hosts.names, self.hosts.home
        wrong = {"cut": "link", "partition": "hosts"}.get(kind, "target")
        for key in ("target", "link", "hosts"):
            refuse(key in table and key != wrong, (*path, key), f"does not go with kind {kind!r}")
        purpose = PURPOSE["target_hosts" if wrong == "target" else wrong]
        refuse(wrong not in table, path, f"'{wrong}' is missing{purpose}")
        if kind == "cut":
            assert fault.link is not None
            for index, name in enumerate(fault.link):
                self.host(name, (*path, "link", index))
            same = f"a link joins two hosts, not {fault.link[0]!r} and itself"
            refuse(fault.link[0] == fault.link[1], (*path, "link", 1), same)
        elif kind == "partition":
            for index, name in enumerate(fault.hosts):
                self.host(name, (*path, "hosts", index))
            whole = "names every host: a partition cuts some hosts from the rest"
            refuse(set(fault.hosts) >= set(names), (*path, "hosts"), whole)
        else:
            for index, name in enumerate(fault.targets):
                self.host(name, (*path, "target", index))
                own = (
                    f"{name!r} is the run's own host (its router is the run process, with "
                    f"the clients): {kind} only another host's"
                )
                refuse(name == home, (*path, "target", index), own)

    def whom(self, fault: schema.FaultPlan, path: KeyPath, table: dict[str, Any]) -> None:
        """Whom a fault of a manager hits: managers of the tree."""
        kind, managers, refuse = fault.kind, self.managers, self.refuse
        given = "target" in table
        missing = f"'target' is missing{PURPOSE['target']}"
        refuse(not given and kind != "kill_resource", path, missing)
        threads = all(m.isolation == "thread" for m in managers.values())
        problem = "kill_resource kills resource processes of process managers; every manager of "
        refuse(not given and threads, path, problem + "this tree has isolation 'thread'")
        for at, name in (((*path, "target", i), name) for i, name in enumerate(fault.targets)):
            self.named(name, at)  # the element, or the key if it gives one name
            thread = kind in schema.NEEDS_PROCESS and managers[name].isolation != "process"
            refuse(thread, at, f"{kind} needs a process manager; {name!r} has isolation 'thread'")
            home = self.hosts.home if self.hosts is not None else None
            away = managers[name].host not in (None, home)
            if kind == "split_brain" and self.hosts is not None:  # (its host is cut off)
                here = "split_brain with [hosts] cuts its manager's host off the others, and "
                here += f"{name!r} is on the run's own host ({home}), with the clients"
                refuse(not away, at, here)
                continue
            elsewhere = f"{kind} hits managers of the run's own host ({home}); {name!r} is on "
            refuse(away, at, f"{elsewhere}{managers[name].host!r} (fault it with freeze, cut, ...)")

    def when(self, fault: schema.FaultPlan, path: KeyPath, duration: float) -> None:
        """When a fault comes: within the run, not too often."""
        refuse = self.refuse
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

    # -- compare ------------------------------------------------------------------------------

    def compare(self, compare: schema.Compare) -> None:
        path, setting, values = ("compare",), compare.setting, compare.values
        why = NOT_COMPARED.get(setting.split(".")[0])
        self.refuse(why, (*path, "setting"), f"{setting!r} cannot be compared: {why}")
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


def _tables(data: dict[str, Any], key: str) -> list[tuple[int, dict[str, Any]]]:
    """The tables of the array `data[key]`, with their indices (msgspec refuses anything else)."""
    items = data.get(key)
    return (
        [(i, x) for i, x in enumerate(items) if isinstance(x, dict)] if type(items) is list else []
    )


# -- the line of a key in the TOML text (tomllib gives no positions) ---------------------------


def line_of(text: str, paths: list[KeyPath]) -> int:
    """The 1-based line of the first of `paths` (most specific first) in `text`; 0 if none."""
    rows = text.splitlines(keepends=True)
    for path in paths:
        low, high = 1, len(rows) + 1  # the line is in [low, high]; high: not in the text
        while low < high:
            middle = (low + high) // 2
            low, high = (low, middle) if _holds(rows[:middle], path) else (middle + 1, high)
        if low <= len(rows):
            return low
    return 0


def key_lines(text: str) -> dict[KeyPath, int]:
    """Every key, table and array element of `text` (valid TOML), with its line."""

    def paths(node: Any, path: KeyPath) -> Iterator[KeyPath]:
        if isinstance(node, dict | list):
            for key, child in node.items() if isinstance(node, dict) else enumerate(node):
                yield (*path, key)
                yield from paths(child, (*path, key))

    return {path: line_of(text, [path]) for path in paths(tomllib.loads(text), ())}


def held(data: Any, path: KeyPath) -> KeyPath:
    """The longest start of `path` that `data` has."""
    for n, key in enumerate(path):
        keys = (
            data if isinstance(data, dict) else range(len(data)) if isinstance(data, list) else ()
        )
        if key not in keys:
            return path[:n]
        data = data[key]
    return path


def _holds(rows: list[str], path: KeyPath) -> bool:
    """Whether the data of `rows`, closed if cut inside a value, has a value at `path`."""
    for closer in ("", "]", "]]", "]]]", '"""', "'''", '"""]', "''']"):
        try:
            return held(tomllib.loads(f"{''.join(rows)}\n{closer}"), path) == path
        except tomllib.TOMLDecodeError:
            continue
    return False
