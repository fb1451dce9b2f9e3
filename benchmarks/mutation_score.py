"""The verdict's strength as a number: mutants of the protocol modules, searched by the plans.

Issue 68 item 8. Mutation testing as the field does it, with cosmic-ray's operators
(`pip install cosmic-ray`, in the `dev` extra), driven one mutant at a time through its
API (`cosmic_ray.mutating.mutate_code`) rather than its own runner, which runs a test
command, not a search of seeded simulations:

    every mutation cosmic-ray's core operators can make in rr_actors/_registrar/, _store/,
      _catalog/, _supervision/ (its two random operators, VariableInserter and
      VariableReplacer, left out: a mutant must be the same on every run)
    a sample of `--sample` of them (`--seed`: the same sample for the same source)
    each mutant in a copy of the package in a temporary folder (the worktree is never edited)
    a child process with PYTHONPATH at the copy (PYTHONHASHSEED=0, as a sweep has) runs the
      shipped simulated plans' seeds (`rr_actors_lab.experiments.simulate.run_seed`) in
      turns, one seed of each plan, cheapest plans first, then the second seed of each, ...,
      until a seed's verdict is `violated` or seeds 1 to `--seeds` of every plan ran, within
      `--cpu` CPU seconds (RLIMIT_CPU) and ten times that of wall time
    a violation counts only if the unedited copy does not violate the same rule on that
      plan and seed (then the search goes on from the next seed)

`--seeds` counts seeds per plan, not runs: any budget searches every plan named (a count of
runs, 20 say, ran the first 20 plans' seed 1 and never the last four). One seed of each plan in
`ORDER` (24 then, 29 now) was about 30 CPU s; a search that `--cpu` ends first is a timeout,
not a survivor.

Each mutant is then one of:

    killed    a rule's violation (the rule, the plan and seed that found it)
    crashed   no violation, but a run crashed (raised, or its tree did not start) on a plan
              and seed where the unedited copy's did not (the first such plan and seed), or
              the copy did not import: found, but by no rule (a crash does not end the
              search: the next seed runs, and a later violation still kills)
    timeout   no crash of its own, and the CPU or wall bound ended the search first
    survived  every seed held (or was unverifiable, or crashed as the unedited copy does)
    equivalent  a survivor listed in `EQUIVALENT`, with the line that shows it

Score = killed / (all - equivalent - crashed): a crashed mutant says nothing of the rules
(it is counted apart, as a run error is in Stryker's score). The survivors are printed with
their place and edit: each one is a rule or plan missing, or an equivalent mutant to add to
`EQUIVALENT`.

    python benchmarks/mutation_score.py --sample 100 --seeds 3 --jobs 2     # the figure
    python benchmarks/mutation_score.py --sample 3 --seeds 1                # a quick look
    python benchmarks/mutation_score.py --plans crashloop \
        --only _supervision/policy.py:457:ReplaceComparisonOperator_LtE_Lt  # one mutant
    python benchmarks/mutation_score.py --list | wc -l                      # all mutants
    python benchmarks/mutation_score.py --budget 900 --json r.json --resume  # in chunks

A mutant's id names its line: an edit above it moves it, and redraws the sample (its
size changes); `EQUIVALENT` is kept for the source it names.

`--json OUT` writes every mutant's result. Figures: benchmarks/NOTES.md, "mutation score".
"""

from __future__ import annotations

import argparse
import ast
import builtins
import concurrent.futures
import dataclasses
import hashlib
import importlib.metadata
import json
import os
import random
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "rr_actors"
LAB = ROOT / "rr_actors_lab"
PLANS = LAB / "experiments" / "plans"
MODULES = ("_registrar", "_store", "_catalog", "_supervision")

ORDER = (
    "crashloop", "first", "hang", "simnostate", "simlisten", "simpatient", "simstop", "simlong",
    "simgone", "simheal", "simhosts", "simshare", "simslow", "simrest", "simchain", "simdoubt",
    "simanswer", "simcommit", "simbackup", "simprogram", "simcancel", "simshed", "simkeptdep",
    "simretry", "simways", "simkept", "simoverload", "simfair", "simtimeout", "bigtree",
    "killheavy", "simescalate", "simwithdraw",
)  # fmt: skip
"""The shipped plans the simulation runs, cheapest seed first (CPU s of seed 1, 2026-11-27:
0.3 for the first four, 0.5-0.9 to simdoubt, 1.2-3.7 after; killheavy 4.8; simkept, added
later, 3.3; simoverload 1.6; simcommit, added later, about 1: after simdoubt; simanswer,
added 2026-11-28, 0.85: after simdoubt; simkeptdep, added 2026-11-28, 1.5-1.9: before
simretry; simpatient, added then, 0.2: after simnostate; simstop, added then, 0.3: after
simpatient; simbackup, added then, 0.7-1.2: after simcommit; simtimeout, added then: after
simoverload; simfair, added then, 1.5-1.7: after simoverload; simlisten, added then,
0.2-0.4: after simnostate; simlong, added 2026-11-29, 0.2-0.4: after simstop; simgone,
added then, 0.15-0.25: after simlong; simescalate and simwithdraw, added then, 0.34 and
0.39: last, out of that order)."""

COSMIC_RAY = importlib.metadata.version("cosmic-ray")

LEFT_OUT = ("core/VariableInserter", "core/VariableReplacer")  # (random: not reproducible)

EQUIVALENT: dict[str, str] = {
    "_registrar/status.py:550:ReplaceComparisonOperator_Lt_Is": "`_Call.lapse`'s early "
    "return is a shortcut: on every call it runs on (running, or queued in a lane) `wake` is "
    "`_earliest(self, *merged)` (`__init__`, `merge`, `settle` and `lapse` keep it so; a call "
    "merged into another leaves its lane and is never lapsed again), so with now < wake no "
    "call is overdue and the rest returns [] and sets `wake` to itself; `now is self.wake` "
    "never holds (`wake` is `monotonic() + patience`, a new float)",
    "_registrar/consumer.py:735:NumberReplacer:1": "an id never answered: 0 < epoch and "
    "-1 < epoch alike, every epoch asked being new_epoch()'s, at least 1",
    "_supervision/policy.py:263:ReplaceComparisonOperator_NotEq_IsNot": "incarnations are "
    "ints from 0 up by 1: `is not` is `!=` in CPython up to 256 (its small ints), so for "
    "every run with fewer than 257 restarts of one child",
    "_supervision/policy.py:377:ReplaceComparisonOperator_Eq_Is": "`Child.state` is only "
    "ever set to string literals (`ChildState`), which CPython interns (identifier-like): "
    "`is 'restarting'` is `== 'restarting'`",
    "_supervision/children.py:351:ReplaceFalseWithTrue": "a default of `Level.stop`, a "
    "`Protocol` stub no class inherits: a call runs its implementation's own signature",
    "_supervision/watching.py:52:NumberReplacer": "`_since` before any switch on: events "
    "are kept from `at >= since`, a wall clock's seconds (the simulation's from 2026), so "
    "0.0 and 1.0 drop the same events (none) on any clock past 1970-01-01 00:00:01",
    "_registrar/state.py:496:ZeroIterationForLoop": "`Probes.around`'s after hooks: only "
    "`rr_actors.testing.intercept(after=...)` installs one, which no plan, runtime path or "
    "lab tool calls (the `kill_before_commit` fault installs a `before` hook of a point) "
    "(equivalent for every program but a test's: tests/registrar/test_calls.py)",
    "_registrar/state.py:504:ZeroIterationForLoop": "`Probes.fire`'s hooks: only "
    "`rr_actors.testing.intercept` installs one, which no runtime path calls: a test's, "
    "or the simulated fault `kill_before_commit`'s (simcommit), whose kill then never "
    "comes (recorded as skipped): the registrar's steps are the same",
    "_store/schema.py:299:ReplaceBinaryOperator_Add_Pow": "`create`'s migration loop is "
    "`range(CREATED_VERSION, SCHEMA_VERSION)`, `range(7, 7)`: its body never runs (only "
    "tests add steps)",
    "_store/schema.py:262:ReplaceBinaryOperator_Sub_BitXor": "`found ^ expected` adds to "
    "`check_objects`' loop only the expected objects the file lacks, each a known name of "
    "its kind: a problem raised as `CatalogCorruptError`, where `found - expected` raises "
    "it naming them as missing: the same refusal of the same files, another message",
    "_store/schema.py:326:ReplaceComparisonOperator_Eq_Is": "the scheme read from the file "
    "is a new `str`, never the module's `DIGEST_SCHEME` object: `is` is always false, so "
    "every open recomputes the digests, to the values a current file holds already (a "
    "cost at open; no row or event differs while its requests unpickle, as every plan's do)",
    "_store/outbox.py:82:ReplaceBinaryOperator_Sub_Mul": "the text of a `ValueError` that "
    "`read_told` catches, logs at DEBUG and skips the row for (`continue` either way)",
    "_store/saver.py:490:ReplaceBinaryOperator_Mul_LShift:1": "`journal_size_limit` "
    "(SQLite clamps `8 * 1024 << 1024` to 2**63 - 1): only how much of an emptied WAL file "
    "stays on disk after a checkpoint; every row, restore and event is the same",
    "_store/schema.py:616:ReplaceComparisonOperator_NotEq_IsNot": "`response_version`s are "
    "ints: `is not` is true wherever `!=` is, and where only it is (equal versions past 256, "
    "two objects) the UPDATE writes the response the row already holds: the same row",
    "_registrar/consumer.py:585:ReplaceComparisonOperator_Is_Eq": "`ResourceState` is a "
    "plain `enum.Enum`, whose `==` is identity: `== UNLOADING` is `is UNLOADING`",
    "_supervision/policy.py:342:ReplaceComparisonOperator_NotEq_Lt": "a child whose "
    "latest `Restart` (`_due`) is the one run in its generation is always 'restarting': "
    "only that run starts it (`start_all` comes before any), `_take_down` sets it back "
    "after its stop, and `stop_all`/`give_up` call `cancel` first; 'restarting' < "
    "'restarting' is false as != is (where `_due` is another `Restart`, both `continue`)",
    "_supervision/policy.py:342:ReplaceComparisonOperator_NotEq_Gt": "as policy.py:342 "
    "NotEq_Lt: a child whose latest `Restart` runs is 'restarting', and 'restarting' > "
    "'restarting' is false as != is ('exited', the only smaller state, never meets it)",
    "_supervision/children.py:412:NumberReplacer:1": "incarnations are only bumped by 1 and "
    "compared with `!=` to the one a watcher posted (no event or page shows one): starting "
    "at -1 shifts every one alike",
    "_registrar/consumer.py:735:NumberReplacer": "epochs are only compared with each other "
    "and with 0 (an id answered before any list), in one process: counting by 2 keeps every "
    "order",
    "_supervision/children.py:189:ReplaceComparisonOperator_Eq_LtE": "past `one_for_one` "
    "(returned above) a strategy is `one_for_all` or `rest_for_one` (`SupervisorSpec` checks "
    "it): only the first is `<= 'one_for_all'`, as only it is `==`",
    "_store/files.py:712:NumberReplacer:2": "a 9-byte slice of the -shm never equals the 8 "
    "salts kept, so `CommitCount.committed` always takes its slow path: the -wal header's "
    "salts, which SQLite copies into the -shm's (`WalIndexHdr.aSalt`), the same test; the "
    "same count and record bytes (a performance path: a pread a commit, no event)",
    "_store/files.py:730:ReplaceFalseWithTrue": "a new `CommitCount` never maps the -shm "
    "until its first `reopen`/`close`: `committed` takes its slow path, the -wal header's "
    "salts, which SQLite copies into the -shm's; the same count and record (as files.py:712)",
    "_supervision/policy.py:339:ReplaceComparisonOperator_NotEq_Gt": "a `Restart` carries "
    "the generation it was made in, and `cancel` only adds 1: `>` is never true; a stale one "
    "(`<`) then `continue`s for each child, as `_due`, emptied at each new generation, holds "
    "only that generation's `Restart`s, never it (its names are the node's own, `by_name` "
    "fixed): no start, state or event differs",
    "_store/schema.py:186:ReplaceComparisonOperator_Eq_LtE": "a module-level `assert` run "
    "once at import, on two constants (7 functions in `MIGRATIONS`, `SCHEMA_VERSION = 7`): "
    "7 <= 7 holds as 7 == 7 does, so the import goes on the same (tests that replace them "
    "do so after the import)",
    "_supervision/children.py:347:RemoveDecorator": "the `@property` of `Level.giving_up`, "
    "a `Protocol` stub no class inherits (`Record`, its one subclass, is a `Protocol` too; "
    "`Node` defines its own property): nothing reads the stub (as children.py:351)",
    "_registrar/life.py:994:ReplaceBinaryOperator_Sub_Pow": "`life.lost_everything`'s "
    "`also` is never passed (its one runtime caller, `tree.lost_everything`, passes `name` "
    "and `handle`; no lab code calls it): `also` is an empty set, the loop never reached",
    "_registrar/actor.py:469:ReplaceFalseWithTrue:1": "`launch`'s cleanup of a failed "
    "start: `open_catalog` made the `Saver` just before with nothing pending, and nothing "
    "stages a change before the actor's own thread runs (`RegistrarActor.__init__` and its "
    "parts only build state), so `flush()` writes nothing (the one way past: an asynchronous "
    "KeyboardInterrupt inside `Thread.start` after the actor's thread began)",
    "_store/files.py:148:ReplaceComparisonOperator_Gt_NotEq": "`st_size` is never negative: "
    "`!= 0` is `> 0`",
    "_store/files.py:747:ReplaceComparisonOperator_Eq_Is": "an 8-byte slice of the -shm is a "
    "new `bytes`, never `self._salts`: `committed` always takes its slow path, which reads "
    "the same -shm salts with `==` and writes the same record (salts, then the count: the "
    "bytes the fast path's count alone leaves; the same sync) (as files.py:712)",
    "_store/saver.py:439:ReplaceBinaryOperator_FloorDiv_RShift": "`len(value) >> 4096` is 0: "
    "a large value no longer hurries the background checkpoint, still woken every "
    "`checkpoint_every` ops: only when and how much of the WAL is copied, timing and disk "
    "space (the log holds every commit until then; a restore and the count read it alike)",
    "_store/saver.py:490:ReplaceBinaryOperator_Mul_RShift:1": "`journal_size_limit` 0 "
    "(`8 * 1024 >> 1024`): SQLite truncates a restarted WAL to the frames of its first "
    "commit (never to 0 bytes: `_has_log` alike), not to 8 MiB; the stale frames cut had "
    "another generation's salts, where `_commit_frames` stops: only disk space (as Mul_LShift:1)",
    "_store/files.py:825:NumberReplacer:1": "a count record cut short read as -1 commits, not "
    "0: with its -wal there whole, the salts (b'') differ, `None` as before; missing or cut "
    "short, `(-1, why)`: a WARNING of -1 lost commits, `lost_commits` -1 (which nothing "
    "reads) and the count file removed, the first commit writing the record the short one "
    "would have got: only a log's text",
}
"""Survivors shown equivalent: mutant id (`FILE:LINE:OPERATOR[:N]`) -> the line that shows it."""


@dataclasses.dataclass(frozen=True)
class Mutant:
    """One mutation: a file under rr_actors/, cosmic-ray's operator and occurrence in it."""

    file: str
    operator: str  # e.g. core/ReplaceComparisonOperator_Is_IsNot
    occurrence: int  # of the operator in the file, in cosmic-ray's walk order
    line: int
    nth: int  # 0 for the operator's first mutation on that line, then 1, ...

    @property
    def id(self) -> str:
        """`FILE:LINE:OPERATOR` (and `:N` when the operator mutates that line more than once)."""
        name = self.operator.split("/", 1)[1]
        return f"{self.file}:{self.line}:{name}" + (f":{self.nth}" if self.nth else "")


# -- the mutants ----------------------------------------------------------------------


def operators() -> list[tuple[str, Any]]:
    """cosmic-ray's operators (name, instance), the random ones left out."""
    from cosmic_ray.plugins import get_operator, operator_names  # noqa: PLC0415

    return [(n, get_operator(n)()) for n in operator_names() if n not in LEFT_OUT]


def annotations(text: str) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """The spans ((line, column), (end line, end column)) of `text`'s annotations: never
    evaluated under `from __future__ import annotations`, so a mutant there is equivalent."""
    spans = []
    for node in ast.walk(ast.parse(text)):
        found: list[ast.expr | None] = []
        if isinstance(node, ast.arg):
            found.append(node.annotation)
        elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            found.append(node.returns)
        elif isinstance(node, ast.AnnAssign):
            found.append(node.annotation)
        spans += [
            ((a.lineno, a.col_offset), (a.end_lineno or a.lineno, a.end_col_offset or 0))
            for a in found
            if a is not None
        ]
    return spans


def enumerate_mutants(modules: tuple[str, ...] = MODULES) -> list[Mutant]:
    """Every mutant of `modules` (folders or files under rr_actors/), in a stable order
    (file, operator, occurrence); those inside annotations left out."""
    from cosmic_ray.ast import ast_nodes, get_ast  # noqa: PLC0415

    ops = operators()
    found: list[Mutant] = []
    paths = sorted(
        {
            p
            for m in modules
            for p in ((PACKAGE / m).rglob("*.py") if (PACKAGE / m).is_dir() else [PACKAGE / m])
        }
    )
    for path in paths:
        file = str(path.relative_to(PACKAGE))
        text = path.read_text(encoding="utf-8")
        digest = hashlib.sha256(f"{COSMIC_RAY}\n{file}\n{text}".encode()).hexdigest()[:16]
        cached = Path(tempfile.gettempdir()) / f"rr-mutants-{digest}.json"  # (20 CPU s for all)
        if cached.is_file():
            found += [Mutant(**m) for m in json.loads(cached.read_text(encoding="utf-8"))]
            continue
        mine: list[Mutant] = []
        spans = annotations(text)
        positions: dict[str, list[tuple[int, bool]]] = {name: [] for name, _ in ops}
        for node in ast_nodes(get_ast(text)):
            for name, op in ops:
                for start, _end in op.mutation_positions(node):
                    typed = any(a <= tuple(start) < b for a, b in spans)
                    positions[name].append((start[0], typed))
        for name, _ in ops:
            seen: dict[int, int] = {}
            for occurrence, (line, typed) in enumerate(positions[name]):
                nth = seen.get(line, 0)
                seen[line] = nth + 1
                if not typed:
                    mine.append(Mutant(file, name, occurrence, line, nth))
        cached.write_text(json.dumps([dataclasses.asdict(m) for m in mine]), encoding="utf-8")
        found += mine
    return found


def mutated(mutant: Mutant) -> tuple[str, str]:
    """The mutant's file text, and its edit in a line (`old -> new`, stripped)."""
    from cosmic_ray.mutating import mutate_code  # noqa: PLC0415
    from cosmic_ray.plugins import get_operator  # noqa: PLC0415

    text = (PACKAGE / mutant.file).read_text(encoding="utf-8")
    new = mutate_code(text, get_operator(mutant.operator)(), mutant.occurrence)
    if new is None:
        raise SystemExit(f"{mutant.id}: cosmic-ray made no mutation (the source moved)")
    old_lines, new_lines = text.splitlines(), new.splitlines()
    edit = next(
        (
            f"{a.strip()}  ->  {b.strip()}"
            for a, b in zip(old_lines, new_lines, strict=False)
            if a != b
        ),
        "(no line changed)",
    )
    return new, edit


def sample(every: list[Mutant], size: int, seed: int) -> list[Mutant]:
    """`size` mutants drawn from `every` (seeded), those that do not compile skipped (a
    stillborn mutant, as the field counts them: cosmic-ray turns the `*` of `def f(a, *, b)`
    into `%`), and those cosmic-ray fails to make (its `ExceptionReplacer` raises
    `AttributeError` on a dotted name in an `except (a.B, C)` tuple, cosmic-ray 8.7)."""
    drawn = random.Random(seed).sample(every, len(every))  # noqa: S311 - a sample, not a secret
    chosen: list[Mutant] = []
    for mutant in drawn:
        if len(chosen) == size:
            break
        if not stillborn(mutant):
            chosen.append(mutant)
    return chosen


def stillborn(mutant: Mutant) -> bool:
    """Whether the mutant does not compile, or cosmic-ray fails to make it (see `sample`)."""
    try:
        compile(mutated(mutant)[0], mutant.file, "exec")
    except (SyntaxError, AttributeError):
        return True
    return False


def scratch(folder: Path, mutant: Mutant | None) -> tuple[Path, str]:
    """A copy of the package and lab under `folder` (`mutant` applied); its edit in a line."""
    shutil.copytree(PACKAGE, folder / "rr_actors", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(LAB, folder / "rr_actors_lab", ignore=shutil.ignore_patterns("__pycache__"))
    if mutant is None:
        return folder, ""
    text, edit = mutated(mutant)
    (folder / "rr_actors" / mutant.file).write_text(text, encoding="utf-8")
    return folder, edit


# -- the parent: one child per mutant, a clean child per violation ----------------------


class Clean:
    """The unedited copy's violated rules per (plan, seed), run once each, on demand."""

    def __init__(self, folder: Path) -> None:
        self.path, _ = scratch(folder, None)
        self.runs: dict[tuple[str, int], dict[str, Any]] = {}
        self.lock = threading.Lock()

    def run(self, plan: str, seed: int) -> dict[str, Any]:
        """The unedited copy's line for `plan` at `seed` (its verdict, rules, ...)."""
        with self.lock:
            if (plan, seed) not in self.runs:
                lines, ended = run_child(self.path, [plan], seed, 1, None)
                self.runs[(plan, seed)] = lines[-1] if lines else {"verdict": ended, "rules": []}
            return self.runs[(plan, seed)]

    def violated(self, plan: str, seed: int) -> set[str]:
        return set(self.run(plan, seed)["rules"])


def run_child(
    path: Path, plans: list[str], start: int, seeds: int, cpu: float | None
) -> tuple[list[dict[str, Any]], str | None]:
    """Runs `seeds` turns from turn `start` (1-based) on the copy at `path`: the child's
    lines (one per seed run) and why it ended early (None when it ended by itself)."""
    env = {**os.environ, "PYTHONPATH": str(path), "PYTHONHASHSEED": "0"}
    command = [sys.executable, __file__, "--child", str(path), ",".join(plans), str(start)]

    def bound() -> None:  # (in the child, before exec)
        if cpu is not None:
            resource.setrlimit(resource.RLIMIT_CPU, (int(cpu) + 1, int(cpu) + 2))

    with subprocess.Popen(
        [*command, str(seeds)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=bound,  # noqa: PLW1509 - no threads touch the fork's memory before exec
    ) as child:
        try:
            out, err = child.communicate(timeout=None if cpu is None else cpu * 10 + 60)
        except subprocess.TimeoutExpired:
            child.kill()
            out, err = child.communicate()
            return _lines(out), "timeout (wall)"
    lines = _lines(out)
    if child.returncode == -24:  # SIGXCPU: RLIMIT_CPU
        return lines, "timeout (CPU)"
    if child.returncode != 0:
        tail = err.strip().splitlines()[-1:] or [f"exit status {child.returncode}"]
        return lines, f"child failed: {tail[0][:160]}"
    return lines, None


def _lines(out: str) -> list[dict[str, Any]]:
    return [json.loads(line) for line in out.splitlines() if line.startswith("{")]


CRASHES = ("crashed", "raised")
"""A child line's verdicts for a run that crashed (the simulation's, or `run_seed` raised)."""


def judge(mutant: Mutant, options: argparse.Namespace, clean: Clean) -> dict[str, Any] | None:
    """One mutant's search and its class (None: `--budget` was spent before it started)."""
    plans: list[str] = options.plans
    started = time.monotonic()
    if started > options.deadline:
        return None
    result: dict[str, Any] = {"id": mutant.id, "operator": mutant.operator}
    turns = options.seeds * len(plans)  # (seeds 1 to --seeds of every plan)
    with tempfile.TemporaryDirectory(prefix="rr-mutant-") as folder:
        path, result["edit"] = scratch(Path(folder), mutant)
        runs: list[dict[str, Any]] = []
        ended: str | None = None
        turn, cpu = 1, float(options.cpu)
        while turn <= turns:
            if cpu <= 0:
                ended = "timeout (CPU)"
                break
            lines, ended = run_child(path, plans, turn, turns - turn + 1, cpu)
            runs += lines
            cpu -= sum(line["cpu_s"] for line in lines)
            last = lines[-1] if lines else None
            if last is not None and last["verdict"] == "violated":
                new = sorted(set(last["rules"]) - clean.violated(last["plan"], last["seed"]))
                if new:
                    result.update(status="killed", rules=new, plan=last["plan"], seed=last["seed"])
                    break
                if ended is None:
                    turn = last["turn"] + 1  # (the unedited code violates it too: go on)
                    continue
            break
        result.update(runs=len(runs), plans_run=len({r["plan"] for r in runs}))
        result["crashes"] = sum(r["verdict"] in CRASHES for r in runs)
        if "status" not in result:
            result.update(unkilled(runs, ended, clean))
    if result["status"] == "survived" and mutant.id in EQUIVALENT:
        result.update(status="equivalent", why=EQUIVALENT[mutant.id])
    result["wall_s"] = round(time.monotonic() - started, 1)
    return result


def unkilled(runs: list[dict[str, Any]], ended: str | None, clean: Clean) -> dict[str, Any]:
    """The class of a search no rule ended: crashed (with the first run that crashed where
    the unedited copy's did not: its plan, seed and error), timeout, or survived."""
    for run in runs:
        if run["verdict"] in CRASHES:
            theirs = clean.run(run["plan"], run["seed"])["verdict"]
            if theirs not in CRASHES:
                why = f"{run['plan']} seed {run['seed']}: {run['error']} (unedited: {theirs})"
                return {"status": "crashed", "plan": run["plan"], "seed": run["seed"], "why": why}
    if ended is not None and ended.startswith("timeout"):
        return {"status": "timeout", "why": ended}
    if ended is not None:  # (the copy did not import, or the child died outside a run)
        return {"status": "crashed", "why": ended}
    return {"status": "survived"}


# -- the child: turns of seeds on the copy PYTHONPATH names --------------------------------


def child_main(path: str, plans: str, start: int, count: int) -> None:
    """Runs turns `start`.. of the plans' seeds until a violation; a JSON line per run."""
    import logging  # noqa: PLC0415

    builtins.CosmicRayTestingException = type(  # type: ignore[attr-defined]
        "CosmicRayTestingException", (Exception,), {}
    )  # (cosmic-ray's ExceptionReplacer names it in an `except`)
    logging.disable(logging.CRITICAL)  # (a mutant's tracebacks: the verdict is what counts)
    import rr_actors  # noqa: PLC0415 - the copy's, from PYTHONPATH
    from rr_actors_lab.experiments import load_plan, simulate  # noqa: PLC0415

    for module in (rr_actors, simulate):
        here = Path(module.__file__ or "").resolve()
        if not here.is_relative_to(Path(path).resolve()):
            raise SystemExit(f"the child imported {here}, not the copy at {path}")
    names = plans.split(",")
    loaded = {
        name: load_plan(str(Path(path) / PLANS.relative_to(ROOT) / f"{name}.toml"))
        for name in names
    }
    for turn in range(start, start + count):
        name = names[(turn - 1) % len(names)]
        seed = (turn - 1) // len(names) + 1
        began = time.process_time()
        line: dict[str, Any] = {"turn": turn, "plan": name, "seed": seed, "rules": []}
        try:
            run = simulate.run_seed(loaded[name], seed)
        except Exception as exc:  # (the mutant's: a crash, reported)
            line.update(verdict="raised", error=f"{type(exc).__name__}: {one_line(exc)[:120]}")
        else:
            rules = {
                f.split("[", 1)[1].split("]", 1)[0]
                for f in run.findings
                if f.lstrip().startswith("violation")
            }
            line.update(verdict=run.verdict, rules=sorted(rules))
            if run.verdict == "crashed":
                crashed = [f.strip() for f in run.findings if "crashed" in f]
                line["error"] = one_line((crashed or ["crashed"])[0])[:160]
        line["cpu_s"] = round(time.process_time() - began, 3)
        print(json.dumps(line), flush=True)
        if line["verdict"] == "violated":
            return


def one_line(text: object) -> str:
    """`text` (an error's, which may hold a traceback) on one line of the table."""
    return " ".join(str(text).split())


# -- the table ------------------------------------------------------------------------


def report(results: list[dict[str, Any]], options: argparse.Namespace) -> None:
    """The score, the counts by class and by rule, then each survivor and timeout."""
    counts = dict.fromkeys(("killed", "crashed", "timeout", "survived", "equivalent"), 0)
    for r in results:
        counts[r["status"]] += 1
    judged = len(results) - counts["equivalent"] - counts["crashed"]
    score = counts["killed"] / judged if judged else 0.0
    print(
        f"mutation score: {counts['killed']}/{judged} = {score:.1%} killed by a rule "
        f"({len(results)} mutants less {counts['equivalent']} equivalent and "
        f"{counts['crashed']} crashed; sample seed {options.seed}; seeds 1-{options.seeds} "
        f"of each of {len(options.plans)} plans, at most {options.cpu:g} CPU s a mutant: "
        f"{','.join(options.plans)})"
    )
    print("  " + ", ".join(f"{k} {v}" for k, v in counts.items()))
    rules: dict[str, int] = {}
    for r in results:
        for rule in r.get("rules", [])[:1]:
            rules[rule] = rules.get(rule, 0) + 1
    if rules:
        by = ", ".join(f"{k} {v}" for k, v in sorted(rules.items(), key=lambda kv: -kv[1]))
        print(f"  killed by (first rule): {by}")
    for status in ("survived", "timeout", "crashed", "equivalent"):
        chosen = [r for r in results if r["status"] == status]
        if chosen:
            print(f"{status}:")
        for r in chosen:
            why = f"  ({r['why']})" if r.get("why") else ""
            runs = (
                f"{r['runs']} runs, {r.get('plans_run', '?')} plans, {r.get('crashes', 0)} crashed"
            )
            print(f"  {r['id']}  {r['edit']}  [{runs}]{why}")
    if counts["killed"]:
        print("killed:")
    for r in results:
        if r["status"] == "killed":
            print(f"  {r['id']}  [{','.join(r['rules'])}] {r['plan']} seed {r['seed']}")


def search_all(
    chosen: list[Mutant], options: argparse.Namespace, results: list[dict[str, Any]]
) -> list[dict[str, Any]]:
    """Each mutant's result after `results` (an earlier run's), `--jobs` at once, in sample
    order (a line each on stderr)."""
    results = list(results)
    with tempfile.TemporaryDirectory(prefix="rr-mutant-clean-") as folder:
        clean = Clean(Path(folder))
        with concurrent.futures.ThreadPoolExecutor(options.jobs) as pool:
            futures = [pool.submit(judge, m, options, clean) for m in chosen]
            for i, future in enumerate(futures, 1):
                r = future.result()
                if r is None:
                    continue
                results.append(r)
                if options.json is not None:  # (after each: a run cut short keeps what it did)
                    options.json.write_text(json.dumps(results, indent=1) + "\n", "utf-8")
                found = ",".join(r.get("rules", [])) or r.get("why", "")
                print(
                    f"  [{i}/{len(chosen)}] {r['status']:<8} {r['id']}  {found} "
                    f"({r['runs']} runs, {r['wall_s']} s)",
                    file=sys.stderr,
                    flush=True,
                )
    return results


def earlier_results(options: argparse.Namespace) -> list[dict[str, Any]]:
    """With `--resume`, the results an earlier chunk wrote to `--json` (none before the first;
    a survivor since listed in `EQUIVALENT` is equivalent)."""
    if not options.resume or options.json is None or not options.json.is_file():
        return []
    results: list[dict[str, Any]] = json.loads(options.json.read_text(encoding="utf-8"))
    for r in results:
        if r["status"] == "survived" and r["id"] in EQUIVALENT:
            r.update(status="equivalent", why=EQUIVALENT[r["id"]])
    return results


def only(parser: argparse.ArgumentParser, ids: str, every: list[Mutant]) -> list[Mutant]:
    """The mutants `--only` names (`parser.error` for one unknown, or stillborn: a
    search would stop at it with cosmic-ray's traceback, the results before unprinted)."""
    by_id = {m.id: m for m in every}
    wanted = ids.split(",")
    if unknown := [w for w in wanted if w not in by_id]:
        parser.error(f"--only: no mutant {', '.join(unknown)} (see --list)")
    chosen = [by_id[w] for w in wanted]
    if unmade := [m.id for m in chosen if stillborn(m)]:
        parser.error(f"--only: {', '.join(unmade)} cannot be made or does not compile")
    return chosen


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if args[:1] == ["--child"]:
        child_main(args[1], args[2], int(args[3]), int(args[4]))
        return 0
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--sample", type=int, default=100, help="mutants drawn (default 100)")
    parser.add_argument("--seed", type=int, default=68, help="the sample's seed")
    parser.add_argument(
        "--seeds",
        type=int,
        default=3,
        help="seeds searched of each plan: 1 to SEEDS (default 3: about 90 CPU s, all plans)",
    )
    parser.add_argument("--cpu", type=float, default=120.0, help="most CPU s per mutant")
    parser.add_argument(
        "--budget", type=float, help="wall seconds: no mutant starts after them (a smaller sample)"
    )
    parser.add_argument("--jobs", type=int, default=1, help="mutants searched at once")
    parser.add_argument("--plans", default=",".join(ORDER), help="plans, in turn order")
    parser.add_argument(
        "--modules", default=",".join(MODULES), help="folders or files under rr_actors/ to mutate"
    )
    parser.add_argument("--only", help="mutant ids (FILE:LINE:OPERATOR[:N]), comma-separated")
    parser.add_argument("--list", action="store_true", help="print every mutant's id, then stop")
    parser.add_argument("--json", type=Path, help="write every mutant's result here")
    parser.add_argument(
        "--resume",
        action="store_true",
        help="keep the results already in --json and search only the sample's others "
        "(a search in chunks: each chunk under its own --budget)",
    )
    options = parser.parse_args(args)
    options.plans = options.plans.split(",")
    options.deadline = time.monotonic() + (options.budget or float("inf"))
    if missing := [p for p in options.plans if not (PLANS / f"{p}.toml").is_file()]:
        parser.error(f"--plans: no shipped plan {', '.join(missing)}")
    if options.seeds < 1 or options.jobs < 1 or options.sample < 1:
        parser.error("--seeds, --jobs and --sample must be at least 1")
    if options.only:
        options.modules = ",".join(sorted({w.split(":", 1)[0] for w in options.only.split(",")}))
    modules = tuple(options.modules.split(","))
    if missing := [m for m in modules if not (PACKAGE / m).exists()]:
        parser.error(f"--modules: no {', '.join(missing)} under rr_actors/")
    every = enumerate_mutants(modules)
    if options.list:
        for mutant in every:
            print(mutant.id)
        return 0
    chosen = only(parser, options.only, every) if options.only else None
    if chosen is None:
        chosen = sample(every, options.sample, options.seed)
    if options.resume and options.json is None:
        parser.error("--resume needs --json (the file the earlier chunks wrote)")
    earlier = earlier_results(options)
    done = {r["id"] for r in earlier}
    print(
        f"{len(every)} mutants in {', '.join(modules)}; {len(chosen)} drawn, "
        f"{len(done)} searched before",
        file=sys.stderr,
    )
    results = search_all([m for m in chosen if m.id not in done], options, earlier)
    if len(results) < len(chosen):
        print(f"--budget spent: {len(results)} of the {len(chosen)} mutants searched")
    report(results, options)
    return 0


if __name__ == "__main__":
    sys.exit(main())
