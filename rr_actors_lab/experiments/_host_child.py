"""The process of one host of a plan with `[hosts]` (`_hosts.HostProcess` starts it in the
host's network namespace): its part of the tree on its own Zenoh router, its events sent
back as JSON lines, commands read from stdin (`_hosts` says the protocol)."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import pickle
import selectors
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import IO, Any

from rr_actors import events
from rr_actors_lab.experiments._hosts import HostSpec, network
from rr_actors_lab.experiments.runner import (
    build_tree,
    count_entries,
    preload_setups,
    wait_all_serving,
)


def _watch_parent(parent: int) -> None:
    """Exit when the run process dies (its managers die with this process)."""
    try:
        pidfd = os.pidfd_open(parent)
    except ProcessLookupError:
        os._exit(3)
    with selectors.DefaultSelector() as selector:  # (not select(): fds of 1024 and up)
        selector.register(pidfd, selectors.EVENT_READ)
        selector.select()
    os._exit(3)


def _serve(spec: HostSpec, out: IO[str]) -> None:
    lock = threading.Lock()

    def send(message: dict[str, Any]) -> None:
        line = json.dumps(message) + "\n"
        with lock:
            out.write(line)
            out.flush()

    preload_setups(spec.plan)
    net = network(spec)
    state = Path(spec.state_dir) if spec.state_dir is not None else None
    sup = build_tree(spec.plan, state, seed=spec.seed, host=spec.host, network=net)
    subscription = sup.subscribe(lambda e: send({"e": events.to_dict(e)}), maxsize=200_000)
    sup.start()
    managers = [m.name for m in spec.plan.managers() if spec.plan.host_of(m.name) == spec.host]
    send({"r": "ready"})
    for line in sys.stdin:
        command = json.loads(line)
        op = command["op"]
        if op == "wait_serving":
            wait_all_serving(sup, managers, float(command["timeout"]))
            send({"r": "serving"})
        elif op == "count":
            entries, unread = count_entries(sup, managers, [])
            send({"r": [entries, unread]})
        elif op == "flush":
            sup.flush_events()
            send({"r": "flushed"})
    sup.stop()
    subscription.wait_delivered()
    subscription.close()
    with contextlib.suppress(Exception):
        net.close()


def main(argv: Sequence[str] | None = None) -> int:
    """The host process: `python -m rr_actors_lab.experiments._host_child SPEC PARENT_PID`."""
    args = list(sys.argv[1:] if argv is None else argv)
    spec: HostSpec = pickle.loads(Path(args[0]).read_bytes())
    logging.basicConfig(level=logging.WARNING, format=f"{spec.host}: %(name)s: %(message)s")
    threading.Thread(target=_watch_parent, args=(int(args[1]),), daemon=True).start()
    out = sys.stdout
    sys.stdout = sys.stderr  # nothing else may write to the line channel
    _serve(spec, out)
    out.flush()
    sys.stderr.flush()
    os._exit(0)  # no interpreter teardown: Zenoh's native threads may not let it finish


if __name__ == "__main__":
    sys.exit(main())
