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
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterable
from typing import Any

from rr_actors._types import Status

__all__ = ["climb", "shares"]

climb: Callable[[str | None, Collection[str], Status], Iterable[str]] | None = None
"""The student's status climb, or `None`: the registrar's own."""

shares: Callable[[Any, Any, bool, bool], bool] | None = None
"""The student's dedup test, or `None`: the catalog's own."""
