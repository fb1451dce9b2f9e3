"""Test probes on a registrar's named steps (the seam behind `rr_actors.testing.intercept`).

Race tests need to hold a registrar at an exact point (before it handles an `Abandon`,
after it committed a pending record, as it ends) or to watch which thread runs a step.
They do it through step *names*, never through private handler tables: a name that no
step has raises `ConfigError`, so renaming a step cannot turn a race test into a test
that passes without racing anything.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from rr_actors.errors import ConfigError

__all__ = ["STEPS", "Hook", "Probes"]

Hook = Callable[[Any], None]
"""`hook(subject)`: the message a step handles, or what a point is about."""

MESSAGE_STEPS: frozenset[str] = frozenset(
    {
        "load",  # a Load arrives at the provider
        "unload",  # an Unload arrives at the provider
        "abandon",  # an Abandon arrives at the provider
        "fetch",  # a Fetch arrives at the provider
        "status_notice",  # a StatusNotice arrives at a consumer
        "revoke",  # a Revoke arrives at a consumer
        "response_updated",  # a ResponseUpdated arrives at a consumer
        "consumer_down",  # death watch: a consumer is gone for good
        "reconcile",  # a Reconcile arrives at the provider (a consumer lists what it holds)
        "reconcile_ask",  # a ReconcileAsk arrives at a consumer (its provider restarted)
        "pending",  # a durable call's pending record is to be committed
        "client_loaded",  # a call's answer is to be recorded
        "call_failed",  # a call failed or was withdrawn
        "request",  # a request from the handle (run in the actor thread)
        "answer",  # the answer to one of this actor's own questions
        "flush",  # the save-interval timer fired
        "crash",  # `rr_actors.testing.crash`
    }
)
"""Steps that handle one message on the registrar's actor thread (`before`/`after` it)."""

POINTS: frozenset[str] = frozenset(
    {
        "close_resource",  # unregister_server: a resource gets FATAL, is revoked, unloads
        "unload_resource",  # the last consumer left: dependencies, then `unload`
        "stop_drained",  # stop(): waiting callers failed, mailbox drained; the actor ends next
        "send_load",  # a call's Load is about to leave the caller's thread (durable: committed)
        "withdraw",  # a caller that stopped waiting is about to send its Abandon
    }
)
"""Points inside a step (`before` runs there; `after` is the same as `before`)."""

STEPS: frozenset[str] = MESSAGE_STEPS | POINTS
"""Every name `rr_actors.testing.intercept` accepts."""


class Probes:
    """The hooks installed on one registrar, by step name (any thread may fire them)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._before: dict[str, tuple[Hook, ...]] = {}
        self._after: dict[str, tuple[Hook, ...]] = {}

    def add(self, step: str, *, before: Hook | None, after: Hook | None) -> None:
        """Install hooks on `step`.

        Raises:
            ConfigError: no step has that name.
        """
        if step not in STEPS:
            raise ConfigError(f"no registrar step is named {step!r}; steps: {sorted(STEPS)}")
        with self._lock:
            if before is not None:
                self._before[step] = (*self._before.get(step, ()), before)
            if after is not None:
                self._after[step] = (*self._after.get(step, ()), after)

    def remove(self, step: str, *, before: Hook | None, after: Hook | None) -> None:
        """Remove hooks `add` installed (no-op for hooks that are not there)."""
        with self._lock:
            for table, hook in ((self._before, before), (self._after, after)):
                if hook is not None and hook in table.get(step, ()):
                    table[step] = tuple(h for h in table[step] if h is not hook)

    def around(self, step: str, subject: Any, run: Callable[[Any], None]) -> None:
        """Run `run(subject)` between the `before` and `after` hooks of `step`."""
        for hook in self._before.get(step, ()):
            hook(subject)
        run(subject)
        for hook in self._after.get(step, ()):
            hook(subject)

    def fire(self, step: str, subject: Any) -> None:
        """Run the hooks of a point `step` (its `before` hooks, then its `after` hooks)."""
        for hook in (*self._before.get(step, ()), *self._after.get(step, ())):
            hook(subject)
