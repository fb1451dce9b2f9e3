"""The other hosts of a run: one host process per host, each its host's router and tree.

    run process (in the first host's namespace: its router, clients, managers without `host`)
      │  HostProcess.start ── ip netns exec rrx-<pid>-<i>
      │                         python -m rr_actors_lab.experiments._host_child SPEC PARENT_PID
      ▼
    host process (one per other host)                       its stdout, one JSON line each:
      ZenohNetwork(listen: its addresses, connect: the      {"e": event}   ──► the run's events
        hosts before it; mutual TLS; `lease`)  = the host's  {"r": reply}   ──► HostProcess.ask
        Zenoh router (ROUTER-mode session)                   its stdin: {"op": ...} lines; end
      Supervisor(the managers with `host` = it, network=)    of file: stop the tree and exit
        └─ manager processes: CLIENT sessions through the router's Unix socket

`freeze` SIGSTOPs a host process (its router and supervisor; its managers run on);
`kill_router` SIGKILLs it (its managers die with it) and `HostProcess` starts it again at
once, restoring every manager's catalog.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import pickle
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import rr_actors as rr
from rr_actors import events
from rr_actors._transport.resolve import RESOLVE_STRATEGIES
from rr_actors_lab.experiments.plan import Plan
from rr_actors_lab.experiments.reading import import_object

__all__ = ["HostProcess", "HostSpec"]

logger = logging.getLogger("rr_actors.experiments")

SYSTEM = "experiment"
"""The Zenoh system every run's hosts join."""


@dataclasses.dataclass(frozen=True)
class HostSpec:
    """What one host process runs.

    Attributes:
        plan: the plan (one compared value).
        host: the host's name.
        listen: its Zenoh endpoints (`tls/<address>:<port>` on each of its links).
        connect: the endpoints it dials (the routers of the hosts before it).
        lease: `ZenohNetwork(lease=)`, seconds.
        tls: the keyword arguments of `rr.ZenohTLS` (paths and members).
        state_dir: its managers' catalogs (`None`: in memory).
        seed: the run's seed (the backoff jitter of its tree).
        namespace: its network namespace.
    """

    plan: Plan
    host: str
    listen: tuple[str, ...]
    connect: tuple[str, ...]
    lease: float
    tls: dict[str, Any]
    state_dir: str | None
    seed: int
    namespace: str


def network(spec: HostSpec) -> rr.ZenohNetwork:
    """The host's `ZenohNetwork` (its router), with the plan's rule 22 policy (`resolve`)."""
    plan = spec.plan
    resolve: Any = plan.hosts.resolve if plan.hosts is not None else "first_served"
    if resolve not in RESOLVE_STRATEGIES:  # (a user's function, as a setup is imported)
        resolve = import_object(resolve, base_dir=plan.base_dir)
    return rr.ZenohNetwork(
        system=SYSTEM,
        listen=list(spec.listen),
        connect=list(spec.connect),
        tls=rr.ZenohTLS(**spec.tls),
        lease=spec.lease,
        resolve=resolve,
    )


# -- the run's side ----------------------------------------------------------------------------


class HostProcess:
    """One host's process, driven from the run process; started again if it dies.

    Args:
        spec: what it runs.
        spec_path: where its spec is written (read by the host process).
        on_event: called with each event of its tree (on its reader thread).
        on_start: called with the new pid and the monotonic time at each (re)start.
    """

    def __init__(
        self,
        spec: HostSpec,
        spec_path: Path,
        *,
        on_event: Callable[[events.Event], object],
        log: Path,
    ) -> None:
        self.spec = spec
        self.name = spec.host
        self._path = spec_path
        self._on_event = on_event
        self._log = log
        spec_path.write_bytes(pickle.dumps(spec))
        self._replies: queue.Queue[Any] = queue.Queue()
        self._lock = threading.Lock()
        self._stopping = False
        self.restarts: list[float] = []  # wall-clock times the host was started again
        self.process: subprocess.Popen[bytes] | None = None
        self._reader: threading.Thread | None = None

    @property
    def pid(self) -> int | None:
        """The host process's pid (`None` before `start`)."""
        return None if self.process is None else self.process.pid

    def start(self, *, timeout: float) -> None:
        """Start the host process; return once its tree serves.

        Raises:
            RrError: it did not start within `timeout` seconds, or exited first (its
                output is quoted).
        """
        command = [
            *("ip", "netns", "exec", self.spec.namespace),
            *(sys.executable, "-m", "rr_actors_lab.experiments._host_child"),
            *(str(self._path), str(os.getpid())),
        ]
        with self._log.open("ab") as err:
            self.process = subprocess.Popen(  # noqa: S603 - our own module, by its path
                command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err
            )
        reader = self._reader = threading.Thread(
            target=self._read, args=(self.process,), name=f"rr-host-{self.name}", daemon=True
        )
        reader.start()
        try:
            self._answer(timeout, "ready")
        except rr.RrError:
            self.kill()
            raise

    def _read(self, process: subprocess.Popen[bytes]) -> None:
        assert process.stdout is not None
        for line in process.stdout:
            try:
                message = json.loads(line)
            except ValueError:
                continue
            if "e" in message:
                with contextlib.suppress(Exception):  # an event this version cannot read
                    self._on_event(events.from_dict(message["e"]))
            elif "r" in message:
                self._replies.put(message["r"])
        process.wait()
        self._replies.put(None)  # it ended
        with self._lock:
            stopping = self._stopping
        if not stopping:
            self._restart(process)

    def _restart(self, dead: subprocess.Popen[bytes]) -> None:
        """The host process died (`kill_router`): start it again, as a service manager would."""
        logger.info("host %s exited (%s): starting it again", self.name, dead.returncode)
        self.restarts.append(time.time())
        self._replies = queue.Queue()
        try:
            self.start(timeout=self.spec.plan.hosts.start_timeout if self.spec.plan.hosts else 30)
        except rr.RrError:
            logger.exception("host %s did not start again", self.name)

    def _answer(self, timeout: float, what: str) -> Any:
        try:
            reply = self._replies.get(timeout=timeout)
        except queue.Empty:
            raise rr.RrError(f"host {self.name}: no {what} within {timeout:g} s") from None
        if reply is None:
            tail = self._log.read_text(errors="replace")[-2000:]
            raise rr.RrError(f"host {self.name} exited before {what}:\n{tail}")
        return reply

    def ask(self, op: str, *, within: float, **args: Any) -> Any:
        """Send one command to the host process; its reply (`RrError`: none within `within`
        seconds)."""
        process = self.process
        if process is None or process.stdin is None:
            raise rr.RrError(f"host {self.name} is not running")
        try:
            process.stdin.write(json.dumps({"op": op, **args}).encode() + b"\n")
            process.stdin.flush()
        except OSError as exc:
            raise rr.RrError(f"host {self.name} is not running ({exc})") from exc
        return self._answer(within, op)

    def stop(self, *, timeout: float) -> None:
        """Stop its tree and end the host process (SIGKILL after `timeout` seconds)."""
        with self._lock:
            self._stopping = True
        process = self.process
        if process is None:
            return
        with contextlib.suppress(ProcessLookupError):
            process.send_signal(signal.SIGCONT)  # a frozen one must run to stop
        if process.stdin is not None:
            with contextlib.suppress(OSError):
                process.stdin.close()
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            self.kill()
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(timeout)

    def kill(self) -> None:
        """SIGKILL the host process and reap it (no restart)."""
        with self._lock:
            self._stopping = True
        if self.process is not None:
            with contextlib.suppress(ProcessLookupError):
                self.process.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.process.wait(5.0)
