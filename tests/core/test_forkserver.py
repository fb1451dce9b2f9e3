"""A process forked from one that runs rr_actors works, or is refused; it never times out.

- A manager process whose load callback forks: each child starts a registrar of its own
  and calls a provider of the system (issue 29: every such call timed out).
- A plain program that started a registrar and then uses `multiprocessing`'s "fork"
  method: the child starts a registrar and calls; its parent's registrar handle fails at
  once in the child (`RegistrarUnavailableError`), not after the call timeout; it can
  start a supervisor with a manager process of its own (its parent's forkserver is not
  its own).
- A child of a process that opened a Zenoh session is refused with a `ConfigError` that
  names `spawn` and `forkserver`.

The programs run in their own interpreters (`python -c`), so that what the test session
did before (a Zenoh session opened by another test) is not theirs; each bounds its
waits and reaps its children.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import uuid

import cloudpickle
import pytest

import rr_actors as rr
from tests.support import selecting

pytestmark = [
    pytest.mark.skipif(not hasattr(os, "fork"), reason="POSIX fork"),
    pytest.mark.usefixtures("by_value"),  # (tests/conftest.py)
]

CHILD_CALL_TIMEOUT = 10.0
"""Seconds a child's call may take: the old code's calls all ran into it."""


def forked_calls(provider: str, uid: str, children: int) -> list[object]:
    """Fork `children` processes; each starts a registrar and calls `provider`'s "leaf".

    Runs in a manager process (a load callback). Each child writes what its call gave
    (or the error's repr) to a pipe and exits; this waits for each at most
    `CHILD_CALL_TIMEOUT` + 5 seconds, kills one that did not answer, and reaps all.
    """
    results: list[object] = []
    for n in range(children):
        read, write = os.pipe()
        pid = os.fork()
        if pid == 0:  # pragma: no cover - the forked child
            os.close(read)
            try:
                kid = rr.ResourceRegistrar.start(f"kid-{uid}-{n}")
                got: object = kid.call(
                    provider, "leaf", f"kid-{n}", timeout=CHILD_CALL_TIMEOUT
                ).response
                kid.stop()
            except BaseException as exc:  # (reported to the parent)
                got = repr(exc)
            os.write(write, cloudpickle.dumps(got))
            os._exit(0)
        os.close(write)
        try:
            ready, _, _ = selecting.select([read], [], [], CHILD_CALL_TIMEOUT + 5)
            if ready:
                with os.fdopen(read, "rb", closefd=False) as pipe:
                    results.append(cloudpickle.loads(pipe.read()))
            else:
                results.append("no answer")
                os.kill(pid, signal.SIGKILL)
        finally:
            os.close(read)
            os.waitpid(pid, 0)  # (it wrote and exits, or was killed)
    return results


def test_children_forked_in_a_manager_process_start_registrars_and_call_a_provider() -> None:
    uid = uuid.uuid4().hex[:8]
    provider, forker = f"provider-{uid}", f"forker-{uid}"

    def provider_setup(registrar: rr.ResourceRegistrar) -> None:
        registrar.register_server("leaf", load=lambda r: {"for": r}, unload=lambda r, s: None)

    def forker_setup(registrar: rr.ResourceRegistrar) -> None:
        def load(children: int) -> list[object]:
            registrar.call(provider, "leaf", "forker", timeout=10)  # a connection to inherit
            return forked_calls(provider, uid, children)

        registrar.register_server(
            "fork",
            load=load,
            unload=lambda r, s: None,
            timeout=3 * (CHILD_CALL_TIMEOUT + 5),
        )

    sup = rr.Supervisor(
        [
            rr.ManagerSpec(provider, provider_setup, isolation="process"),
            rr.ManagerSpec(forker, forker_setup, isolation="process"),
        ]
    )
    with sup:
        app = sup.registrar(f"app-{uid}")
        got = app.call(forker, "fork", 2, timeout=3 * (CHILD_CALL_TIMEOUT + 5)).response

    assert [{"for": "kid-0"}, {"for": "kid-1"}] == got


PLAIN_PROGRAM = textwrap.dedent(
    """
    import multiprocessing, os, sys
    import rr_actors as rr

    uid, timeout = sys.argv[1], float(sys.argv[2])
    provider = f"provider-{uid}"

    def setup(registrar):
        registrar.register_server("leaf", load=lambda r: {"for": r}, unload=lambda r, s: None)

    def child(app, out):
        kid = rr.ResourceRegistrar.start(f"kid-{uid}")
        out.send(("call", kid.call(provider, "leaf", "kid", timeout=timeout).response))
        try:
            app.call(provider, "leaf", "parent's", timeout=timeout)
        except rr.RrError as exc:
            out.send(("parent's handle", type(exc).__name__, str(exc)))
        sup = rr.Supervisor([rr.ManagerSpec(f"grand-{uid}", setup, isolation="process")])
        with sup:
            mine = sup.registrar(f"mine-{uid}")
            got = mine.call(f"grand-{uid}", "leaf", "g", timeout=timeout).response
            out.send(("own supervisor", got))
        kid.stop()

    def main():
        sup = rr.Supervisor([rr.ManagerSpec(provider, setup, isolation="process")])
        with sup:
            app = sup.registrar(f"app-{uid}")
            got = app.call(provider, "leaf", "parent", timeout=timeout).response
            print("parent", got, flush=True)
            read, write = multiprocessing.Pipe(duplex=False)
            process = multiprocessing.get_context("fork").Process(target=child, args=(app, write))
            process.start()
            write.close()
            while read.poll(timeout + 10):
                try:
                    print(*read.recv(), sep=" | ", flush=True)
                except EOFError:
                    break
            process.kill()  # (a no-op once it ended)
            process.join(10)
            print("exit", process.exitcode, flush=True)

    if __name__ == "__main__":
        main()
    """
)


def run(program: str, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", program, *args],
        capture_output=True,
        text=True,
        timeout=50,
        check=False,
    )


def test_a_child_forked_by_multiprocessing_from_a_plain_program_starts_a_registrar_and_calls() -> (
    None
):
    uid = uuid.uuid4().hex[:8]
    result = run(PLAIN_PROGRAM, uid, str(CHILD_CALL_TIMEOUT))
    lines = result.stdout.splitlines()

    assert 0 == result.returncode, result.stderr
    assert [
        "parent {'for': 'parent'}",
        "call | {'for': 'kid'}",
        "own supervisor | {'for': 'g'}",
        "exit 0",
    ] == [line for line in lines if not line.startswith("parent's handle")], result.stderr
    handle = [line for line in lines if line.startswith("parent's handle")]
    assert 1 == len(handle), result.stdout
    assert handle[0].startswith("parent's handle | RegistrarUnavailableError | "), handle
    assert f"registrar 'app-{uid}' runs in process" in handle[0]
    assert "which this process was forked from" in handle[0]


ZENOH_PROGRAM = textwrap.dedent(
    """
    import multiprocessing, sys
    import rr_actors as rr

    uid = sys.argv[1]

    def child(net, out):
        for start in (
            lambda: rr.ResourceRegistrar.start(f"kid-{uid}"),
            lambda: rr.ResourceRegistrar.start(f"kid-{uid}", network=net),
            lambda: rr.Supervisor([rr.ManagerSpec(f"m-{uid}", None)]).start(),
        ):
            try:
                start()
                out.send(("started",))
            except rr.RrError as exc:
                out.send((type(exc).__name__, str(exc)))

    def main():
        net = rr.ZenohNetwork(system=f"fork-{uid}", tls=None)
        reg = rr.ResourceRegistrar.start(f"router-{uid}", network=net)
        read, write = multiprocessing.Pipe(duplex=False)
        process = multiprocessing.get_context("fork").Process(target=child, args=(net, write))
        process.start()
        write.close()
        while read.poll(20):
            try:
                print(*read.recv(), sep=" | ", flush=True)
            except EOFError:
                break
        process.kill()  # (a no-op once it ended)
        process.join(10)
        print("exit", process.exitcode, flush=True)
        reg.stop()
        net.close()

    if __name__ == "__main__":
        main()
    """
)


def test_a_child_forked_after_a_zenoh_session_opened_is_refused_with_a_config_error() -> None:
    pytest.importorskip("zenoh")
    result = run(ZENOH_PROGRAM, uuid.uuid4().hex[:8])
    lines = result.stdout.splitlines()

    assert 0 == result.returncode, result.stderr
    assert 4 == len(lines), result.stdout + result.stderr
    for line in lines[:3]:
        kind, message = line.split(" | ", 1)
        assert "ConfigError" == kind, line
        assert "forked from process" in message
        assert "Zenoh session" in message
        assert "'spawn'" in message
        assert "'forkserver'" in message
    assert "exit 0" == lines[3]
