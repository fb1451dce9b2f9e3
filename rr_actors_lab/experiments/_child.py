"""The run process: `python -m rr_actors_lab.experiments._child RUN_DIR PARENT_PID` runs one run.

It runs `RUN_DIR/spec.pickle` with `runner.execute` into `RUN_DIR/result.pickle`. SIGTERM,
SIGINT or the experiment's death (`PARENT_PID`) ends the run early: the tree is stopped,
no result written (exit code 3). Its managers' forkserver is killed before it exits.
"""

from __future__ import annotations

import logging
import os
import pickle
import selectors
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path

from rr_actors_lab.experiments import _procs
from rr_actors_lab.experiments.runner import RunSpec, execute

STOPPED_EXIT = 3
"""Exit code of a run that was told to stop before it finished."""


def _watch_parent(stop: threading.Event, parent: int) -> None:
    """Set `stop` when the process that started this one (pid `parent`) dies."""
    try:
        pidfd = os.pidfd_open(parent)
    except ProcessLookupError:
        stop.set()
        return
    if os.getppid() != parent:  # it died before we looked (we were re-parented): pid reused?
        os.close(pidfd)
        stop.set()
        return
    with selectors.DefaultSelector() as selector:  # (not select(): fds of 1024 and up)
        selector.register(pidfd, selectors.EVENT_READ)
        selector.select()
    os.close(pidfd)
    stop.set()


def main(argv: Sequence[str] | None = None) -> int:
    """Run the run in `argv[0]` for the experiment of pid `argv[1]`; 0 or `STOPPED_EXIT`."""
    args = list(sys.argv[1:] if argv is None else argv)
    run_dir = Path(args[0])
    parent = int(args[1]) if len(args) > 1 else os.getppid()
    spec: RunSpec = pickle.loads((run_dir / "spec.pickle").read_bytes())
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    stop = threading.Event()

    def on_signal(_signum: int, _frame: object) -> None:
        # Not stop.set() here: the main thread may hold the event's lock right now.
        threading.Thread(target=stop.set, daemon=True).start()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    watch = threading.Thread(
        target=_watch_parent, args=(stop, parent), name="rr-parent", daemon=True
    )
    watch.start()
    try:
        result = execute(spec, run_dir, stop=stop)
    finally:
        _end_forkserver()
    if stop.is_set():
        return STOPPED_EXIT
    partial = run_dir / "result.pickle.tmp"
    partial.write_bytes(pickle.dumps(result))
    partial.replace(run_dir / "result.pickle")
    return 0


def _end_forkserver() -> None:
    """SIGKILL the managers' forkserver (the tree has stopped): left alone, it would exit after
    this process and the experiment would wait for its teardown."""
    me = os.getpid()
    _procs.kill(
        [
            pid
            for pid in _procs.children(me)
            if "multiprocessing.forkserver import main" in _procs.cmdline(pid)
        ]
    )


if __name__ == "__main__":
    sys.exit(main())
