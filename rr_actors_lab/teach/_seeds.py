"""The process a check runs a student's code in: `python -m rr_actors_lab.teach._seeds`.

```
 grade.check_folder (the parent: compares, judges)       this process (the child: runs)
   {"folder", "plan", "step", "rules", ...} ──stdin──►   the plan read (the student's setups
                                                         imported), step.py in its slot, then
                                                         the kit hidden (`hide_kit`)
   ◄──stdout── {"ready": true} | {"error": "..."}
   {"seed": N} ──────────────────────────────────────►   simulate.run_seed(plan, N)
   ◄── {"seed", "history", "events", "raised", "replaced", "cpu_s"} | {"seed", "setup": "..."}
   {"shrink": N, "budget", "cpu_s"} ──────────────────►  shrink.shrink(..., keep=the student's)
   ◄── {"shrinking": runs so far}, ... (after each run: the parent's progress)
   ◄── {"text", "seed", "history", "kind", "events", "cpu_s"} | {"shrunk": null, ...}
   stdin closed ─────────────────────────────────────►   exit 0
```

Why a process of its own: the verdict must not be reachable from the code it judges. The
parent never imports the student's modules; it gets each seed's history as plain data
(JSON lines) and judges it with the checker's and the kit's rules itself. Here, once the
student's code is loaded, `rr_actors_lab.teach` (the kit: its grader, the registrar's own
steps, `shipped_step`, the exercises and their solutions) is gone from `sys.modules` and
cannot be imported again, from the student's files or through `importlib`; a protocol
step's slot is put back before each seed and looked at after it (a step that put something
else there is told). One process for the whole check: its start (about 0.5 CPU s of
imports) is paid once, not per seed.

What it does not guard: a student who reads the solution's file from the disk, or rewrites
the simulation's own code from theirs (Python has no sandbox within a process; a check is
not a security boundary, it is a grade that no shortcut the kit offers can reach).
"""

from __future__ import annotations

import builtins
import contextlib
import dataclasses
import importlib.abc
import importlib.util
import json
import logging
import os
import signal
import sys
import time
import traceback
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any, TextIO

from rr_actors.config import Steps
from rr_actors.errors import ConfigError, RrError

__all__ = ["KIT", "RETURNS", "UNLOAD", "hide_kit", "main", "student_step"]

KIT = "rr_actors_lab.teach"
"""The package a student's code may not import in a check."""

UNLOAD = "unload"
"""In `release_order`'s answer: where the resource's own unload runs."""

RETURNS: dict[str, tuple[Callable[[Any, tuple[Any, ...]], bool], str]] = {
    "climb": (
        lambda r, _args: (
            isinstance(r, list | tuple | set | frozenset) and all(isinstance(i, str) for i in r)
        ),
        "a list of resource ids (str)",
    ),
    "shares": (lambda r, _args: isinstance(r, bool), "True or False"),
    "unloads": (lambda r, _args: isinstance(r, bool), "True or False"),
    "in_doubt": (lambda r, _args: isinstance(r, bool), "True or False"),
    "recent": (
        lambda r, _args: isinstance(r, int) and not isinstance(r, bool) and r >= 0,
        "a count of restarts (an int >= 0)",
    ),
    "reconcile": (
        lambda r, _args: (
            isinstance(r, tuple)
            and len(r) == 2
            and all(
                isinstance(part, list | tuple | set | frozenset)
                and all(isinstance(i, str) for i in part)
                for part in r
            )
        ),
        "two sets of query ids (str): (release, unknown)",
    ),
    "release_order": (
        lambda r, args: isinstance(r, list | tuple) and sorted(r) == sorted([*args[0], UNLOAD]),
        'a list of every dependency id and "unload", each once',
    ),
    "group": (
        lambda r, _args: (
            isinstance(r, list | tuple | set | frozenset) and all(isinstance(i, str) for i in r)
        ),
        "a list of child names (str)",
    ),
}
"""What each step must return, as a test (of the result and the step's arguments) and in
words (a student's step is held to it)."""


def load_step(folder: Path, name: str, raised: list[str] | None = None) -> Callable[..., Any]:
    """`folder/step.py`'s function `name`, watched: what it raises, or a result of another
    shape than `RETURNS` says, is added to `raised` (`Type: message (step.py, line N)`),
    then raised on.

    Raises:
        ConfigError: no `step.py`, it does not import, or has no function `name`.
    """
    path = folder / "step.py"
    if not path.is_file():
        raise ConfigError(f"{folder} has no step.py: the step you fix (start it again?)")
    spec = importlib.util.spec_from_file_location(f"rr_teach_step_{name}", path)
    if spec is None or spec.loader is None:
        raise ConfigError(f"{path} cannot be imported")
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except Exception as exc:  # noqa: BLE001 - the student's code: said, not raised
        raise ConfigError(f"{path} does not import: {type(exc).__name__}: {exc}") from None
    step = getattr(module, name, None)
    if not callable(step):
        raise ConfigError(f"{path} has no function {name!r}: the step you fix")
    returns = RETURNS.get(name)

    def watched(*args: Any) -> Any:
        try:
            result = step(*args)
            if returns is not None and not returns[0](result, args):
                raise TypeError(f"it must return {returns[1]}, not {result!r}")  # noqa: TRY301
        except Exception as exc:
            if raised is not None:
                line = next(
                    (f.lineno for f in reversed(traceback.extract_tb(exc.__traceback__))
                     if Path(f.filename) == path),
                    None,
                )  # fmt: skip
                where = f" (step.py, line {line})" if line is not None else ""
                raised.append(f"{type(exc).__name__}: {exc}{where}")
            raise
        return result

    return watched


@contextlib.contextmanager
def student_step(
    step: str | None, folder: Path, raised: list[str] | None = None
) -> Iterator[Callable[..., Any] | None]:
    """A protocol exercise's `folder/step.py` function in the registrar's slot of `step`
    inside the block (`None`: a use exercise, nothing replaced); the watched function.

    Raises:
        ConfigError: as `load_step`; the slot is taken already.
    """
    from rr_actors_lab.experiments import simulate  # noqa: PLC0415 - the simulation extra's

    if step is None:
        yield None
        return
    watched = load_step(folder, step, raised)
    outer = simulate.steps_now()
    if getattr(outer, step) is not None:
        raise ConfigError(f"the step {step!r} is replaced already (one copy at a time)")
    with simulate.steps_in_place(dataclasses.replace(outer, **{step: watched})):
        yield watched


class _KitFinder(importlib.abc.MetaPathFinder):
    """Refuses every import of `KIT` (once `hide_kit` took it out of `sys.modules`)."""

    def find_spec(self, fullname: str, path: Any, target: Any = None) -> Any:
        del path, target
        if fullname == KIT or fullname.startswith(KIT + "."):
            raise ImportError(_refused(fullname), name=fullname)
        return None


def _refused(name: str) -> str:
    return (
        f"{name} is the classroom kit: a check runs your code where the kit (its grader, "
        "the registrar's own steps, the exercises' solutions) cannot be imported"
    )


def hide_kit(folder: Path) -> None:
    """From now on in this process, `KIT` is gone and cannot be imported: out of
    `sys.modules` (and its parent package's attributes), refused by a finder, and refused
    to any import statement of a module of `folder` (the student's), even of a module
    imported already."""
    for name in [n for n in sys.modules if n == KIT or n.startswith(KIT + ".")]:
        del sys.modules[name]
    parent = sys.modules.get(KIT.rpartition(".")[0])
    if parent is not None and hasattr(parent, "teach"):
        delattr(parent, "teach")
    sys.meta_path.insert(0, _KitFinder())
    where = str(folder.resolve())
    real_import = builtins.__import__

    def guarded_import(
        name: str,
        globals: Mapping[str, object] | None = None,  # (__import__'s own names)
        locals: Mapping[str, object] | None = None,
        fromlist: Sequence[str] | None = (),
        level: int = 0,
    ) -> ModuleType:
        file = (globals or {}).get("__file__")
        if (
            level == 0
            and isinstance(file, str)
            and os.path.dirname(os.path.abspath(file)) == where
            and (name == KIT or name.startswith(KIT + ".") or _names_kit(name, fromlist))
        ):
            raise ImportError(_refused(name), name=name)
        return real_import(name, globals, locals, fromlist, level)

    builtins.__import__ = guarded_import


def _names_kit(name: str, fromlist: Sequence[str] | None) -> bool:
    """`from rr_actors_lab import teach`."""
    return f"{name}." == KIT[: len(name) + 1] and "teach" in (fromlist or ())


# -- the child's loop ---------------------------------------------------------------------------


def main() -> int:
    """Serve one check's requests (stdin) with replies (stdout), one JSON object a line."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # (a Ctrl-C: the parent ends this process)
    replies = os.fdopen(os.dup(sys.stdout.fileno()), "w", encoding="utf-8")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())  # (a student's print: not a reply)
    logging.getLogger("rr_actors").setLevel(logging.CRITICAL)  # (the story tells them)
    lines = iter(sys.stdin.readline, "")
    first = next(lines, "")
    if not first:
        return 0
    try:
        check = _Check(json.loads(first))
    except (ConfigError, RrError) as exc:
        _reply(replies, {"error": str(exc)})
        return 0
    _reply(replies, {"ready": True})
    check.progress = lambda runs: _reply(replies, {"shrinking": runs})
    for line in lines:
        _reply(replies, check.serve(json.loads(line)))
    replies.close()
    os._exit(0)  # (what a run left, a thread of a shrink's candidate that broke, is not waited for)


def _reply(out: TextIO, reply: dict[str, Any]) -> None:
    out.write(json.dumps({**reply, "cpu_s": time.process_time()}) + "\n")
    out.flush()


class _Check:
    """One check's plan, step and judge, in this process."""

    def __init__(self, spec: dict[str, Any]) -> None:
        from rr_actors_lab.experiments import shrink, simulate  # noqa: PLC0415
        from rr_actors_lab.experiments.reading import load_plan  # noqa: PLC0415
        from rr_actors_lab.teach import rules  # noqa: PLC0415 - before the kit is hidden

        self.simulate, self.shrink = simulate, shrink
        self.folder = Path(spec["folder"])
        self.path = Path(spec["plan"])
        self.step: str | None = spec.get("step")
        self.keep = tuple(spec.get("keep", ()))
        judged = (spec["rules"], spec["options"], spec["managers"], spec["resolve"])
        self.judge = _judge(rules, *judged, spec["faults"])
        self.raised: list[str] = []
        self.progress: Callable[[int], None] | None = None  # (the shrink's runs so far)
        hide_kit(self.folder)  # (before any of the student's code runs)
        self.watched: Callable[..., Any] | None = None
        if self.step is not None:
            self.watched = load_step(self.folder, self.step, self.raised)
        self.plan = load_plan(self.path)  # (imports the student's setups)
        simulate.check_simulable(self.plan)

    def serve(self, request: dict[str, Any]) -> dict[str, Any]:
        if "seed" in request:
            return self.seed(int(request["seed"]))
        return self.shrunk(int(request["shrink"]), int(request["budget"]), request["cpu_s"])

    @contextlib.contextmanager
    def in_place(self) -> Iterator[list[str]]:
        """The student's step handed to one run (its supervisors' and registrars' config:
        `run_seed`'s steps, a value no code of theirs can swap); what else replaced it: none
        can (the reply's `replaced`, kept for the parent's protocol)."""
        if self.step is None:
            yield []
            return
        with self.simulate.steps_in_place(Steps(**{self.step: self.watched})):
            yield []

    def seed(self, seed: int) -> dict[str, Any]:
        del self.raised[:]
        with self.in_place() as replaced:
            try:
                run = self.simulate.run_seed(self.plan, seed)
            except RrError as exc:  # (the student's setup raised: the tree did not start)
                return {"seed": seed, "setup": str(exc)}
        return {
            "seed": seed,
            "history": run.history,
            "events": run.events,
            "raised": self.raised[:1],
            "replaced": replaced,
        }

    def shrunk(self, seed: int, budget: int, cpu_s: float) -> dict[str, Any]:
        text = self.path.read_text(encoding="utf-8")
        with self.in_place():
            try:
                shrunk = self.shrink.shrink(
                    self.plan,
                    seed,
                    budget=budget,
                    text=text,
                    judge=self.judge,
                    cpu_until=time.process_time() + cpu_s,
                    keep=self.keep,
                    on_run=self.progress,
                )
            except (ConfigError, RrError):
                return {"shrunk": None}
        return {
            "text": shrunk.text,
            "seed": shrunk.seed,
            "history": shrunk.run.history,
            "events": shrunk.run.events,
            "kind": shrunk.kind,
        }


def _judge(
    rules: ModuleType,
    names: list[str],
    options: dict[str, dict[str, Any]],
    managers: list[str],
    resolve: str,
    faults: int,
) -> Callable[[Any], list[Any]]:
    """The shrink's judge: the parent's (`rules.judge`), here only to choose what story to
    tell; the parent judges what the shrink found again."""

    def judge(run: Any) -> list[Any]:
        found: list[Any] = rules.judge(run.history, names, options, managers, resolve, faults)[1]
        return found

    return judge


if __name__ == "__main__":
    sys.exit(main())  # pragma: no cover - the child's own
