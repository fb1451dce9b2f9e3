"""Display texts: what an observer shows of a request, a response or a resource, made once.

```
 a record set (start_load, load_done, update_response, a client record added)
   ──show_*──► a plain value (built-in strs, numbers, small containers of them: its repr
   │           runs no user code) ──► the text now, on the actor thread, in the same write
   └── any other value, any label(request) ──► a worker, bounded by compare_timeout
           ──► its text, or "<repr failed: TimeoutError>" ──► back on the actor thread
           ──► the record's text set (if it still holds that value) ──► written
```

An observer, live or reading a backup, shows these texts and never calls `repr` itself:
a backup's values are never unpickled to show them (that would run code from the file),
and a `__repr__` that hangs or raises costs one worker thread once, when the value is
stored, never a refresh of the observer (`rr_actors.observe`). A text is a bounded
`repr` (at most `TEXT_WIDTH` characters); a failure is recorded in its place
(`<repr failed: ValueError>`) and never retried. The texts themselves are made by
`rr_actors._catalog.texts` (pure functions). The cost: a plain value's text on the actor
thread (a few microseconds for a small dict), a worker round trip and one more write for
any other value or a label.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rr_actors._catalog import Resource
from rr_actors._catalog.texts import display_text, label_text, plain_text
from rr_actors._registrar.state import Shared

__all__ = ["show_client", "show_request", "show_response"]


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


def show_request(shared: Shared, resource: Resource, label: Callable[[Any], Any] | None) -> None:
    """Give a resource just begun its request's text (and label); call before its write.

    Runs on the actor thread; a text that needs user code comes later, and is written
    then (or with the next write).
    """
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
        _off_actor(
            shared, lambda: label_text(label, request), "label", lambda text: later(label=text)
        )


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


def show_client(shared: Shared, query_id: str) -> None:
    """Give a client record just added its request's text (before its write)."""
    catalog = shared.catalog
    record = catalog.clients.get(query_id)
    if record is None or record.request_text is not None:
        return

    def later(text: str) -> None:
        if catalog.clients.get(query_id) is record:
            catalog.set_client_text(query_id, text)
            shared.commit()

    record.request_text = _text_now_or_later(shared, record.query.request, later)
