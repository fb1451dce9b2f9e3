"""Display texts: what an observer shows of a request, a response or a resource, made once.

```
 a record set (start_load, load_done, update_response, a client record added)
   ──show_*──► a plain value (built-in strs, numbers, small containers of them: its repr
   │           runs no user code) ──► the text now, on the actor thread, in the same write
   └── any other value, any label(request) ──► a worker, bounded by compare_timeout
           ──► its text, or "<repr failed: TimeoutError>" ──► back on the actor thread
           ──► the record's text set (if it still holds that value) ──► written
```

An observer never calls `repr` itself: a backup's values are never unpickled to show
them, and a `__repr__` that hangs or raises costs one worker thread once, when the value
is stored. The texts are made by `rr_actors._catalog.texts` (pure functions). Why client
records share one text per request object: docs/explanation/inside.md, "Display texts".
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rr_actors._catalog import ClientRecord, Resource
from rr_actors._catalog.texts import display_text, label_text, plain_text
from rr_actors._registrar.state import Shared

_BUILTIN = frozenset({str, bytes, int, float, complex, bool, type(None), dict, list, tuple, set})
"""Requests of these exact types get their record's text when it is first read."""


def _off_actor(
    shared: Shared, work: Callable[[], str], what: str, then: Callable[[str], None]
) -> None:
    """Run `work()` on a worker, bounded by `compare_timeout`; `then(text)` on the actor."""
    done = shared.come_back(lambda text, _: then(text))

    def task() -> None:
        done.set_result(work())  # (work never raises)

    def overdue() -> None:
        done.set_result(f"<{what} failed: TimeoutError>")

    try:
        shared.workers.submit(task, timeout=shared.config.compare_timeout, on_overdue=overdue)
    except RuntimeError:
        then(f"<{what} failed: no worker thread>")


def _text_now_or_later(shared: Shared, value: Any, then: Callable[[str], None]) -> str | None:
    text = plain_text(value)
    if text is None:
        _off_actor(shared, lambda: display_text(value), "repr", then)
    return text


def show_request(
    shared: Shared,
    resource: Resource,
    label: Callable[[Any], Any] | None,
    labelled: Callable[[], None] | None = None,
) -> None:
    """Give a resource just begun its request's text (and label), on the actor thread, before
    its write; one that needs user code is written later. `labelled()` runs once the label
    is set, if there is a `label`."""
    catalog = shared.catalog
    rid = resource.id

    def later(request_text: str | None = None, label: str | None = None) -> None:
        if catalog.resources.get(rid) is resource:
            catalog.set_texts(rid, request_text=request_text, label=label)
            shared.commit()

    resource.request_text = _text_now_or_later(
        shared, resource.request, lambda text: later(request_text=text)
    )
    if label is not None:
        request = resource.request

        def label_made(text: str) -> None:
            later(label=text)
            if labelled is not None:
                labelled()

        _off_actor(shared, lambda: label_text(label, request), "label", label_made)


def show_response(shared: Shared, resource: Resource) -> None:
    """Give a resource whose response was just set that response's text (before its write)."""
    catalog = shared.catalog
    rid = resource.id
    version = resource.response_version

    def later(text: str) -> None:
        if catalog.resources.get(rid) is resource and resource.response_version == version:
            catalog.set_texts(rid, response_text=text)
            shared.commit()

    resource.response_text = _text_now_or_later(shared, resource.response, later)


class ClientTexts:
    """The request texts of one registrar's client records: one per request object held
    (`is`: no user code), shared by the records holding it; the table maps an object's
    `id` to a record holding it, and is rebuilt when it outgrows the records."""

    __slots__ = ("due", "holders", "shared", "waiting")

    def __init__(self, shared: Shared) -> None:
        self.shared = shared
        self.holders: dict[int, str] = {}  # id(request) -> a query id whose record holds it
        self.waiting: dict[str, list[str]] = {}  # query id whose text a worker makes -> others
        self.due: list[str] = []  # query ids of records added whose text nobody read yet

    def added(self, record: ClientRecord) -> None:
        """A client record was just added (before its write): its text now if it is written or
        its request is not of a built-in type, else when first read (`fill`)."""
        query_id = record.query.id
        if self.shared.saver.store is not None or type(record.query.request) not in _BUILTIN:
            self.show(query_id)
            return
        due = self.due
        due.append(query_id)
        catalog = self.shared.catalog
        if len(due) > 2 * len(catalog.client_records()) + 64:  # records gone unread
            self.due = [q for q in due if catalog.client(q) is not None]

    def fill(self) -> None:
        """Give each record added since the last read its text, in order: before a snapshot."""
        due, self.due = self.due, []
        for query_id in due:
            self.show(query_id)

    def show(self, query_id: str) -> None:
        catalog = self.shared.catalog
        record = catalog.client(query_id)
        if record is None or record.request_text is not None:
            return
        request = record.query.request
        holder_id = self.holders.get(id(request))
        holder = None if holder_id is None else catalog.client(holder_id)
        if holder is not None and holder.query.request is request:
            if holder.request_text is not None:
                record.request_text = holder.request_text
                return
            waiting = self.waiting.get(holder.query.id)
            if waiting is not None:  # its text is on its way
                waiting.append(query_id)
                return
        records = catalog.client_records()
        if len(self.holders) > 2 * len(records) + 64:  # stale entries: records gone
            self.holders = {id(r.query.request): r.query.id for r in records}
        self.holders[id(request)] = query_id
        text = plain_text(request)
        if text is not None:
            record.request_text = text
            return
        self.waiting[query_id] = []
        _off_actor(
            self.shared, lambda: display_text(request), "repr", lambda t: self.shown(query_id, t)
        )

    def shown(self, query_id: str, text: str) -> None:
        """A worker made the text of `query_id`'s request: give it to each record waiting."""
        catalog = self.shared.catalog
        for waiting_id in [query_id, *self.waiting.pop(query_id, ())]:
            record = catalog.client(waiting_id)
            if record is not None and record.request_text is None:
                catalog.set_client_text(waiting_id, text)
        self.shared.commit()
