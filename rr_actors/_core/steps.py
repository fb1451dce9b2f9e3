"""Steps of the registrar's protocol a classroom exercise may replace (`rr_actors.teach`).

One slot per step, `None` unless an exercise's check put a student's copy there
(`rr_actors.teach.replaced_step`): the registrar (or its catalog) reads the slot where
the step runs and runs its own code when it is empty (one attribute read: nothing else
when unused). A replaced step is seen by the registrars of this OS process only: a
simulated run's (every simulated process is a greenlet of it), never a manager in a real
process of its own. Each slot's shape is in `rr_actors.teach.STEPS`; where the registrar
reads it, in the slot's docstring.
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
"""The student's status climb, or `None`: the registrar's own (`status.py`'s
`on_status_notice`)."""

shares: Callable[[Any, Any, bool, bool], bool] | None = None
"""The student's dedup test of plain requests, or `None`: the catalog's own (`_match`)."""

group: Callable[[str, Sequence[str], str], Iterable[str]] | None = None
"""The student's restart group of a crash, or `None`: the supervisor's own
(`_supervision/policy.py`'s `affected`)."""

unloads: Callable[[Collection[str]], bool] | None = None
"""The student's last-release test, or `None`: the registrar's own, no id left
(`provider.py`'s `release`)."""

in_doubt: Callable[[str], bool] | None = None
"""The student's in-doubt test of a restored row's state, or `None`: the registrar's own
(`life.py`'s `cut_short`, rule 16)."""

Reconcile = Callable[[Set[str], Set[str], Set[str]], tuple[Iterable[str], Iterable[str]]]
"""`reconcile(mine, held, under_way) -> (ids to release, ids unknown)`."""

reconcile: Reconcile | None = None
"""The student's reconcile (ids to release, ids unknown), or `None`: the registrar's own
(`provider.py`'s `on_reconcile`)."""

release_order: Callable[[tuple[str, ...]], Iterable[str]] | None = None
"""The student's teardown order (`"unload"` among the ids), or `None`: the registrar's
own, every dependency, then the unload (`provider.py`'s `unload_resource`)."""

recent: Callable[[tuple[float, ...], float, float], int] | None = None
"""The student's count of the restarts within the period, or `None`: the supervisor's own
(`_supervision/policy.py`'s `RestartIntensity.add`)."""
