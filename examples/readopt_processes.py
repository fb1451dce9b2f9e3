"""Re-adopt running OS processes after a manager crash (the ERM pattern of TeMoto, thesis 6).

An "external resource manager" (ERM) runs in its own process under a supervisor and starts
OS processes as resources. It is SIGKILLed; the supervisor restarts it; its registrar
restores its catalog before traffic is accepted, and `setup` re-adopts each process that
still runs. A process is identified by its pid AND its creation time, so a new process that
happens to get a recycled pid is never mistaken for ours (TeMoto checked the pid alone). On
Linux a signal goes through a pidfd opened before that check, so it cannot reach a process
that took the pid after the check either.

Run: `python examples/readopt_processes.py`
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import subprocess
import sys
import tempfile
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import rr_actors as rr


def process_start_time(pid: int) -> int | float | None:
    """When process `pid` started (clock ticks since boot on Linux), or `None` if it is gone.

    Linux: field 22 (`starttime`) of `/proc/<pid>/stat`. Elsewhere: `psutil` if installed.
    A zombie counts as gone.
    """
    stat = Path(f"/proc/{pid}/stat")
    if Path("/proc/self/stat").exists():
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            return None
        return None if fields[0] == "Z" else int(fields[19])
    try:
        import psutil  # noqa: PLC0415 - optional extra
    except ImportError as exc:
        raise RuntimeError("re-adopting processes needs /proc or psutil") from exc
    try:
        process = psutil.Process(pid)
        if process.status() == psutil.STATUS_ZOMBIE:
            return None
        return float(process.create_time())
    except psutil.NoSuchProcess:
        return None


def same_process(pid: int, start_time: float | None) -> bool:
    """Whether `pid` is still the very process that started at `start_time` (no pid reuse)."""
    return start_time is not None and process_start_time(pid) == start_time


@contextlib.contextmanager
def pidfd(pid: int) -> Iterator[int | None]:
    """A pidfd of `pid` (Linux >= 5.3), closed on exit; `None` if gone or unsupported."""
    try:
        fd = os.pidfd_open(pid)
    except (AttributeError, OSError):
        yield None
        return
    try:
        yield fd
    finally:
        os.close(fd)


def signal_process(pid: int, start_time: float | None, signum: int) -> bool:
    """Send `signum` to `pid` if it is still our process; return whether it was sent.

    The pidfd is opened before the start-time check, so it names the process that was
    checked: if that process ends and its pid is reused after the check, the signal goes
    nowhere rather than to the newcomer. Without pidfds (not Linux) a small race remains.
    """
    with pidfd(pid) as fd:
        if not same_process(pid, start_time):
            return False
        try:
            if fd is not None:
                signal.pidfd_send_signal(fd, signum)
            else:
                os.kill(pid, signum)
        except ProcessLookupError:
            return False
    return True


def wait_ended(pid: int, start_time: float | None, timeout: float) -> bool:
    """Wait (at most `timeout` seconds) until our process `pid` ended; whether it did."""
    with pidfd(pid) as fd:
        if fd is not None and same_process(pid, start_time):
            select.select([fd], [], [], timeout)  # readable once the process ended
    return not same_process(pid, start_time)


def erm_setup(registrar: rr.ResourceRegistrar) -> None:
    """The ERM's setup: re-adopt what the restored catalog says is running, then serve.

    Runs in the ERM's process, after its catalog was restored and before it accepts
    traffic (so no `start_process` call can interleave with the re-adoption).
    """

    adopted: dict[tuple[str, ...], dict[str, Any]] = {}  # what this ERM manages, by command

    def start(request: dict[str, Any]) -> dict[str, Any]:
        child = subprocess.Popen(  # noqa: S603 - the command comes from our own callers
            request["cmd"], start_new_session=True, stdout=subprocess.DEVNULL
        )
        # reap it when it ends (no zombie); after an ERM crash, init (or a subreaper) does
        threading.Thread(target=child.wait, name=f"reap-{child.pid}", daemon=True).start()
        response = {"pid": child.pid, "start_time": process_start_time(child.pid)}
        adopted[tuple(request["cmd"])] = response
        return response

    def stop(request: dict[str, Any], response: dict[str, Any]) -> None:
        adopted.pop(tuple(request["cmd"]), None)
        signal_process(response["pid"], response["start_time"], signal.SIGTERM)

    registrar.register_server("start_process", load=start, unload=stop)
    if not registrar.restored:
        return
    for query in registrar.server_queries("start_process"):
        response = query.response
        key = tuple(query.request["cmd"])
        if key in adopted:
            continue  # several consumers of one process: adopt it once
        if same_process(response["pid"], response["start_time"]):
            adopted[key] = response
            print(
                f"ERM re-adopted process {response['pid']} (pid and start time match)", flush=True
            )
        else:
            registrar.send_status(query.id, rr.Status.FATAL, "process ended while the ERM was down")
    for query in registrar.in_doubt:
        # The ERM died inside `start`: a process may have started without its pid being
        # recorded. This example does not stop it: such a process is LEAKED. A real ERM
        # would mark what it starts (an environment variable naming the query, a cgroup,
        # a pid file written before `start` returns) so that it can find and stop it here.
        print(f"in doubt, possibly leaked (never recorded): {query.request}", flush=True)


def running_processes(registrar: rr.ResourceRegistrar) -> list[int]:
    """Run in the ERM's process: pids of its resources that still run (pid + start time)."""
    return sorted(
        q.response["pid"]
        for q in registrar.server_queries("start_process")
        if same_process(q.response["pid"], q.response["start_time"])
    )


def main() -> None:
    """Start a supervised ERM, start a process, SIGKILL the ERM, watch it re-adopt."""
    tag = uuid.uuid4().hex[:6]
    erm, app_name = f"erm-{tag}", f"app-{tag}"
    statuses: list[str] = []
    fatal = threading.Event()

    def on_status(_: rr.Query, update: rr.StatusUpdate) -> None:
        statuses.append(f"{update.status.name}: {update.message}")
        fatal.set()

    with tempfile.TemporaryDirectory() as state_dir:
        spec = rr.ManagerSpec(erm, setup=erm_setup, isolation="process")
        with rr.Supervisor([spec], max_restarts=3, period=10.0, state_dir=state_dir) as sup:
            app = sup.registrar(app_name)
            sleeper = app.call(erm, "start_process", {"cmd": ["sleep", "60"]}, timeout=10.0)
            quick = app.call(
                erm, "start_process", {"cmd": ["sleep", "0.1"]}, on_status=on_status, timeout=10.0
            )
            pid = sleeper.response["pid"]
            print(f"ERM started process {pid}")
            # let the short process end while the ERM lives
            if not wait_ended(quick.response["pid"], quick.response["start_time"], 10.0):
                sys.exit("the short process did not end")
            erm_pid = sup.child(erm).pid
            assert erm_pid is not None
            os.kill(erm_pid, signal.SIGKILL)
            info = sup.wait_restarted(erm, timeout=15.0)
            print(f"ERM restarted ({info.last_exit}); pid {erm_pid} -> {info.pid}")
            print(f"running after restart: {sup.run_in(erm, running_processes)}")
            print(
                f"process {pid} still running: {same_process(pid, sleeper.response['start_time'])}"
            )
            print(f"pid reuse is detected: {not same_process(pid, -1)}")
            fatal.wait(5.0)
            print(f"status for the process that ended: {statuses}")
            app.unload(sleeper.id, timeout=10.0)
            app.unload(quick.id, timeout=10.0)
            if not wait_ended(pid, sleeper.response["start_time"], 10.0):
                sys.exit(f"process {pid} still runs after unload")
            print(f"process {pid} stopped by unload after the restart: True")


if __name__ == "__main__":
    main()
