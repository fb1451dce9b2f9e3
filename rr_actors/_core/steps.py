"""Steps of the registrar's protocol a classroom exercise may replace (`rr_actors.teach`).

One slot per step, `None` unless an exercise's check put a student's copy there
(`rr_actors.teach.replaced_step`): the registrar (or its catalog) reads the slot where
the step runs and runs its own code when it is empty (one attribute read: nothing else
when unused). A
replaced step is seen by the registrars of this OS process only: a simulated run's (every
simulated process is a greenlet of it), never a manager in a real process of its own.

- `climb(parent, resources, status)`: where a status delivered to a consumer id climbs
  (`status.py`'s `on_status_notice`). `parent` is the id of the resource that id is a
  dependency of (`None`: a client's own call), `resources` the ids of the resources its
  registrar serves, `status` the `Status`; the ids of the resources to notify in turn.
- `shares(stored, request, loading, failed)`: whether a resource of `stored` request
  serves a call of `request` (`_catalog/catalog.py`'s `_match`, for plain requests:
  those with a digest); `loading`: its load has not ended yet; `failed`: its provider
  reported it `FATAL`.
- `group(strategy, names, crashed)`: the children a crash of `crashed` takes down with it
  (`_supervision/policy.py`'s `affected`): `strategy` the supervisor's, `names` every
  child's name in start order; the names to stop and restart, itself included.
- `unloads(left)`: whether a release that left consumer ids `left` (a collection of
  query ids) on a loaded resource unloads it (`provider.py`'s `release`).
- `in_doubt(state)`: whether a restored row in `state` (`"loading"`, `"loaded"`,
  `"unloading"`) was cut short by a crash (`life.py`'s `cut_short`, rule 16).
- `reconcile(mine, held, under_way)`: at a consumer's reconcile, the ids a provider
  holds for it (`mine`), those it says it holds (`held`), those whose load is under way
  here (`under_way`), all sets of query ids: the ids to release and the ids to name
  unknown to it (`provider.py`'s `on_reconcile`).
- `release_order(dependencies)`: when a resource goes, the query ids of its
  dependencies (a tuple) and `"unload"` (its own unload), in the order they run: those
  before `"unload"` are released before it, those after once it is done, those left
  out never (`provider.py`'s `unload_resource`).
- `recent(times, now, period)`: at a child's exit, how many of the restarts counted so
  far (`times`, monotonic seconds, this one's `now` last) count toward the restart
  intensity (`_supervision/policy.py`'s `RestartIntensity.add`): above `max_restarts`,
  the supervisor gives up.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterable, Sequence, Set
from typing import Any

from rr_actors._types import Status

__all__ = [
    "climb",
    "group",
    "in_doubt",
    "recent",
    "reconcile",
    "release_order",
    "shares",
    "unloads",
]

climb: Callable[[str | None, Collection[str], Status], Iterable[str]] | None = None
"""The student's status climb, or `None`: the registrar's own."""

shares: Callable[[Any, Any, bool, bool], bool] | None = None
"""The student's dedup test, or `None`: the catalog's own."""

group: Callable[[str, Sequence[str], str], Iterable[str]] | None = None
"""The student's restart group of a crash, or `None`: the supervisor's own."""

unloads: Callable[[Collection[str]], bool] | None = None
"""The student's last-release test, or `None`: the registrar's own (no id left)."""

in_doubt: Callable[[str], bool] | None = None
"""The student's in-doubt test of a restored row's state, or `None`: the registrar's own."""

Reconcile = Callable[[Set[str], Set[str], Set[str]], tuple[Iterable[str], Iterable[str]]]
"""`reconcile(mine, held, under_way) -> (ids to release, ids unknown)`."""

reconcile: Reconcile | None = None
"""The student's reconcile (ids to release, ids unknown), or `None`: the registrar's own."""

release_order: Callable[[tuple[str, ...]], Iterable[str]] | None = None
"""The student's teardown order (`"unload"` among the ids), or `None`: the registrar's
own (every dependency, then the unload)."""

recent: Callable[[tuple[float, ...], float, float], int] | None = None
"""The student's count of the restarts within the period, or `None`: the supervisor's own."""
