"""`ZenohNetwork` (`rr_actors._transport.zenoh.net`): its arguments, its warnings, one
system per process; opening, waiting for a registrar, and ending with the program.
"""

from __future__ import annotations

import logging
import multiprocessing
import multiprocessing.connection
import multiprocessing.context
import os
import pickle
import pwd
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

import rr_actors as rr
from rr_actors._core.hlc import CLOCK, MAX_OFFSET
from rr_actors._transport.zenoh.net import ZenohNetwork
from rr_actors._transport.zenoh.ops.config import session_config
from tests.support import pki, selecting
from tests.support.hosts import free_port
from tests.support.supervising import wait_gone
from tests.support.tls_lab import member_tls, router
from tests.support.waiting import wait_for
from tests.test_init import HIDE_THE_LAB


def _attached_max_offset(address: Any) -> float:
    member = address.attach()
    try:
        return CLOCK.max_offset
    finally:
        member.close()


# -- helpers -------------------------------------------------------------------------------------


def _me() -> str:
    return f"{pwd.getpwuid(os.geteuid()).pw_name} (uid {os.geteuid()})"


def _system() -> str:
    return f"test-{uuid.uuid4().hex[:8]}"


@pytest.fixture
def net() -> Iterator[ZenohNetwork]:
    """A fresh system whose router is the test process, listening on loopback TCP."""
    network = rr.ZenohNetwork(system=_system(), listen=[f"tcp/127.0.0.1:{free_port()}"], tls=None)
    yield network
    network.close()


pytest.importorskip("zenoh")


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


REASON = r"the listener's certificate is not signed by this system's CA .*lab"


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


def _read_until(master: int, text: bytes, deadline: float) -> bytes:
    """What the terminal shows until `text` appears, the program's side closes, or the
    deadline."""
    seen = b""
    while text not in seen and time.monotonic() < deadline:
        readable, _, _ = selecting.select([master], [], [], max(0.0, deadline - time.monotonic()))
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


# -- configuration ---------------------------------------------------------------------------


@pytest.mark.parametrize("system", ["", "a/b", "*", ".hidden", "-x", "lab lab", "rr/**", 7, None])
def test_a_bad_system_name_is_a_config_error_naming_system(system: Any) -> None:
    with pytest.raises(rr.ConfigError, match="system"):
        rr.ZenohNetwork(system=system, tls=None)


@pytest.mark.parametrize(
    "endpoint",
    [
        "10.0.0.1:7447",
        "udp/10.0.0.1:7447",
        "tcp/10.0.0.1",
        "tcp/10.0.0.1:port",
        "tcp/10.0.0.1:70000",
        "tcp/:7447",
        "tcp/[nonsense]:7447",
        "tcp/10.0.0.1:7447/extra",
        7447,
    ],
)
@pytest.mark.parametrize("role", ["listen", "connect"])
def test_a_malformed_endpoint_is_a_config_error_naming_it(role: str, endpoint: Any) -> None:
    with pytest.raises(rr.ConfigError, match=role) as caught:
        rr.ZenohNetwork(system="lab", tls=None, **{role: [endpoint]})

    assert repr(endpoint) in str(caught.value)


def test_a_system_name_of_64_characters_is_accepted_and_of_65_a_config_error_naming_it() -> None:
    assert "s" * 64 == rr.ZenohNetwork(system="s" * 64, tls=None).system

    with pytest.raises(rr.ConfigError) as caught:
        rr.ZenohNetwork(system="s" * 65, tls=None)

    assert str(caught.value).startswith(
        f"system {'s' * 65!r} is 65 characters long: a system name has at most 64 (NAME_MAX"
    )


def test_endpoints_given_as_one_string_are_a_config_error() -> None:
    with pytest.raises(rr.ConfigError, match="listen must be a list"):
        rr.ZenohNetwork(system="lab", listen="tcp/127.0.0.1:7447", tls=None)  # type: ignore[arg-type]


def test_tls_has_no_default() -> None:
    with pytest.raises(TypeError, match="tls"):
        rr.ZenohNetwork(system="lab")  # type: ignore[call-arg]


@pytest.mark.parametrize("tls", [True, "mtls", {"ca": "ca.pem"}])
def test_tls_other_than_none_or_a_zenoh_tls_is_a_config_error(tls: Any) -> None:
    with pytest.raises(rr.ConfigError, match=r"tls must be rr\.ZenohTLS"):
        rr.ZenohNetwork(system="lab", tls=tls)


@pytest.mark.parametrize("lease", [0, -1.0, float("nan"), float("inf"), True, "1", 1e6])
def test_a_bad_lease_is_a_config_error_naming_lease(lease: Any) -> None:
    with pytest.raises(rr.ConfigError, match="lease"):
        rr.ZenohNetwork(system="lab", tls=None, lease=lease)


@pytest.mark.parametrize("resolve", ["largest", "", None, 3, rr.Claimant])
def test_a_bad_resolve_is_a_config_error_naming_resolve(resolve: Any) -> None:
    with pytest.raises(rr.ConfigError, match="resolve must be"):
        rr.ZenohNetwork(system="lab", tls=None, resolve=resolve)


def test_the_resolve_strategy_reaches_the_processes_that_attach() -> None:
    """Every process of a host decides alike (rule 22): the manager processes that join
    through the router take its `resolve` from its address."""
    net = rr.ZenohNetwork(system=f"resolve-{uuid.uuid4().hex[:8]}", tls=None, resolve="majority")
    try:
        assert ("majority", "majority") == (net.resolution.resolve, net.address.resolve)
        assert "resolve='majority'" in repr(net)
    finally:
        net.close()


def _nested_resolve() -> Any:
    keep = "second"

    def resolve(first: Any, second: Any) -> Any:
        return second if keep == "second" else first

    return resolve


def _attached_resolve(address: Any) -> Any:
    member = address.attach()
    try:
        return member.resolution.resolve("first", "second")
    finally:
        member.close()


@pytest.mark.parametrize("kind", ["lambda", "nested"])
def test_a_resolve_function_crosses_in_the_address_by_value(
    kind: str, context: multiprocessing.context.ForkServerContext
) -> None:
    """A process manager's start arguments, the address among them, are pickled with
    plain pickle: a lambda or a nested `resolve` crosses cloudpickled, and the process
    that attaches through the address decides with it."""
    keep = "second"
    resolve = (
        (lambda first, second: second if keep == "second" else first)
        if kind == "lambda"
        else _nested_resolve()
    )
    network = rr.ZenohNetwork(system=_system(), tls=None, resolve=resolve)
    try:
        address = network.address  # (opens the router)
        copy = pickle.loads(pickle.dumps(address))
        with context.Pool(1) as pool:
            there = pool.apply(_attached_resolve, (address,))
    finally:
        network.close()

    assert ("second", "second") == (copy.resolve("first", "second"), there)
    assert (copy.system, copy.socket_path, copy.router) == (
        address.system,
        address.socket_path,
        address.router,
    )


def test_a_resolve_function_that_cannot_be_pickled_is_a_config_error_naming_resolve() -> None:
    numbers = (n for n in range(3))  # (a generator: not even cloudpickle pickles it)
    with pytest.raises(rr.ConfigError, match="resolve must be a function that can be pickled"):
        rr.ZenohNetwork(
            system="lab", tls=None, resolve=lambda first, second: next(numbers) and first
        )


@pytest.mark.parametrize("max_offset", [0, -1.0, float("nan"), float("inf"), True, "60", 1e9])
def test_a_bad_max_offset_is_a_config_error_naming_max_offset(max_offset: Any) -> None:
    with pytest.raises(rr.ConfigError, match="max_offset"):
        rr.ZenohNetwork(system="lab", tls=None, max_offset=max_offset)


def test_the_max_offset_of_a_network_is_its_processes_clocks(
    context: multiprocessing.context.ForkServerContext,
) -> None:
    """The router's clock and that of a process that attaches through it take the
    network's `max_offset` (the clock is the process's: one system per process)."""
    network = rr.ZenohNetwork(system=_system(), tls=None, max_offset=2.5)
    try:
        address = network.address  # (opens the router)
        here = CLOCK.max_offset
        with context.Pool(1) as pool:
            there = pool.apply(_attached_max_offset, (address,))
    finally:
        network.close()
        CLOCK.max_offset = MAX_OFFSET

    assert (2.5, 2.5, 2.5) == (here, address.max_offset, there)


@pytest.mark.parametrize("endpoint", ["tcp/127.0.0.1:7447", "tcp/[::1]:7447", "tcp/localhost:0"])
def test_plain_tcp_on_loopback_is_a_warning_that_every_local_user_can_run_code_here(
    caplog: pytest.LogCaptureFixture, endpoint: str
) -> None:
    with caplog.at_level(logging.WARNING, logger="rr_actors"):
        rr.ZenohNetwork(system="lab", listen=[endpoint], tls=None)

    assert [
        (
            "rr_actors",
            logging.WARNING,
            f"ZenohNetwork 'lab' listens on {endpoint} in plain TCP (tls=None): every user "
            f"and process on this machine can connect and run code as this user, "
            f"{_me()} (what crosses is pickles); use tls= and tls/ endpoints",
        )
    ] == caplog.record_tuples


def test_plain_tcp_elsewhere_is_a_warning_that_anyone_who_reaches_it_can_run_code_here(
    caplog: pytest.LogCaptureFixture,
) -> None:
    with caplog.at_level(logging.WARNING, logger="rr_actors"):
        rr.ZenohNetwork(system="lab", listen=["tcp/10.0.0.2:7447", "tcp/0.0.0.0:7448"], tls=None)

    assert [
        "anyone who can reach 10.0.0.2 can connect",
        "anyone who can reach this machine (at any of its addresses) can connect",
    ] == [r.getMessage().split(": ", 1)[1].split(" and run")[0] for r in caplog.records]


def test_a_plain_tcp_connect_endpoint_is_a_warning_that_whoever_answers_can_run_code_here(
    caplog: pytest.LogCaptureFixture,
) -> None:
    with caplog.at_level(logging.WARNING, logger="rr_actors"):
        rr.ZenohNetwork(system="lab", connect=["tcp/127.0.0.1:7447", "tcp/10.0.0.1:7447"], tls=None)

    assert [
        "ZenohNetwork 'lab' connects to tcp/127.0.0.1:7447 in plain TCP (tls=None): every "
        "user and process on this machine (whoever listens on port 7447 first) can run code "
        f"as this user, {_me()}",
        "ZenohNetwork 'lab' connects to tcp/10.0.0.1:7447 in plain TCP (tls=None): whoever "
        "answers at 10.0.0.1 port 7447 (anyone who can listen there or sits between) can run "
        f"code as this user, {_me()}",
    ] == [r.getMessage().split(" (what crosses")[0] for r in caplog.records]


def test_a_network_only_on_its_unix_socket_logs_no_warning(
    caplog: pytest.LogCaptureFixture,
) -> None:
    with caplog.at_level(logging.WARNING, logger="rr_actors"):
        rr.ZenohNetwork(system="lab", tls=None)

    assert [] == caplog.record_tuples


def test_an_unreachable_connect_endpoint_is_a_warning_not_an_error(
    caplog: pytest.LogCaptureFixture,
) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    net = rr.ZenohNetwork(system=_system(), connect=[endpoint], tls=None)
    try:
        with caplog.at_level(logging.WARNING, logger="rr_actors"):
            assert [] == net.names()  # opens it

        assert any(endpoint in r.getMessage() for r in caplog.records)
    finally:
        net.close()


def test_import_rr_actors_does_not_import_zenoh() -> None:
    code = "import sys, rr_actors; assert 'zenoh' not in sys.modules; rr_actors.ZenohNetwork"
    code += "; assert 'zenoh' in sys.modules"

    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


def test_a_network_of_the_runtime_alone_runs_nothing_beside_its_session() -> None:
    """The runtime reads alone (issues 54, 71): a `ZenohNetwork` made from its module, with
    the lab not installed, opens and serves without it (no event feed, no link watch:
    `Beside`), and its `subscribe_events` names the import that attaches the feed."""
    code = HIDE_THE_LAB + textwrap.dedent(
        """
        import sys
        from rr_actors._transport.zenoh.net import ZenohNetwork
        from rr_actors.errors import ConfigError

        net = ZenohNetwork(system=sys.argv[1], tls=None)
        try:
            print(net.names(), net.address.beside, net.beside)
            try:
                net.subscribe_events(print)
            except ConfigError as exc:
                print("refused:", exc)
            print(sorted(m for m in sys.modules if m.startswith("rr_actors_lab.observe")))
        finally:
            net.close()
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", code, _system()],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )

    opened, refused, lab = done.stdout.splitlines()
    assert ("[] None None", "[]") == (opened, lab)
    assert "refused: the event stream across hosts is the observer's: import " in refused


def test_rr_zenoh_network_runs_the_labs_feed_and_watch_beside_and_hands_them_on() -> None:
    """`rr.ZenohNetwork` attaches the lab's `Across` (the event feed, the link watch); the
    address a manager process attaches through carries it by reference (unpickling it
    there imports it), so that process sends its events too."""
    net = rr.ZenohNetwork(system=_system(), tls=None)
    try:
        beside = pickle.loads(pickle.dumps(net.address)).beside
        net.link()
        kind = type(net.beside)

        named = [f"{each.__module__}.{each.__qualname__}" for each in (beside, kind)]
        assert ["rr_actors_lab.observe._feed.Across"] * 2 == named
        assert b"rr_actors_lab.observe._feed" in pickle.dumps(net.address)
    finally:
        net.close()


def test_the_runtime_directory_is_private_and_removed_at_close() -> None:
    net = rr.ZenohNetwork(system=_system(), tls=None)
    path = net.address.socket_path
    directory = os.path.dirname(path)
    mode = os.stat(directory).st_mode & 0o777
    net.close()

    assert (0o700, False) == (mode, os.path.exists(directory))


def test_a_process_belongs_to_one_system() -> None:
    first = rr.ZenohNetwork(system=_system(), tls=None)
    second = rr.ZenohNetwork(system=_system(), tls=None)
    try:
        first.names()
        with pytest.raises(rr.ConfigError, match=f"system {second.system!r}"):
            second.names()
    finally:
        first.close()
        second.close()


class TestBadArguments:
    """`ZenohNetwork.wait_for` and `subscribe_events` given what they cannot use.

    A name no registrar can have (`None`, `5`, a key expression such as `"*"`) is a
    `ConfigError` at once, not a wait of the whole timeout that ends saying the registrar was
    not served; a callback that is not callable is refused before the session opens, not
    logged as a `TypeError` for every event.
    """

    @pytest.fixture
    def net(self) -> Iterator[rr.ZenohNetwork]:
        """A plain-TCP network on loopback, not opened yet."""
        system = f"bad-args-{uuid.uuid4().hex[:8]}"
        made = rr.ZenohNetwork(system=system, listen=[f"tcp/127.0.0.1:{free_port()}"], tls=None)
        try:
            yield made
        finally:
            made.close()

    @pytest.mark.parametrize("name", [None, 5, "*", "a/**", ""])
    def test_wait_for_a_name_no_registrar_can_have_is_a_config_error_naming_it(
        self, net: rr.ZenohNetwork, name: object
    ) -> None:
        with pytest.raises(rr.ConfigError, match="not a registrar name"):
            net.wait_for(name, timeout=5)  # type: ignore[arg-type]

    def test_subscribe_events_with_a_callback_that_is_not_callable_is_a_config_error(
        self,
        net: rr.ZenohNetwork,
    ) -> None:
        with pytest.raises(rr.ConfigError, match="callback"):
            net.subscribe_events("print")  # type: ignore[arg-type]


class TestOpen:
    """How long opening a Zenoh router takes, and what it waits for.

    Zenoh's open of a router session waits its scouting `delay` (500 ms) for links to other
    routers: the ones it connects to, and the ones that connect to its TCP `listen` endpoints
    (a router of another host that retries every 250 ms-1 s gets in meanwhile). With neither
    (one host alone, scouting off) nothing can come up, so `ZenohNetwork` sets the delay to 0:
    such a router (every test of the zenoh placement opens one) is open at once. With a
    `connect` or TCP `listen` endpoint the wait stays: the link to the other router is up when
    the open returns, so a name served right away is checked against that host too.
    """

    def test_a_router_without_connect_endpoints_opens_without_the_scouting_wait(self):
        """Its config sets Zenoh's scouting `delay` to 0 (a wall-clock bound on the open
        failed under load: 1.5 s of CPU waits, no scouting), and it opens."""
        alone = session_config("router", ["unixsock-stream//tmp/rr-alone.sock"], [], 1.0)
        linked = session_config("router", [], ["tcp/127.0.0.1:7447"], 1.0)
        network = rr.ZenohNetwork(system=f"open-{uuid.uuid4().hex[:8]}", tls=None)
        try:
            assert network.address.socket_path  # opens the router session
        finally:
            network.close()

        assert ("0", "null") == (
            alone.get_json("scouting/delay"),
            linked.get_json("scouting/delay"),
        )

    def test_a_router_with_a_connect_endpoint_is_linked_when_its_open_returns(self):
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        listening = zenoh.open(session_config("router", [endpoint], [], 1.0))
        try:
            connecting = zenoh.open(session_config("router", [], [endpoint], 1.0))
            try:
                assert [listening.zid()] == list(connecting.info.routers_zid())
            finally:
                connecting.close()  # type: ignore[no-untyped-call]
        finally:
            listening.close()  # type: ignore[no-untyped-call]


class TestWaitFor:
    """`ZenohNetwork.wait_for`: "either machine may start first" (docs/how-to/two-machines.md).

    The waiting side's first call no longer fails at once when the other side starts later:
    `wait_for` returns as soon as the registrar's presence is seen, and at its timeout says
    why it was not (a connect endpoint with no link, and the link watch's reason). An
    `UnknownRegistrarError` says the same. The provider runs in a process of its own (a
    process belongs to one system), started after the wait began.
    """

    @pytest.mark.timeout(90)
    def test_wait_for_returns_once_a_provider_that_starts_later_serves_and_the_call_then_works(
        self,
    ) -> None:
        system, port, name = (
            f"wait-{uuid.uuid4().hex[:8]}",
            free_port(),
            f"erm-{uuid.uuid4().hex[:8]}",
        )
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

    def test_wait_for_a_registrar_served_in_this_process_returns_at_once(self) -> None:
        name = f"erm-{uuid.uuid4().hex[:8]}"
        with (
            rr.ZenohNetwork(system=f"wait-{uuid.uuid4().hex[:8]}", tls=None) as net,
            rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name), network=net),
        ):
            net.wait_for(name, timeout=0)

    def test_wait_for_with_no_connect_endpoint_times_out_unavailable(self) -> None:
        with rr.ZenohNetwork(system=f"wait-{uuid.uuid4().hex[:8]}", tls=None) as net:
            began = time.monotonic()
            with pytest.raises(
                rr.RegistrarUnavailableError,
                match=r"^no registrar named 'erm' was served on system 'wait-\w+' within 0\.5 s$",
            ):
                net.wait_for("erm", timeout=0.5)
            assert time.monotonic() - began >= 0.5

    @pytest.mark.parametrize("timeout", [-1, float("nan"), "5", True])
    def test_wait_for_with_a_bad_timeout_is_a_config_error(self, timeout: object) -> None:
        net = rr.ZenohNetwork(system="wait", tls=None)
        with pytest.raises(rr.ConfigError, match="timeout must be seconds >= 0"):
            net.wait_for("erm", timeout=timeout)  # type: ignore[arg-type]
        assert not net.closed  # never opened

    def test_wait_for_after_close_says_the_process_left_the_system(self) -> None:
        net = rr.ZenohNetwork(system=f"wait-{uuid.uuid4().hex[:8]}", tls=None)
        net.address  # noqa: B018 - opens the session
        net.close()
        with pytest.raises(rr.RegistrarStoppedError, match="left system"):
            net.wait_for("erm", timeout=1)

    # -- a host this process cannot link to ----------------------------------------------------

    @pytest.fixture
    def refused(self, tmp_path: Path):  # type: ignore[no-untyped-def]
        """A TLS listener of another CA on loopback, and this host's `ZenohTLS` (of the lab's)."""
        port = free_port()
        other = member_tls(tmp_path / "other", pki.make_ca(tmp_path / "other-ca", "other"), "robot")
        mine = member_tls(tmp_path / "mine", pki.make_ca(tmp_path / "lab", "lab"), "operator")
        with router(other, [f"tls/127.0.0.1:{port}"], []):
            yield port, mine

    def test_wait_for_a_registrar_behind_a_refusing_host_names_the_endpoint_and_why(
        self,
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
        assert message.startswith(
            "no registrar named 'erm' was served on system 'lab' within 1 s; "
        )
        assert f"no link to connect endpoint {endpoint} (" in message
        assert re.search(REASON, message), message

    def test_a_call_to_a_registrar_behind_a_refusing_host_names_the_endpoint_and_why(
        self,
        refused: tuple[int, object],
    ) -> None:
        port, tls = refused
        endpoint, uid = f"tls/127.0.0.1:{port}", uuid.uuid4().hex[:8]
        with rr.ZenohNetwork(system="lab", connect=[endpoint], tls=tls) as net:  # type: ignore[arg-type]
            station = rr.ResourceRegistrar.start(
                rr.RegistrarConfig(name=f"station{uid}"), network=net
            )
            try:
                with pytest.raises(rr.UnknownRegistrarError) as raised:
                    station.call(f"erm-{uid}", "camera", 0, timeout=10)
            finally:
                station.stop()
        message = str(raised.value)
        assert message.startswith(f"no registrar named 'erm-{uid}' on system 'lab'")
        assert f"this process has no link to connect endpoint {endpoint} (" in message
        assert re.search(REASON, message), message

    # -- plain TCP: a connect endpoint nobody listens on (issue 44 item 7) ------------------

    def test_wait_for_over_plain_tcp_names_the_connect_endpoint_nobody_listens_on(self) -> None:
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

    def test_a_call_over_plain_tcp_names_the_connect_endpoint_nobody_listens_on(self) -> None:
        endpoint, uid = f"tcp/127.0.0.1:{free_port()}", uuid.uuid4().hex[:8]
        with rr.ZenohNetwork(system="lab", connect=[endpoint], tls=None) as net:
            station = rr.ResourceRegistrar.start(
                rr.RegistrarConfig(name=f"station{uid}"), network=net
            )
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

    def test_a_plain_tcp_connect_endpoint_that_is_linked_is_not_named(self) -> None:
        port, uid = free_port(), uuid.uuid4().hex[:8]
        with (
            router(None, [f"tcp/127.0.0.1:{port}"], [], system="lab") as other,
            rr.ZenohNetwork(system="lab", connect=[f"tcp/127.0.0.1:{port}"], tls=None) as net,
        ):
            station = rr.ResourceRegistrar.start(
                rr.RegistrarConfig(name=f"station{uid}"), network=net
            )
            try:
                assert wait_for(lambda: bool(list(other.info.links())), 10)  # (linked)
                with pytest.raises(rr.UnknownRegistrarError) as raised:
                    station.call(f"erm-{uid}", "camera", 0, timeout=10)
            finally:
                station.stop()

        assert "no link" not in str(raised.value)


class TestExit:
    """A program with a `ZenohNetwork` ends: after an error, when it forgets `close()`, and at
    the first Ctrl-C (one line, killed by SIGINT as Python ends after a Ctrl-C: a shell says
    130), in a real terminal.

    Zenoh's callback threads are not daemons: a session left open kept the interpreter
    waiting for them forever, and a Ctrl-C reached the manager processes too (each printed a
    traceback). Each test runs the how-to's programs (docs/how-to/two-machines.md), on
    loopback, in their own interpreter.
    """

    @pytest.mark.parametrize(("ending", "code"), [("raises", 1), ("returns", 0)])
    def test_a_program_that_leaves_its_network_open_ends(self, ending: str, code: int) -> None:
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

    @pytest.mark.timeout(120)
    def test_the_first_ctrl_c_in_a_terminal_ends_a_supervisor_with_a_network_in_one_line(
        self,
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
