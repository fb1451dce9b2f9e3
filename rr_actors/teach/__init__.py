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
step's place, `replaced_step`). `kit.py` reads the exercises, `grade.py` checks a
folder (with the kit's own rules besides the checker's, `rules.py`), `cli.py` the
command; `STEPS` lists the protocol steps a student's copy can replace, with their shapes.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Collection, Iterable, Iterator, Sequence
from collections.abc import Set as AbstractSet
from typing import Any

from rr_actors._core import runtime as _runtime
from rr_actors._types import Status
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
"""The steps a classroom's copy may replace, each name with the registrar's own code.

Each step's shape (`shipped_step` gives the registrar's own code as a function of it):

- `climb(parent, resources, status) -> ids`: where a status delivered to a consumer id
  climbs: `parent` the id of the resource that id is a dependency of (`None`: a client's
  own call), `resources` the ids of the resources its registrar serves (a collection:
  `in` is what to ask it), `status` the `rr_actors.Status`; returns the ids of the
  resources to notify in turn (an iterable of `str`; ids not in `resources` are skipped).
- `shares(stored, request, loading, failed) -> bool`: whether a resource loaded (or
  loading: `loading`) for request `stored` serves a new call of `request` (rule 1:
  equal requests share one resource); `failed`: its provider reported it `FATAL`.
  Asked for plain requests (those the catalog digests: numbers, strings, tuples,
  dicts of them...), of the same server, on the registrar's actor thread.
- `group(strategy, names, crashed) -> names`: the children a crash of child `crashed`
  takes down with it, itself included: `strategy` the supervisor's (`"one_for_one"`,
  `"one_for_all"`, `"rest_for_one"`), `names` every child's name in start order (a
  tuple of `str`); returns the names to stop and restart (an iterable of `str`; the
  supervisor stops them in reverse start order, then starts them in start order). Runs
  on the supervisor's thread.
- `unloads(left) -> bool`: whether the release of one consumer id of a loaded resource
  unloads it: `left` the consumer ids still on it after that release (a frozenset of
  query ids, maybe empty). Asked on the registrar's actor thread at each release.
- `in_doubt(state) -> bool`: whether a row restored from a backup was cut short by a
  crash (rule 16): `state` its state there, `"loading"`, `"loaded"` or `"unloading"`.
  Asked as the registrar starts, before it serves (its launching thread, then its
  actor thread).
- `reconcile(mine, held, under_way) -> (release, unknown)`: a provider's side of a
  reconcile with one consumer: `mine` the query ids it holds for that consumer, `held`
  those the consumer says it holds there, `under_way` those whose loads are under way
  here (frozensets of `str`); returns the ids to release here (those not in `mine` are
  skipped) and the ids to answer as unknown (the consumer reports them `FATAL`), two
  iterables of `str`. Asked on the provider's actor thread.
- `release_order(dependencies) -> order`: when a resource's last consumer left, the
  query ids of the calls it holds as dependencies (a tuple of `str`, oldest first)
  and `"unload"` (its provider's unload callback), in the order they run: every id
  and `"unload"` once (a list). Those before `"unload"` are released before it runs,
  those after once it is done. Asked on the registrar's actor thread.
- `recent(times, now, period) -> int`: at a child's exit that its supervisor would
  restart, how many restarts count toward its intensity: `times` every restart counted
  since the supervisor (re)started, this one last (a tuple of monotonic seconds), `now`
  this one's time, `period` the supervisor's (seconds). Above `max_restarts`, the
  supervisor gives up. Asked on the supervisor's thread.
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
def replaced_step(name: str, step: Callable[..., Any]) -> Iterator[None]:
    """Inside the block, the registrars of this OS process run `step` as their step `name`.

    Only the registrars of this process see it: those of a simulated run
    (`rr_actors.simulation`, `rr_actors.experiments.simulate`), never a manager in a real
    process of its own. The step runs on the registrar's actor thread (a simulated one):
    it must return at once and must not call a registrar. The registrar's own code is
    back when the block ends, even on an error.

    Raises:
        ConfigError: `name` is not one of `STEPS`, `step` is not callable, or another
            copy of the step is in place (blocks of one step do not nest).
    """
    shipped_step(name)
    if not callable(step):
        raise ConfigError(f"the step {name!r} must be a function, got {step!r}")
    if getattr(_runtime.steps, name) is not None:
        raise ConfigError(f"the step {name!r} is replaced already (one copy at a time)")
    setattr(_runtime.steps, name, step)
    try:
        yield
    finally:
        setattr(_runtime.steps, name, None)
