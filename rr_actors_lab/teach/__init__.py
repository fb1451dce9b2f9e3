"""A classroom kit: exercises checked by the verdict of simulated runs (`rr-actors teach`).

```
 rr-actors teach list                 the exercises: name, kind, level, topic
 rr-actors teach start NAME [DIR]     its README and starter files into DIR (./NAME)
 rr-actors teach check [DIR]          its plan over its seeds on the simulation, the verdict
 rr-actors teach hint [DIR]           the next hint (those shown: DIR/.teach.json)
 rr-actors teach solution --teacher   the solution's files
```

Two kinds of exercise: `use` (the student writes a manager's setup or a plan, as a user
of the framework would) and `protocol` (the student gets one step of the registrar with
a bug, in `step.py`, and fixes it: the check runs the simulation with their copy in the
step's place). `kit.py` reads the exercises (what is the student's, `[yours]`, and what a
folder changed besides), `grade.py` checks a folder (with the kit's own rules besides the
checker's, `rules.py`), running the student's code in a child process (`_seeds.py`) where
this package cannot be imported, `cli.py` the command; `STEPS` lists the protocol steps a
student's copy can replace, with their shapes (`shipped_step`: the registrar's own, for a
teacher and a student's own tests, never reachable from a check).
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable, Collection, Iterable, Iterator, Sequence
from collections.abc import Set as AbstractSet
from typing import Any

from rr_actors._types import Status
from rr_actors.config import Steps
from rr_actors.errors import ConfigError, _known_names

__all__ = ["STEPS", "replaced_step", "shipped_step"]


def _climb(parent: str | None, resources: Collection[str], status: Status) -> Iterable[str]:
    """The registrar's own climb: to the resource the id is a dependency of, whatever
    the status (rule 9: a status reaches every resource on its paths)."""
    del status
    return [parent] if parent is not None and parent in resources else []


def _shares(stored: Any, request: Any, loading: bool, failed: bool) -> bool:
    """The catalog's own dedup test: an equal request shares the resource, loaded or
    still loading (the call waits for its load), unless its provider reported it
    `FATAL` (rule 1: a dead resource is never matched again)."""
    del loading
    return not failed and bool(stored == request)


def _group(strategy: str, names: Sequence[str], crashed: str) -> Iterable[str]:
    """The supervisor's own group (OTP): `one_for_one` the crashed child alone,
    `one_for_all` every child, `rest_for_one` it and the children started after it."""
    if strategy == "one_for_one":
        return (crashed,)
    if strategy == "one_for_all":
        return tuple(names)
    return tuple(names[names.index(crashed) :])


def _unloads(left: Collection[str]) -> bool:
    """The registrar's own last-release test: the resource is unloaded once no consumer
    id is left on it (rule 7), and not before."""
    return not left


def _in_doubt(state: str) -> bool:
    """The registrar's own in-doubt test: a restored row not committed as loaded (its
    load or its unload cut short by a crash) is in doubt (rule 16)."""
    return state != "loaded"


def _reconcile(
    mine: AbstractSet[str], held: AbstractSet[str], under_way: AbstractSet[str]
) -> tuple[set[str], set[str]]:
    """The provider's own side of a reconcile: release the ids the consumer no longer
    holds; name unknown those it holds that this provider lost, but not a load still
    under way here (rules 12, 20)."""
    return set(mine - held), set(held - mine - under_way)


def _release_order(dependencies: tuple[str, ...]) -> list[str]:
    """The registrar's own teardown of a resource: every dependency released, then its
    own unload (rule 7)."""
    return [*dependencies, "unload"]


def _recent(times: Sequence[float], now: float, period: float) -> int:
    """The supervisor's own count (OTP's restart intensity): the restarts less than
    `period` seconds before `now`, this one included."""
    return sum(1 for t in times if now - t < period)


STEPS: dict[str, Callable[..., Any]] = {
    "climb": _climb,
    "recent": _recent,
    "release_order": _release_order,
    "reconcile": _reconcile,
    "in_doubt": _in_doubt,
    "group": _group,
    "shares": _shares,
    "unloads": _unloads,
}
"""The steps a classroom's copy may replace, each name with the registrar's own code
(`shipped_step`), each with its shape:

- `climb(parent, resources, status) -> ids`: the resources to notify in turn of a status
  delivered to a consumer id (`parent`: the resource it is a dependency of, `None` for a
  client's own call; `resources`: a collection of the ids the registrar serves; ids not
  in it are skipped).
- `shares(stored, request, loading, failed) -> bool`: whether a resource loaded (or
  `loading`) for `stored` serves a new call of `request` (rule 1); `failed`: reported
  `FATAL`. Asked for plain requests of one server, on the registrar's actor thread.
- `group(strategy, names, crashed) -> names`: the children (start-ordered `names`) a crash
  of `crashed` takes down with it, itself included, per `strategy` (`"one_for_one"`,
  `"one_for_all"`, `"rest_for_one"`); on the supervisor's thread.
- `unloads(left) -> bool`: whether a release unloads a loaded resource, `left` the
  frozenset of consumer ids still on it; on the registrar's actor thread.
- `in_doubt(state) -> bool`: whether a restored row (`"loading"`, `"loaded"`,
  `"unloading"`) was cut short by a crash (rule 16); as the registrar starts.
- `reconcile(mine, held, under_way) -> (release, unknown)`: a provider's reconcile with
  one consumer (frozensets of `str`: its ids for it, those the consumer holds there, those
  loading); the ids to release (not in `mine`: skipped) and to answer unknown (reported
  `FATAL`); on the provider's actor thread.
- `release_order(dependencies) -> order`: at a resource's last release, its dependencies'
  query ids (oldest first) and `"unload"`, each once, in the order they run (those before
  `"unload"` released before it, the rest after); on the registrar's actor thread.
- `recent(times, now, period) -> int`: at a restartable exit, how many restarts count
  toward intensity (`times`: monotonic seconds of every restart since the supervisor
  started, this one last; `period` in seconds); on the supervisor's thread.
"""


def shipped_step(name: str) -> Callable[..., Any]:
    """The registrar's own code of step `name`, as a function of the step's shape.

    Raises:
        ConfigError: `name` is not one of `STEPS`.
    """
    if name not in STEPS:
        raise ConfigError(
            f"no protocol step {name!r}" + _known_names(name, STEPS, shown=len(STEPS))
        )
    return STEPS[name]


@contextlib.contextmanager
def replaced_step(name: str, step: Callable[..., Any]) -> Iterator[Steps]:
    """A `Steps` record with `step` as step `name` (and the steps of an enclosing block),
    to hand in as `RegistrarConfig(steps=)` or `Supervisor(steps=)`; inside the block, this
    thread's simulated runs (`rr_actors_lab.experiments.simulate.run_seed`) run with it.

    A registrar runs the steps its config hands it, no other: one made without them runs its
    own code, inside the block or not. A step runs on the registrar's actor thread: it must
    return at once and must not call a registrar. Simulated runs are back to the registrar's
    own code when the block ends, even on an error.

        with replaced_step("climb", my_climb) as steps:
            run = simulate.run_seed(plan, 3)                 # (or run_seed(plan, 3, steps=steps))
            reg = rr.ResourceRegistrar(rr.RegistrarConfig(name="mine", steps=steps))

    Raises:
        ConfigError: `name` is not one of `STEPS`, `step` is not callable, or another copy
            of the step is in place (blocks of one step do not nest).
    """
    from rr_actors_lab.experiments import simulate as _simulate  # noqa: PLC0415 - its extra's

    shipped_step(name)
    if not callable(step):
        raise ConfigError(f"the step {name!r} must be a function, got {step!r}")
    outer = _simulate.steps_now()
    if getattr(outer, name) is not None:
        raise ConfigError(f"the step {name!r} is replaced already (one copy at a time)")
    with _simulate.steps_in_place(dataclasses.replace(outer, **{name: step})) as steps:
        yield steps
