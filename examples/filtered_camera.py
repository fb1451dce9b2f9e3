"""Two actions share a filtered camera, and both hear when the camera fails.

The scenario of figure 2.7 of the TeMoto thesis, with real OS processes:

- The external resource manager (registrar `erm`) starts programs: its servers `camera`
  and `filter` each start a small Python process and watch it.
- The component manager (registrar `cm`) serves `filtered_camera`; its `load` asks `erm`
  for a camera and a filter. Those two calls are *dependencies* of the filtered camera.
- Two actions (registrars `action-1` and `action-2`) each ask `cm` for the same filtered
  camera. The second request equals the first, so nothing is loaded again: both actions
  share one camera process and one filter process.
- The camera process dies (we kill it). The `erm` notices and sends `FATAL` about its
  camera; the status climbs the dependency path through `cm/filtered_camera` to both
  actions.
- Everything is unloaded (the processes are stopped) and every registrar stops.

Run it with `python examples/filtered_camera.py`.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from typing import Any

import rr_actors as rr

# A stand-in for a device driver: it runs until its standard input is closed.
PROGRAM = "import sys; sys.stdin.read()"

# The story is told from several threads (the registrars' workers, the process watchers).
# `print` writes the text and the line end separately, so another thread's line could
# land between them: each line is written whole, under a lock.
_SAY_LOCK = threading.Lock()


def say(who: str, text: str) -> None:
    """Print one line of the story (safe from any thread: lines never interleave)."""
    line = f"[{who:>8}] {text}\n"
    with _SAY_LOCK:
        sys.stdout.write(line)
        sys.stdout.flush()


class ProcessServer:
    """The `erm`'s way of running programs: one OS process per distinct request.

    `load` runs on a worker thread of the `erm`; a watcher thread per process reports an
    unexpected exit to every consumer with `Status.FATAL`.
    """

    def __init__(self, registrar: rr.ResourceRegistrar, server: str) -> None:
        self.registrar = registrar
        self.server = server
        self._lock = threading.Lock()
        self._procs: dict[int, subprocess.Popen[bytes]] = {}
        self._watchers: dict[int, threading.Thread] = {}
        self._stopping: set[int] = set()

    def load(self, request: dict[str, Any]) -> dict[str, Any]:
        """Start the program the request names; the response carries its pid."""
        proc = subprocess.Popen(  # noqa: S603 - our own interpreter, fixed program
            [sys.executable, "-c", PROGRAM], stdin=subprocess.PIPE
        )
        watcher = threading.Thread(target=self._watch, args=(proc, request), daemon=True)
        with self._lock:
            self._procs[proc.pid] = proc
            self._watchers[proc.pid] = watcher
        watcher.start()
        say(self.registrar.name, f"started {self.server} {request} as pid {proc.pid}")
        return {"pid": proc.pid, **request}

    def unload(self, request: dict[str, Any], response: dict[str, Any]) -> None:
        """Stop the process: close its input, then kill it if it does not exit in 5 s."""
        pid = response["pid"]
        with self._lock:
            self._stopping.add(pid)
            proc = self._procs.pop(pid)
            watcher = self._watchers.pop(pid)
        if proc.stdin is not None:
            proc.stdin.close()
        try:
            proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        watcher.join(timeout=5.0)
        say(self.registrar.name, f"stopped {self.server} pid {pid} (exit code {proc.returncode})")

    def _watch(self, proc: subprocess.Popen[bytes], request: dict[str, Any]) -> None:
        code = proc.wait()
        with self._lock:
            expected = proc.pid in self._stopping
        if expected:
            return
        say(self.registrar.name, f"{self.server} pid {proc.pid} died (exit code {code})")
        # Any consumer id of the resource reaches all of its consumers (rule 9).
        for query in self.registrar.server_queries(self.server):
            if query.request == request:
                self.registrar.send_status(
                    query.id, rr.Status.FATAL, f"{self.server} pid {proc.pid} died"
                )
                return

    def pid_of(self, request: dict[str, Any]) -> int:
        """The pid of the process running for `request`."""
        for query in self.registrar.server_queries(self.server):
            if query.request == request:
                pid: int = query.response["pid"]
                return pid
        raise LookupError(request)


def main() -> None:
    """Run the story; every registrar and process started here is stopped again."""
    erm = rr.ResourceRegistrar.start("erm")
    cm = rr.ResourceRegistrar.start("cm")
    actions = [rr.ResourceRegistrar.start(f"action-{n}") for n in (1, 2)]
    try:
        cameras = ProcessServer(erm, "camera")
        filters = ProcessServer(erm, "filter")
        erm.register_server("camera", load=cameras.load, unload=cameras.unload)
        erm.register_server("filter", load=filters.load, unload=filters.unload)

        loads: list[dict[str, Any]] = []

        def load_filtered_camera(request: dict[str, Any]) -> dict[str, Any]:
            # Calls made inside a load are dependencies of the resource being loaded.
            loads.append(request)
            say("cm", f"building a filtered camera for {request}")
            camera = cm.call("erm", "camera", {"device": request["device"]})
            pipe = cm.call("erm", "filter", {"kind": request["filter"], "input": request["device"]})
            return {"camera_pid": camera.response["pid"], "filter_pid": pipe.response["pid"]}

        def unload_filtered_camera(request: dict[str, Any], response: dict[str, Any]) -> None:
            say("cm", f"filtered camera {request} released (its camera and filter already are)")

        def cm_on_status(query: rr.Query, update: rr.StatusUpdate) -> None:
            say("cm", f"filtered_camera hears {update.status.name} from {update.source}")

        cm.register_server(
            "filtered_camera",
            load=load_filtered_camera,
            unload=unload_filtered_camera,
            on_status=cm_on_status,
        )

        request = {"device": "/dev/video0", "filter": "gaussian"}
        heard = {action.name: threading.Event() for action in actions}
        queries: list[rr.Query] = []
        for action in actions:

            def on_status(query: rr.Query, update: rr.StatusUpdate, who: str = action.name) -> None:
                say(who, f"heard {update.status.name}: {update.message!r} (query {query.id[:8]})")
                heard[who].set()

            query = action.call("cm", "filtered_camera", request, on_status=on_status)
            say(action.name, f"got filtered camera {query.response} (query {query.id[:8]})")
            queries.append(query)

        shared = queries[0].response == queries[1].response
        consumers = len(cm.server_queries("filtered_camera"))
        say("main", f"filtered_camera loaded {len(loads)} time(s) for {consumers} consumers")
        say("main", f"both actions share one camera and one filter process: {shared}")

        camera_pid = cameras.pid_of({"device": request["device"]})
        say("main", f"the camera fails: SIGKILL to pid {camera_pid}")
        os.kill(camera_pid, signal.SIGKILL)
        for name, event in heard.items():
            if not event.wait(10.0):
                raise SystemExit(f"{name} never heard about the failed camera")
        say("main", "both actions heard the camera fail")

        for action, query in zip(actions, queries, strict=True):
            say(action.name, f"unloads query {query.id[:8]}")
            action.unload(query.id)
        say("main", f"erm still serves {len(erm.server_queries('camera'))} camera(s)")
    finally:
        for registrar in [*actions, cm, erm]:
            registrar.stop()
            say("main", f"stopped registrar {registrar.name}")
    say("main", "done")


if __name__ == "__main__":
    main()
