"""Fault commands across hosts: a page's button on host A, the fault injected on host B.

```
 host A (serving the page)                         host B (its tree)
 page's button ─► Server ─► SystemView.fault ─► send_fault ── JSON command (a get on
                                                      │        rr/<system>/obs/B/fault) ──►
                                                      │   FaultDesk: checked, then run on a
                                                      │   thread of its own (MAX_FAULTS at
                                                      │   once) ─► _faults.inject ─► an
                                                      │   "ObserverFault" event in B's hub
 "B: what it did" or FaultRefused ◄── {"ok", "message", "status"} ◄─┘
```

A command is `{"kind": "kill"|"hang"|"resume"|"fatal", "by": member, ...}` with the page's
request's fields; a host without `allow_faults=True` refuses every one.
"""

from __future__ import annotations

import contextlib
import json
import logging
import threading
import time
from typing import TYPE_CHECKING, Any

from rr_actors._transport.zenoh.callbacks import tracked
from rr_actors._transport.zenoh.wire import ObserverKey
from rr_actors.config import NAME
from rr_actors_lab.observe._crossing import dumps, text
from rr_actors_lab.observe._faults import KINDS, FaultRefused, Faults, inject
from rr_actors_lab.observe._hub import Hub

if TYPE_CHECKING:
    import zenoh

    from rr_actors._transport.zenoh.net import Services

__all__ = ["FAULT_TIMEOUT", "MAX_COMMAND", "MAX_FAULTS", "FaultDesk", "send_fault"]

logger = logging.getLogger("rr_actors")

FAULT_TIMEOUT = 8.0
"""Seconds a page's host waits for another host's answer to a fault command."""


MAX_COMMAND = 4096
"""Bytes a fault command may have."""

MAX_FAULTS = 4
"""Fault commands from other hosts run at once; one more is refused."""


def send_fault(services: Services, by: str, member: str, kind: str, data: dict[str, Any]) -> str:
    """Ask host `member`'s `FaultDesk` to inject a fault into one of its managers; what it did.
    Waits up to `FAULT_TIMEOUT` seconds, on the calling thread; `by` is this host's member
    name, `kind` one of `_faults.KINDS`, `data` the page's request.

    Raises:
        FaultRefused: that host refused (its reason), or did not answer.
    """
    command = {k: v for k, v in data.items() if k != "host"}
    command.update(kind=kind, by=by)
    key = services.keys.observer(ObserverKey(member, "fault"))
    replies = services.session.get(key, payload=dumps(command), timeout=FAULT_TIMEOUT)
    for reply in replies:
        if reply.ok is None:
            continue
        try:
            answer = json.loads(reply.ok.payload.to_bytes())
        except (ValueError, RecursionError):
            break
        if not isinstance(answer, dict) or not text(answer.get("message")):
            break
        if answer.get("ok") is True:
            return f"{member}: {answer['message']!s}"
        status = answer.get("status")
        code = status if isinstance(status, int) and 400 <= status < 600 else 409
        raise FaultRefused(f"{member} refused: {answer['message']}", code)
    raise FaultRefused(
        f"{member} did not answer within {FAULT_TIMEOUT:g} s (is the link to it up?)", 504
    )


class FaultDesk:
    """Takes the fault commands other hosts send this host (its `fault` queryable).

    Args:
        hub: this host's own hub (each fault done is an `ObserverFault` event in it).
        services: the router's session and what goes with it.
        member: this host's member name.
        faults: the teaching mode's faults (`None`: every command is refused).
    """

    def __init__(self, hub: Hub, services: Services, member: str, faults: Faults | None) -> None:
        self._hub = hub
        self._member = member
        self._faults = faults
        self._running = threading.BoundedSemaphore(MAX_FAULTS)
        self._threads: set[threading.Thread] = set()  # commands running (each replies)
        self._lock = threading.Lock()
        self._closed = False
        key = services.keys.observer(ObserverKey(member, "fault"))
        self._queryable = services.session.declare_queryable(
            key, tracked(services.session, self._on_query)
        )

    def close(self, timeout: float = 5.0) -> None:
        """Take no more commands; wait (at most `timeout` s) for those running to answer
        (they call Zenoh: not once the session closed)."""
        with self._lock:
            self._closed = True
            running = list(self._threads)
        with contextlib.suppress(Exception):
            self._queryable.undeclare()  # type: ignore[no-untyped-call]
        deadline = time.monotonic() + timeout
        for thread in running:
            thread.join(max(0.0, deadline - time.monotonic()))

    def _on_query(self, query: zenoh.Query) -> None:  # (Zenoh's thread: hand it over)
        if not self._running.acquire(blocking=False):
            self._answer(query, False, "too many fault commands at once: try again", 503)
            return
        thread = threading.Thread(
            target=self._run, args=(query,), name="rr-observe-fault", daemon=True
        )
        with self._lock:
            if self._closed:
                self._running.release()
                closed = True
            else:
                self._threads.add(thread)
                thread.start()
                closed = False
        if closed:
            self._answer(query, False, f"{self._member} stopped taking commands", 503)

    def _run(self, query: zenoh.Query) -> None:
        try:
            data = query.payload.to_bytes() if query.payload is not None else b""
            try:
                message = self._command(data)
            except FaultRefused as exc:
                self._answer(query, False, str(exc), exc.status)
            else:
                self._answer(query, True, message, 200)
        except Exception:
            logger.exception("observer of %s: a fault command failed", self._member)
            self._answer(query, False, "the command failed on this host (see its log)", 500)
        finally:
            self._running.release()
            with self._lock:
                self._threads.discard(threading.current_thread())

    def _command(self, data: bytes) -> str:
        """Check and run one fault command; what was done (`FaultRefused`: why not)."""
        if len(data) > MAX_COMMAND:
            raise FaultRefused("the command is too large", 413)
        try:
            command = json.loads(data)
        except (ValueError, RecursionError):
            raise FaultRefused("the command is not JSON", 400) from None
        if not isinstance(command, dict):
            raise FaultRefused("the command must be a JSON object", 400)
        kind, by = command.get("kind"), command.get("by")
        if not isinstance(by, str) or not NAME.fullmatch(by):
            raise FaultRefused("the command names no member it comes from (by)", 400)
        if kind not in KINDS:
            raise FaultRefused(f"no fault {kind!r} ({', '.join(KINDS)})", 404)
        if self._faults is None:
            raise FaultRefused(
                f"{self._member} does not allow faults: its observer was opened without "
                "allow_faults=True",
                403,
            )
        done = inject(self._faults, kind, command)
        line = f"{done} (from {by}'s page)"
        self._hub.add_event(
            {"type": "ObserverFault", "kind": kind, "text": line, "at": time.time()}
        )
        return done

    def _answer(self, query: zenoh.Query, ok: bool, message: str, status: int) -> None:
        try:
            with contextlib.suppress(Exception):
                query.reply(query.key_expr, dumps({"ok": ok, "message": message, "status": status}))
        finally:
            with contextlib.suppress(Exception):
                query.drop()  # type: ignore[no-untyped-call]
