"""Teaching mode: the faults the page's buttons inject (only with `allow_faults=True`).

```
 page button ─► confirm ─► POST /api/faults/<kind> {"child", "pid"} or {"registrar", "resource_id"}
   (JSON only, with the observer's token) ─► Faults.<kind>(...) ─► checks ─► the signal, or a FATAL
```

Every field is checked against the live tree first: a signal goes only to the pid the
supervisor has for that process manager now (an older incarnation's page gets a refusal),
through a pidfd where there is one, so the pid cannot be reused in between.
"""

from __future__ import annotations

import contextlib
import functools
import os
import selectors
import signal
import threading
from collections.abc import Callable
from typing import Any

from rr_actors._registrar import ResourceRegistrar
from rr_actors._types import Status
from rr_actors.config import ManagerSpec, SupervisorSpec, managers
from rr_actors_lab.observe._sources import Observable

__all__ = ["FATAL_MESSAGE", "KINDS", "FaultRefused", "Faults", "inject"]

FATAL_MESSAGE = "FATAL sent from the observer (teaching mode)"
"""The status message of a FATAL the page sends."""

FATAL_TIMEOUT = 5.0
"""Seconds a FATAL from the page may take to reach every consumer."""


class FaultRefused(Exception):  # noqa: N818 - a refusal, not an error of rr_actors
    """The page asked for a fault that cannot be injected now; the message says why.

    Attributes:
        status: the HTTP status to answer with.
    """

    def __init__(self, message: str, status: int = 409) -> None:
        super().__init__(message)
        self.status = status


class Faults:
    """Injects the teaching mode's faults into a live tree.

    Args:
        sup: the supervisor.
        spec: the whole tree's specs.
        catalogs: returns the catalog section the page was shown for a registrar.
    """

    def __init__(
        self,
        sup: Observable,
        spec: SupervisorSpec,
        catalogs: Any,
    ) -> None:
        self.sup = sup
        self.specs: dict[str, ManagerSpec] = {m.name: m for m in managers(spec)}
        self.catalogs = catalogs
        self._lock = threading.Lock()
        self._stopped: dict[int, int | None] = {}  # pid -> pidfd of processes we SIGSTOPped

    # -- signals ----------------------------------------------------------------------------

    def kill(self, child: str, pid: int) -> str:
        """SIGKILL process manager `child`, whose pid the page shows as `pid`."""
        self._forget_exited()
        self._signal(child, pid, signal.SIGKILL)
        self._forget(pid)
        return f"SIGKILL sent to {child} (pid {pid}); its supervisor restarts it"

    def hang(self, child: str, pid: int) -> str:
        """SIGSTOP process manager `child` (a hang); say how it resumes."""
        self._forget_exited()
        fd = self._signal(child, pid, signal.SIGSTOP, keep=True)
        with self._lock:
            self._stopped[pid] = fd
        hang_after = self.specs[child].hang_after
        if hang_after is None:
            return (
                f"SIGSTOP sent to {child} (pid {pid}): it hangs. It has no heartbeat, so "
                "nothing notices: press resume (SIGCONT) to let it go on"
            )
        return (
            f"SIGSTOP sent to {child} (pid {pid}): it hangs. Its heartbeat stops; after "
            f"{hang_after:g} s without one the supervisor kills it and restarts it (or press "
            "resume before that: SIGCONT)"
        )

    def resume(self, child: str, pid: int) -> str:
        """SIGCONT process manager `child` (after a hang)."""
        self._signal(child, pid, signal.SIGCONT)
        self._forget(pid)
        return f"SIGCONT sent to {child} (pid {pid}): it runs again"

    def _signal(
        self, child: str, pid: int, sig: signal.Signals, *, keep: bool = False
    ) -> int | None:
        spec = self.specs.get(child)
        if spec is None:
            raise FaultRefused(f"{child!r} is not a manager of this tree", 404)
        if spec.isolation != "process":
            raise FaultRefused(
                f"{child} runs in the supervisor's own process (a thread manager): "
                "there is no process of its own to signal"
            )
        if isinstance(pid, bool) or not isinstance(pid, int) or pid <= 0:
            raise FaultRefused(f"pid must be a positive int, got {pid!r}", 400)
        info = self.sup.snapshot(child)
        if info.state != "running" or info.pid != pid:
            raise FaultRefused(
                f"{child} is {info.state} with pid {info.pid}, not pid {pid}: the page is "
                "behind; nothing was sent"
            )
        fd: int | None = None
        with contextlib.suppress(AttributeError, OSError):
            fd = os.pidfd_open(pid)
        try:
            if self.sup.snapshot(child).pid != pid:  # checked again now that the pid is pinned
                raise FaultRefused(f"{child} was restarted meanwhile: nothing was sent")
            if fd is not None:
                signal.pidfd_send_signal(fd, sig)
            else:
                os.kill(pid, sig)
        except ProcessLookupError:
            raise FaultRefused(f"{child} (pid {pid}) has just exited: nothing was sent") from None
        finally:
            if fd is not None and not keep:
                os.close(fd)
        return fd

    def _forget(self, pid: int) -> None:
        with self._lock:
            fd = self._stopped.pop(pid, None)
        if fd is not None:
            os.close(fd)

    def _forget_exited(self) -> None:
        """Close the pidfds of stopped processes that have exited since (a heartbeat's kill)."""
        with self._lock:
            gone = [pid for pid, fd in self._stopped.items() if fd is not None and _exited(fd)]
            fds = [self._stopped.pop(pid) for pid in gone]
        for fd in fds:
            if fd is not None:
                os.close(fd)

    def resume_all(self) -> None:
        """SIGCONT every process a hang button stopped that still exists (at close); close every
        pidfd."""
        with self._lock:
            stopped, self._stopped = self._stopped, {}
        for pid, fd in stopped.items():
            try:
                with contextlib.suppress(OSError):
                    if fd is not None:
                        signal.pidfd_send_signal(fd, signal.SIGCONT)
                    else:
                        os.kill(pid, signal.SIGCONT)
            finally:
                if fd is not None:
                    os.close(fd)

    # -- a FATAL ----------------------------------------------------------------------------

    def fatal(self, registrar: str, resource_id: str) -> str:
        """Send FATAL on `registrar`'s resource `resource_id` to all its consumers; blocks until
        delivered (`FATAL_TIMEOUT` s at most): a worker thread's call."""
        if registrar not in self.specs:
            raise FaultRefused(f"{registrar!r} is not a manager of this tree", 404)
        section = self.catalogs(registrar)
        catalog = section.get("catalog") if section else None
        resources = catalog["resources"] if catalog else []
        resource = next((r for r in resources if r["id"] == resource_id), None)
        if resource is None:
            raise FaultRefused(f"{registrar} serves no resource {resource_id!r} now", 404)
        if not resource["consumers"]:
            raise FaultRefused(f"resource {resource_id[:8]} of {registrar} has no consumer")
        query_id = resource["consumers"][0]["query_id"]
        send = functools.partial(_send_fatal, query_id)
        try:
            self.sup.run_in(registrar, send, timeout=FATAL_TIMEOUT + 1.0)
        except Exception as exc:
            raise FaultRefused(f"the FATAL could not be sent: {type(exc).__name__}: {exc}") from exc
        return (
            f"FATAL sent on {registrar}/{resource['server']} {resource['request']} "
            f"(resource {resource_id[:8]}) to its {len(resource['consumers'])} consumer(s)"
        )


def _exited(pidfd: int) -> bool:
    """Whether the process of `pidfd` has exited (its pidfd polls readable then)."""
    with selectors.DefaultSelector() as selector:  # (not select(): fds of 1024 and up)
        selector.register(pidfd, selectors.EVENT_READ)
        return bool(selector.select(0))


def _send_fatal(query_id: str, registrar: ResourceRegistrar) -> None:
    """Runs in the provider's process: the FATAL of the page, on one of its consumer ids."""
    registrar.send_status(query_id, Status.FATAL, FATAL_MESSAGE, timeout=FATAL_TIMEOUT)


KINDS = ("kill", "hang", "resume", "fatal")
"""The faults a page may ask for."""


def inject(faults: Faults, kind: str, data: dict[str, Any]) -> str:
    """Run one fault request, checked field by field (a FATAL waits for its delivery: run it on
    a worker thread): `{"child": NAME, "pid": PID}` for kill, hang and resume; `{"registrar":
    NAME, "resource_id": ID}` for fatal. What was done, in words.

    Raises:
        FaultRefused: a malformed request, an unknown kind, or a fault that cannot be
            injected now (the message says why).
    """
    if kind in ("kill", "hang", "resume"):
        child, pid = data.get("child"), data.get("pid")
        if not isinstance(child, str) or isinstance(pid, bool) or not isinstance(pid, int):
            raise FaultRefused('expected {"child": NAME, "pid": PID}', 400)
        action: Callable[[str, int], str] = getattr(faults, kind)
        return action(child, pid)
    if kind == "fatal":
        registrar, resource_id = data.get("registrar"), data.get("resource_id")
        if not isinstance(registrar, str) or not isinstance(resource_id, str):
            raise FaultRefused('expected {"registrar": NAME, "resource_id": ID}', 400)
        return faults.fatal(registrar, resource_id)
    raise FaultRefused(f"no fault {kind!r} ({', '.join(KINDS)})", 404)
