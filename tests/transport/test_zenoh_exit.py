"""A program with a `ZenohNetwork` ends: after an error, when it forgets `close()`, and at
the first Ctrl-C (one line, killed by SIGINT as Python ends after a Ctrl-C: a shell says
130), in a real terminal.

Zenoh's callback threads are not daemons: a session left open kept the interpreter
waiting for them forever, and a Ctrl-C reached the manager processes too (each printed a
traceback). Each test runs the how-to's programs (docs/how-to/two-machines.md), on
loopback, in their own interpreter.
"""

from __future__ import annotations

import os
import select
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from tests.support.supervising import wait_gone
from tests.support.tls_lab import free_port

ROBOT = textwrap.dedent(
    """
    import threading

    import rr_actors as rr


    def erm_setup(registrar):
        registrar.register_server("camera", load=lambda r: r, unload=lambda r, s: None)


    # Only the router's Unix socket (its manager joins there): no TCP endpoint, so no
    # plain-TCP WARNING comes before "serving".
    net = rr.ZenohNetwork(system="exit", listen=[], connect=[], tls=None)
    sup = rr.Supervisor(
        [rr.ManagerSpec("erm", setup=erm_setup, isolation="process")], network=net
    )
    with sup:
        print("serving", sup.child("erm").pid, flush=True)
        threading.Event().wait()  # serve until the program is stopped
    """
)

STATION = textwrap.dedent(
    """
    import sys

    import rr_actors as rr

    net = rr.ZenohNetwork(
        system="exit", listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{sys.argv[1]}"],
        tls=None,
    )
    app = rr.ResourceRegistrar.start(rr.RegistrarConfig(name="station"), network=net)
    if sys.argv[2] == "raises":
        app.call("erm", "camera", {"device": 0})  # nobody serves it: UnknownRegistrarError
    print("done", flush=True)  # neither app.stop() nor net.close()
    """
)

SETSID = shutil.which("setsid") or "/usr/bin/setsid"  # util-linux

BOUND = 30.0
"""Seconds such a program may take to end (it takes well under one)."""


@pytest.mark.parametrize(("ending", "code"), [("raises", 1), ("returns", 0)])
def test_a_program_that_leaves_its_network_open_ends(ending: str, code: int) -> None:
    started, port = time.monotonic(), free_port()
    try:
        done = subprocess.run(  # noqa: PLW1510 - the exit code is what is checked
            [sys.executable, "-c", STATION, str(port), ending],
            capture_output=True,
            text=True,
            timeout=BOUND,
        )
    except subprocess.TimeoutExpired as exc:
        pytest.fail(f"the program did not end within {BOUND:g} s: {exc.stderr!r}")

    assert (code, True) == (done.returncode, time.monotonic() - started < BOUND), done.stderr
    if ending == "raises":
        assert done.stderr.rstrip().endswith(
            "no registrar named 'erm' on system 'exit' (known: 'station'); this process has "
            f"no link to connect endpoint tcp/127.0.0.1:{port} (cannot reach it (Connection "
            "refused)), so a registrar served there is not seen"
        ), done.stderr
        assert "Traceback (most recent call last)" in done.stderr


def _read_until(master: int, text: bytes, deadline: float) -> bytes:
    """What the terminal shows until `text` appears, the program's side closes, or the
    deadline."""
    seen = b""
    while text not in seen and time.monotonic() < deadline:
        readable, _, _ = select.select([master], [], [], max(0.0, deadline - time.monotonic()))
        if not readable:
            break
        try:
            chunk = os.read(master, 65536)
        except OSError:  # the program ended: its side of the terminal closed
            break
        if not chunk:
            break
        seen += chunk
    return seen


@pytest.mark.timeout(120)
def test_the_first_ctrl_c_in_a_terminal_ends_a_supervisor_with_a_network_in_one_line(
    tmp_path: Path,
) -> None:
    script = tmp_path / "robot.py"
    script.write_text(ROBOT)
    master, slave = os.openpty()
    # `setsid -c`: the program leads a session whose controlling terminal is the pty, so
    # ^C there sends SIGINT to its foreground group (the program and its manager), as a
    # terminal does.
    program = subprocess.Popen(
        [SETSID, "-c", sys.executable, str(script)],
        stdin=slave,
        stdout=slave,
        stderr=slave,
    )
    os.close(slave)
    try:
        shown = _read_until(master, b"\n", time.monotonic() + 60)
        assert shown.startswith(b"serving "), shown
        manager = int(shown.split()[1])
        os.write(master, b"\x03")  # Ctrl-C
        interrupted = time.monotonic()
        shown += _read_until(master, b"\0", interrupted + BOUND)  # until the program ends
        code = program.wait(BOUND)
    finally:
        if program.poll() is None:
            program.kill()
            program.wait(10)
        os.close(master)

    after = shown.decode(errors="replace").replace("^C", "").splitlines()[1:]
    assert (-signal.SIGINT, ["KeyboardInterrupt"]) == (code, [s for s in after if s.strip()])
    assert time.monotonic() - interrupted < BOUND
    assert [] == wait_gone([manager])  # its supervisor stopped it
