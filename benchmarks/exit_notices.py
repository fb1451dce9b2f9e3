"""What a program's end costs when its main thread ends holding ids (issue 69, goal 3): counts.

For each N, a Python of its own starts a supervisor of N process managers with a
`state_dir`, each serving `res` (its unload takes `--unload` seconds), and an app registrar
of the supervisor's that holds one id at each; then its main thread returns without a
stop. `rr_actors._core.exit.stop_everything` stops what was left running within
`--exit-timeout` seconds (`EXIT_TIMEOUT`, 10 s): the app's releases (rule 12, one at a
time) spend it, so each manager of the tree is stopped past its bound, that is killed.
Counted during that stop, in the supervisor's process: the death-watch notices sent to
another process (`ConsumerDown`, `life._mark`) and the connections it opened; and the
stop's wall time in seconds. A count, not a speed: no floor.

Run: `python benchmarks/exit_notices.py [--counts 50 100 200] [--unload 0.5]
[--exit-timeout 10]`. More than 100 managers: `flock /work/big.lock` on the shared machine.
"""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve()


def one(count: int, unload: float, exit_timeout: float) -> None:
    """The measured program (`--one`): its main thread returns holding N ids."""
    import rr_actors as rr  # noqa: PLC0415
    from rr_actors._core import exit as at_exit  # noqa: PLC0415
    from rr_actors._registrar import life  # noqa: PLC0415
    from rr_actors.testing import start_forkserver  # noqa: PLC0415

    counts = {"notices": 0, "connections": 0}
    mark, connect, stop_everything = life._mark, socket.socket.connect, at_exit.stop_everything

    def counted_mark(name: str, *, stopped: bool = False) -> Any:
        counts["notices"] += 1
        return mark(name, stopped=stopped)

    def counted_connect(self: socket.socket, address: Any) -> None:
        counts["connections"] += 1
        connect(self, address)

    def measured(_timeout: float = exit_timeout) -> None:
        socket.socket.connect = counted_connect  # type: ignore[method-assign]
        began = time.perf_counter()
        try:
            stop_everything(exit_timeout)
        finally:
            socket.socket.connect = connect  # type: ignore[method-assign]
            stop_s = round(time.perf_counter() - began, 2)
            print(json.dumps({"n": count, "stop_s": stop_s, **counts}), flush=True)

    def setup(registrar: rr.ResourceRegistrar) -> None:
        registrar.register_server("res", load=lambda r: r, unload=lambda r, s: time.sleep(unload))

    life._mark = counted_mark
    at_exit.stop_everything = measured  # (the hook looks it up when the main thread ends)
    start_forkserver()
    names = [f"m{n}" for n in range(count)]
    specs = [rr.ManagerSpec(n, setup, isolation="process", start_timeout=120) for n in names]
    sup = rr.Supervisor(specs, name=f"exit-{count}", state_dir=tempfile.mkdtemp())
    sup.start()
    app = sup.registrar("app")
    for name in names:
        app.call(name, "res", "x", timeout=60)


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[50, 100, 200])
    parser.add_argument("--unload", type=float, default=0.5, help="seconds each unload takes")
    parser.add_argument("--exit-timeout", type=float, default=10.0, help="EXIT_TIMEOUT, s")
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one is not None:
        one(args.one, args.unload, args.exit_timeout)
        return
    print(f"{'N':>5} {'stop s':>8} {'notices':>9} {'connections':>12}")
    for count in args.counts:
        command = [sys.executable, str(HERE), "--one", str(count)]
        command += ["--unload", str(args.unload), "--exit-timeout", str(args.exit_timeout)]
        done = subprocess.run(command, capture_output=True, text=True, check=False)
        lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
        if not lines:
            print(f"{count:>5} failed: {done.stderr.strip()[-200:]}")
            continue
        row = json.loads(lines[-1])
        print(f"{count:>5} {row['stop_s']:>8.2f} {row['notices']:>9,} {row['connections']:>12,}")


if __name__ == "__main__":
    main()
