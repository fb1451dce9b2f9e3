"""`ZenohNetwork.wait_for`: "either machine may start first" (docs/how-to/two-machines.md).

The waiting side's first call no longer fails at once when the other side starts later:
`wait_for` returns as soon as the registrar's presence is seen, and at its timeout says
why it was not (a connect endpoint with no link, and the link watch's reason). An
`UnknownRegistrarError` says the same. The provider runs in a process of its own (a
process belongs to one system), started after the wait began.
"""

from __future__ import annotations

import re
import subprocess
import sys
import textwrap
import threading
import time
import uuid
from pathlib import Path

import pytest

import rr_actors as rr
from tests.support import pki
from tests.support.tls_lab import free_port, member_tls, router
from tests.support.waiting import wait_for

PROVIDER = textwrap.dedent(
    """
    import sys

    import rr_actors as rr

    system, port, name = sys.argv[1:4]
    net = rr.ZenohNetwork(system=system, connect=[f"tcp/127.0.0.1:{port}"], tls=None)
    erm = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name), network=net)
    erm.register_server("camera", load=lambda r: {"device": r}, unload=lambda r, s: None)
    print("serving", flush=True)
    sys.stdin.read()  # until the test closes our standard input
    """
)


@pytest.mark.timeout(90)
def test_wait_for_returns_once_a_provider_that_starts_later_serves_and_the_call_then_works() -> (
    None
):
    system, port, name = f"wait-{uuid.uuid4().hex[:8]}", free_port(), f"erm-{uuid.uuid4().hex[:8]}"
    net = rr.ZenohNetwork(system=system, listen=[f"tcp/127.0.0.1:{port}"], tls=None)
    app = rr.ResourceRegistrar.start(rr.RegistrarConfig(name="app"), network=net)
    returned = threading.Event()
    failed: list[BaseException] = []

    def wait() -> None:
        try:
            net.wait_for(name, timeout=60)
        except BaseException as exc:
            failed.append(exc)
        returned.set()

    waiter = threading.Thread(target=wait, daemon=True)
    waiter.start()
    with subprocess.Popen(
        [sys.executable, "-c", PROVIDER, system, str(port), name],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    ) as provider:
        assert provider.stdout is not None
        assert provider.stdin is not None
        try:
            assert not returned.is_set()  # (the provider's interpreter is not even up yet)
            assert "serving\n" == provider.stdout.readline()
            served = time.monotonic()
            assert returned.wait(30), "wait_for did not return after the provider served"
            assert ([], True) == (failed, time.monotonic() - served < 30)
            query = app.call(name, "camera", 0, timeout=10)
            assert {"device": 0} == query.response
            app.unload(query.id)
        finally:
            app.stop()
            net.close()
            provider.stdin.close()  # the provider ends (its network closes at exit)
            try:
                assert 0 == provider.wait(30)
            finally:
                if provider.poll() is None:
                    provider.kill()
            waiter.join(10)


def test_wait_for_a_registrar_served_in_this_process_returns_at_once() -> None:
    name = f"erm-{uuid.uuid4().hex[:8]}"
    with rr.ZenohNetwork(system=f"wait-{uuid.uuid4().hex[:8]}", tls=None) as net:
        erm = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name), network=net)
        try:
            net.wait_for(name, timeout=0)
        finally:
            erm.stop()


def test_wait_for_with_no_connect_endpoint_times_out_unavailable() -> None:
    with rr.ZenohNetwork(system=f"wait-{uuid.uuid4().hex[:8]}", tls=None) as net:
        began = time.monotonic()
        with pytest.raises(
            rr.RegistrarUnavailableError,
            match=r"^no registrar named 'erm' was served on system 'wait-\w+' within 0\.5 s$",
        ):
            net.wait_for("erm", timeout=0.5)
        assert time.monotonic() - began >= 0.5


@pytest.mark.parametrize("timeout", [-1, float("nan"), "5", True])
def test_wait_for_with_a_bad_timeout_is_a_config_error(timeout: object) -> None:
    net = rr.ZenohNetwork(system="wait", tls=None)
    with pytest.raises(rr.ConfigError, match="timeout must be seconds >= 0"):
        net.wait_for("erm", timeout=timeout)  # type: ignore[arg-type]
    assert not net.closed  # never opened


def test_wait_for_after_close_says_the_process_left_the_system() -> None:
    net = rr.ZenohNetwork(system=f"wait-{uuid.uuid4().hex[:8]}", tls=None)
    net.address  # noqa: B018 - opens the session
    net.close()
    with pytest.raises(rr.RegistrarStoppedError, match="left system"):
        net.wait_for("erm", timeout=1)


# -- a host this process cannot link to ------------------------------------------------------


@pytest.fixture
def refused(tmp_path: Path):  # type: ignore[no-untyped-def]
    """A TLS listener of another CA on loopback, and this host's `ZenohTLS` (of the lab's)."""
    port = free_port()
    other = member_tls(tmp_path / "other", pki.make_ca(tmp_path / "other-ca", "other"), "robot")
    mine = member_tls(tmp_path / "mine", pki.make_ca(tmp_path / "lab", "lab"), "operator")
    with router(other, [f"tls/127.0.0.1:{port}"], []):
        yield port, mine


REASON = r"the listener's certificate is not signed by this system's CA .*lab"


def test_wait_for_a_registrar_behind_a_refusing_host_names_the_endpoint_and_why(
    refused: tuple[int, object],
) -> None:
    port, tls = refused
    endpoint = f"tls/127.0.0.1:{port}"
    with rr.ZenohNetwork(system="lab", connect=[endpoint], tls=tls) as net:  # type: ignore[arg-type]
        began = time.monotonic()
        with pytest.raises(rr.RegistrarUnavailableError) as raised:
            net.wait_for("erm", timeout=1.0)
        assert time.monotonic() - began >= 1.0
    message = str(raised.value)
    assert message.startswith("no registrar named 'erm' was served on system 'lab' within 1 s; ")
    assert f"no link to connect endpoint {endpoint} (" in message
    assert re.search(REASON, message), message


def test_a_call_to_a_registrar_behind_a_refusing_host_names_the_endpoint_and_why(
    refused: tuple[int, object],
) -> None:
    port, tls = refused
    endpoint, uid = f"tls/127.0.0.1:{port}", uuid.uuid4().hex[:8]
    with rr.ZenohNetwork(system="lab", connect=[endpoint], tls=tls) as net:  # type: ignore[arg-type]
        station = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=f"station{uid}"), network=net)
        try:
            with pytest.raises(rr.UnknownRegistrarError) as raised:
                station.call(f"erm-{uid}", "camera", 0, timeout=10)
        finally:
            station.stop()
    message = str(raised.value)
    assert message.startswith(f"no registrar named 'erm-{uid}' on system 'lab'")
    assert f"this process has no link to connect endpoint {endpoint} (" in message
    assert re.search(REASON, message), message


# -- plain TCP: a connect endpoint nobody listens on (issue 44 item 7) ----------------------


def test_wait_for_over_plain_tcp_names_the_connect_endpoint_nobody_listens_on() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # (closed: nothing listens there)
    with (
        rr.ZenohNetwork(system="lab", connect=[endpoint], tls=None) as net,
        pytest.raises(rr.RegistrarUnavailableError) as raised,
    ):
        net.wait_for("erm", timeout=0.5)

    assert (
        "no registrar named 'erm' was served on system 'lab' within 0.5 s; this process has "
        f"no link to connect endpoint {endpoint} (cannot reach it (Connection refused)), so "
        "a registrar served there is not seen"
    ) == str(raised.value)


def test_a_call_over_plain_tcp_names_the_connect_endpoint_nobody_listens_on() -> None:
    endpoint, uid = f"tcp/127.0.0.1:{free_port()}", uuid.uuid4().hex[:8]
    with rr.ZenohNetwork(system="lab", connect=[endpoint], tls=None) as net:
        station = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=f"station{uid}"), network=net)
        try:
            with pytest.raises(rr.UnknownRegistrarError) as raised:
                station.call(f"erm-{uid}", "camera", 0, timeout=10)
        finally:
            station.stop()

    message = str(raised.value)
    assert message.startswith(f"no registrar named 'erm-{uid}' on system 'lab'"), message
    assert (
        f"; this process has no link to connect endpoint {endpoint} (cannot reach it "
        "(Connection refused))"
    ) in message


def test_a_plain_tcp_connect_endpoint_that_is_linked_is_not_named() -> None:
    port, uid = free_port(), uuid.uuid4().hex[:8]
    with (
        router(None, [f"tcp/127.0.0.1:{port}"], [], system="lab") as other,
        rr.ZenohNetwork(system="lab", connect=[f"tcp/127.0.0.1:{port}"], tls=None) as net,
    ):
        station = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=f"station{uid}"), network=net)
        try:
            assert wait_for(lambda: bool(list(other.info.links())), 10)  # (linked)
            with pytest.raises(rr.UnknownRegistrarError) as raised:
                station.call(f"erm-{uid}", "camera", 0, timeout=10)
        finally:
            station.stop()

    assert "no link" not in str(raised.value)
