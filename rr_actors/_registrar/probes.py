"""Test probes on a registrar's named steps (the seam behind `rr_actors.testing.intercept`).

Race tests need to hold a registrar at an exact point (before it handles an `Abandon`,
after it committed a pending record, as it ends) or to watch which thread runs a step.
They do it through step *names*, never through private handler tables: a name that no
step has raises `ConfigError`, so renaming a step cannot turn a race test into a test
that passes without racing anything.

The message steps are the step names of the actor's dispatch table (`actor.DISPATCH`,
one per message); the points inside steps are listed here; `actor.STEPS` is both.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

__all__ = ["POINTS", "Hook", "Probes"]

Hook = Callable[[Any], None]
"""`hook(subject)`: the message a step handles, or what a point is about."""

POINTS: frozenset[str] = frozenset(
    {
        "close_resource",  # unregister_server: a resource gets FATAL, is revoked, unloads
        "unload_resource",  # the last consumer left: dependencies, then `unload`
        "stop_drained",  # stop(): waiting callers failed, mailbox drained; the actor ends next
        "send_load",  # a call's Load is about to leave the caller's thread (durable: committed)
        "withdraw",  # a caller that stopped waiting is about to send its Abandon
        "events_written",  # a change and its events committed together; published next
    }
)
"""Points inside a step (`before` runs there; `after` is the same as `before`)."""


class Probes:
    """The hooks installed on one registrar, by step name (any thread may fire them)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._before: dict[str, tuple[Hook, ...]] = {}
        self._after: dict[str, tuple[Hook, ...]] = {}

    def add(self, step: str, *, before: Hook | None, after: Hook | None) -> None:
        """Install hooks on `step` (`intercept` checks that a step has that name)."""
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
