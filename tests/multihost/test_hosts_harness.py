"""The two-host harness (tests/support/hosts.py), proved with raw Zenoh before any carrier uses it.

Host `a` listens on `tcp/<a>:7447`; host `b` connects to it; multicast scouting is off, so only
the endpoints given are used. Readiness is a liveliness token seen from the other host (an
event, waited on with a bound), never a sleep.
"""

from __future__ import annotations

import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import textwrap
import time

import pytest

from tests.support import hosts

PORT = 7447
LEASE = 1.0
"""Seconds of silence after which Zenoh counts a peer as gone (its default is 10 s)."""


def bind_to(address: str) -> bool:
    """Whether this process can bind a TCP socket to `address` (it is one of its own)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        try:
            probe.bind((address, 0))
        except OSError:
            return False
        return True


def connected(two_hosts: hosts.TwoHosts, *, lease: float | None = None) -> None:
    """`a` listens and holds a token; `b` connects, watches the tokens and has seen `a`'s."""
    a, b = two_hosts.a, two_hosts.b
    a.call(hosts.zenoh_open, listen=[a.endpoint(PORT)], lease=lease, timeout=10)
    a.call(hosts.zenoh_echo, "rr/test/echo", timeout=5)
    a.call(hosts.zenoh_token, "rr/test/alive/a", timeout=5)
    b.call(hosts.zenoh_open, connect=[a.endpoint(PORT)], lease=lease, timeout=10)
    b.call(hosts.zenoh_watch, "rr/test/alive/**", timeout=5)
    kind, key, _ = b.call(hosts.zenoh_next_event, 10.0, timeout=15)
    assert ("put", "rr/test/alive/a") == (kind, key)


# -- the harness ---------------------------------------------------------------------------------


def test_each_worker_runs_in_its_own_host_namespace(two_hosts: hosts.TwoHosts) -> None:
    a, b = two_hosts.a, two_hosts.b

    assert [True, False] == [
        a.call(bind_to, a.address, timeout=10),
        a.call(bind_to, b.address, timeout=10),
    ]
    assert [False, True] == [
        b.call(bind_to, a.address, timeout=10),
        b.call(bind_to, b.address, timeout=10),
    ]
    assert not bind_to(a.address)
    assert [a.worker.pid, b.worker.pid] == [
        a.call(os.getpid, timeout=5),
        b.call(os.getpid, timeout=5),
    ]


def test_an_exception_in_a_worker_is_raised_in_the_test_with_the_workers_traceback(
    two_hosts: hosts.TwoHosts,
) -> None:
    with pytest.raises(ZeroDivisionError) as raised:
        two_hosts.a.call(divmod, 1, 0, timeout=5)

    assert isinstance(raised.value.__cause__, hosts.RemoteTraceback)
    assert "ZeroDivisionError" in str(raised.value.__cause__)


def test_a_call_in_flight_to_a_killed_worker_fails_at_once(two_hosts: hosts.TwoHosts) -> None:
    worker = two_hosts.a.worker
    in_flight = worker.submit(select.select, [], [], [], 60.0)

    worker.kill()

    with pytest.raises(hosts.WorkerDiedError, match=r"ended with -9"):
        in_flight.result(5)
    with pytest.raises(hosts.WorkerDiedError):
        worker.call(os.getpid, timeout=5)
    assert two_hosts.a.call(os.getpid, timeout=10) != worker.pid  # a fresh default worker


def test_a_call_that_outlasts_its_timeout_raises_timeout_error(two_hosts: hosts.TwoHosts) -> None:
    with pytest.raises(TimeoutError, match=r"select on <Worker \d+ on a>: no answer within 0.2 s"):
        two_hosts.a.call(select.select, [], [], [], 30.0, timeout=0.2)


def fail_with_hosts(workers: list[hosts.Worker]) -> None:
    """Start a worker on each host, then fail inside the `with` block."""
    with hosts.TwoHosts() as made:
        workers.extend([made.a.worker, made.b.worker])
        assert [made.a.namespace, made.b.namespace] == sorted(hosts.ours())
        raise LookupError("the test failed")


def test_leaving_the_hosts_stops_the_workers_and_deletes_the_namespaces_also_after_a_failure() -> (
    None
):
    reason = hosts.require_root()
    if reason is not None:
        pytest.skip(reason)
    workers: list[hosts.Worker] = []

    with pytest.raises(LookupError):
        fail_with_hosts(workers)

    assert [] == hosts.ours()
    assert [False, False] == [worker.alive for worker in workers]


def start_detached() -> int:
    """Start a process that survives its worker (a new session, no death signal); its pid."""
    process = subprocess.Popen(
        [sys.executable, "-c", "import select; select.select([], [], [], 60)"],
        start_new_session=True,
    )
    return process.pid


def test_leaving_the_hosts_kills_what_a_worker_left_running_in_its_namespace() -> None:
    reason = hosts.require_root()
    if reason is not None:
        pytest.skip(reason)

    with hosts.TwoHosts() as made:
        left = made.a.call(start_detached, timeout=10)
        made.a.worker.stop()
        assert [left] == made.a.pids()
        pidfd = os.pidfd_open(left)

    try:
        gone, _, _ = select.select([pidfd], [], [], 0)
    finally:
        os.close(pidfd)
    assert gone, f"process {left} outlived its host"


ORPHANED = textwrap.dedent(
    """
    import os, sys, select
    sys.path.insert(0, {root!r})
    from tests.support import hosts
    made = hosts.TwoHosts()
    print(made.a.worker.pid, made.directory, flush=True)
    select.select([], [], [], 60)
    """
)


def test_a_worker_dies_with_the_test_process_and_the_next_run_deletes_its_namespaces() -> None:
    reason = hosts.require_root()
    if reason is not None:
        pytest.skip(reason)
    run = subprocess.Popen(
        [sys.executable, "-c", ORPHANED.format(root=str(hosts.ROOT))],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert run.stdout is not None
        ready, _, _ = select.select([run.stdout], [], [], 30)
        assert ready, "the orphaned run did not start its worker"
        pid, directory = run.stdout.readline().split()
        worker = int(pid)
        assert 2 == len(hosts.ours(run.pid))
        pidfd = os.pidfd_open(worker)
    finally:
        run.kill()
        run.wait(10)
        if run.stdout is not None:
            run.stdout.close()
    try:
        gone, _, _ = select.select([pidfd], [], [], 5)
    finally:
        os.close(pidfd)

    shutil.rmtree(directory)  # (its logs and socket paths)
    assert gone, f"worker {worker} outlived the process that started it"
    hosts.sweep_stale()  # (a run in parallel may sweep them first: either way they go)
    assert [] == hosts.ours(run.pid)


# -- raw Zenoh across the veth -----------------------------------------------------------------


def test_a_get_on_host_b_is_answered_by_a_queryable_on_host_a_across_the_veth(
    two_hosts: hosts.TwoHosts,
) -> None:
    connected(two_hosts)

    answer = two_hosts.b.call(hosts.zenoh_get, "rr/test/echo", b"ping from b", 5.0, timeout=10)

    assert b"ping from b" == answer


def test_a_token_on_host_a_seen_from_host_b_is_gone_within_1_s_after_a_sigkill(
    two_hosts: hosts.TwoHosts,
) -> None:
    connected(two_hosts)

    killed = time.monotonic()
    os.kill(two_hosts.a.worker.pid, signal.SIGKILL)
    kind, key, seen = two_hosts.b.call(hosts.zenoh_next_event, 5.0, timeout=10)

    assert ("delete", "rr/test/alive/a") == (kind, key)
    assert seen - killed < 1.0  # (CLOCK_MONOTONIC is one clock for every namespace)


def test_a_cut_link_takes_the_token_away_at_the_lease_and_a_healed_one_brings_it_back(
    two_hosts: hosts.TwoHosts,
) -> None:
    connected(two_hosts, lease=LEASE)

    cut = time.monotonic()
    two_hosts.link_down()
    kind, key, gone = two_hosts.b.call(hosts.zenoh_next_event, 5.0, timeout=10)
    assert ("delete", "rr/test/alive/a") == (kind, key)
    assert 0.5 * LEASE <= gone - cut < 2 * LEASE  # the lease, not a FIN (the veth sends none)

    healed = time.monotonic()
    two_hosts.link_up()
    kind, key, back = two_hosts.b.call(hosts.zenoh_next_event, 10.0, timeout=15)
    assert ("put", "rr/test/alive/a") == (kind, key)
    assert back - healed < 10.0
    answer = two_hosts.b.call(hosts.zenoh_get, "rr/test/echo", b"again", 5.0, timeout=10)
    assert b"again" == answer
