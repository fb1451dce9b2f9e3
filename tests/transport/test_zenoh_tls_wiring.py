"""`ZenohNetwork(tls=...)` on one host: endpoints, the session's TLS and access control, the
handshake probe and the link watch, against real Zenoh listeners on loopback.

Two hosts (members calling each other, refused peers, impostors, a burst of refused
handshakes) are `tests/multihost/test_zenoh_tls.py`; `ZenohTLS`'s own checks are
`test_zenoh_tls_config.py`. Here the listeners are raw Zenoh sessions made with the very
config `ZenohNetwork` makes (`session_config`), in this process.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import logging
import os
import queue
import socket
import subprocess
import sys
import threading
import types
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

import rr_actors as rr
from rr_actors._transport.zenoh.ops.config import session_config
from rr_actors._transport.zenoh.ops.watch import LinkWatch, handshake_trouble
from rr_actors.testing import start_forkserver
from tests.support import pki
from tests.support.supervising import process
from tests.support.tls_lab import free_port
from tests.support.waiting import wait_for

MEMBERS = ["robot", "operator"]
DAY = datetime.timedelta(days=1)


class Lab:
    """A CA "lab" in a temporary directory, and `ZenohTLS`es of its members on loopback."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.ca = pki.make_ca(directory / "lab", "lab")

    def tls(self, name: str, addresses: tuple[str, ...] = ("127.0.0.1",), **issue: Any) -> Any:
        ca = issue.pop("ca", self.ca)
        where = self.directory / uuid.uuid4().hex[:8]
        cert, key = pki.issue(where, name, addresses, ca=ca, **issue)
        members = [*MEMBERS, name] if name not in MEMBERS else MEMBERS
        return rr.ZenohTLS(ca=ca[0], cert=cert, key=key, members=members)


@pytest.fixture(scope="module", autouse=True)
def forkserver() -> None:
    """Manager processes start from the forkserver: a process with a Zenoh session must not
    fork (started before any test, as the leftover check expects)."""
    start_forkserver()


@pytest.fixture
def lab(tmp_path: Path) -> Lab:
    return Lab(tmp_path)


@contextlib.contextmanager
def listener(tls: Any, port: int, system: str = "lab") -> Iterator[zenoh.Session]:
    """A Zenoh router listening on `tls/127.0.0.1:<port>` with rr_actors's config."""
    session = zenoh.open(
        session_config("router", [f"tls/127.0.0.1:{port}"], [], 1.0, system=system, tls=tls)
    )
    try:
        yield session
    finally:
        session.close()  # type: ignore[no-untyped-call]


# -- endpoints against tls ---------------------------------------------------------------------


@pytest.mark.parametrize("role", ["listen", "connect"])
def test_a_tcp_endpoint_with_tls_is_a_config_error_saying_to_use_tls(lab: Lab, role: str) -> None:
    tls = lab.tls("robot")
    with pytest.raises(
        rr.ConfigError, match=r"'tcp/10\.0\.0\.1:7447' is plain TCP.*'tls/10\.0\.0\.1:7447'"
    ):
        rr.ZenohNetwork(system="lab", tls=tls, **{role: ["tcp/10.0.0.1:7447"]})


@pytest.mark.parametrize("role", ["listen", "connect"])
def test_a_tls_endpoint_without_tls_is_a_config_error_naming_it(role: str) -> None:
    with pytest.raises(
        rr.ConfigError, match=r"'tls/10\.0\.0\.1:7447' is a tls/ endpoint, but tls=None"
    ):
        rr.ZenohNetwork(system="lab", tls=None, **{role: ["tls/10.0.0.1:7447"]})


def test_with_tls_a_public_listen_endpoint_gets_no_plain_tcp_warning(
    lab: Lab, caplog: pytest.LogCaptureFixture
) -> None:
    tls = lab.tls("robot")
    with caplog.at_level(logging.WARNING, logger="rr_actors"):
        net = rr.ZenohNetwork(system="lab", listen=["tls/10.0.0.1:7447"], tls=tls)
    assert "plain TCP" not in caplog.text
    assert "tls=ZenohTLS(" in repr(net)
    assert "'robot'" in repr(net)


# -- the session's config ----------------------------------------------------------------------


def test_the_config_is_mutual_tls_on_tls_and_unix_links_with_default_deny(lab: Lab) -> None:
    tls = lab.tls("robot")
    config = session_config("router", ["tls/127.0.0.1:7447"], [], 1.0, system="lab", tls=tls)
    link = json.loads(config.get_json("transport/link"))
    assert link["protocols"] == ["tls", "unixsock-stream"]
    assert link["tls"]["enable_mtls"] is True
    assert link["tls"]["verify_name_on_connect"] is True
    assert link["tls"]["close_link_on_expiration"] is True
    assert link["tls"]["root_ca_certificate"] == tls.ca
    acl = json.loads(config.get_json("access_control"))
    assert acl["enabled"] is True
    assert acl["default_permission"] == "deny"
    assert acl["rules"][0]["key_exprs"] == ["rr/lab/**"]
    assert acl["rules"][0]["flows"] == ["egress", "ingress"]
    subjects = {subject["id"]: subject for subject in acl["subjects"]}
    assert subjects["members"]["cert_common_names"] == [*MEMBERS]
    assert subjects["local"]["link_protocols"] == ["unixsock-stream"]


def test_a_plain_tcp_peer_cannot_even_open_a_link_to_a_tls_router(lab: Lab) -> None:
    """Protocols are limited to tls and unixsock-stream: a tcp/ connect gets nothing."""
    port = free_port()
    with listener(lab.tls("robot"), port) as router:
        plain = zenoh.open(session_config("peer", [], [f"tcp/127.0.0.1:{port}"], 1.0))
        try:
            assert router.info.links() == []
        finally:
            plain.close()  # type: ignore[no-untyped-call]


# -- the probe ---------------------------------------------------------------------------------


def test_the_probe_passes_a_member_accepted_by_the_listener(lab: Lab) -> None:
    port = free_port()
    with listener(lab.tls("robot"), port):
        assert handshake_trouble(lab.tls("operator"), "127.0.0.1", port) is None


@pytest.mark.parametrize(
    ("issued", "alert"),
    [
        pytest.param({"ca": "other"}, "unknown ca", id="another-ca"),
        pytest.param({"not_after": "past"}, "certificate expired", id="expired"),
    ],
)
def test_the_probe_names_the_listeners_alert_when_it_refuses_our_certificate(
    lab: Lab, tmp_path: Path, issued: dict[str, str], alert: str
) -> None:
    """Files `ZenohTLS` would refuse (they change under a running host: a certificate that
    expired since, a CA bundle that is not the listener's), so given to the probe as is."""
    now = datetime.datetime.now(datetime.UTC)
    options: dict[str, Any] = {"ca": lab.ca}
    if issued.get("ca") == "other":
        options["ca"] = pki.make_ca(tmp_path / "other", "other")
    if issued.get("not_after") == "past":
        options.update(not_before=now - 2 * DAY, not_after=now - DAY)
    cert, key = pki.issue(tmp_path / "ours", "operator", ("127.0.0.1",), **options)
    files = types.SimpleNamespace(ca=str(lab.ca[0]), cert=str(cert), key=str(key))
    port = free_port()
    with listener(lab.tls("robot"), port):
        reason = handshake_trouble(files, "127.0.0.1", port)  # type: ignore[arg-type]
    assert reason == f"the listener refused this host's certificate ({alert})"


def test_the_probe_names_an_impostor_listener_of_another_ca(lab: Lab, tmp_path: Path) -> None:
    other = pki.make_ca(tmp_path / "other", "other")
    port = free_port()
    with listener(lab.tls("robot", ca=other), port):
        reason = handshake_trouble(lab.tls("operator"), "127.0.0.1", port)
    assert reason is not None
    assert reason.startswith("the listener's certificate is not signed by this system's CA")


def test_the_probe_names_a_listener_whose_certificate_does_not_name_the_address(
    lab: Lab,
) -> None:
    port = free_port()
    with listener(lab.tls("robot", ("10.9.9.9",)), port):
        reason = handshake_trouble(lab.tls("operator"), "127.0.0.1", port)
    assert reason is not None
    assert reason.startswith("the listener's certificate does not name 127.0.0.1")


def test_the_probe_says_a_port_nobody_listens_on_cannot_be_reached(lab: Lab) -> None:
    reason = handshake_trouble(lab.tls("operator"), "127.0.0.1", free_port())
    assert reason is not None
    assert reason.startswith("cannot reach it")


def test_the_probe_gives_up_on_a_listener_that_never_hands_shake(lab: Lab) -> None:
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen()
        port = silent.getsockname()[1]
        reason = handshake_trouble(lab.tls("operator"), "127.0.0.1", port, timeout=0.3)
    assert reason == "no TLS handshake within 0.3 s"


def test_the_probe_names_its_own_files_when_they_changed_since(lab: Lab) -> None:
    tls = lab.tls("operator")
    Path(tls.key).write_text("not a key any more")
    reason = handshake_trouble(tls, "127.0.0.1", free_port())
    assert reason is not None
    assert reason.startswith("this host's own TLS files cannot be loaded")


# -- the watch ---------------------------------------------------------------------------------


class Logged(logging.Handler):
    """The `rr_actors` log lines, and an event when one containing `text` comes."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.lines: list[tuple[str, str]] = []
        self.changed = threading.Condition()

    def emit(self, record: logging.LogRecord) -> None:
        with self.changed:
            self.lines.append((record.levelname, record.getMessage()))
            self.changed.notify_all()

    def wait(self, level: str, text: str, timeout: float) -> str:
        def found() -> str | None:
            return next((m for lv, m in self.lines if lv == level and text in m), None)

        with self.changed:
            self.changed.wait_for(found, timeout=timeout)
            line = found()
        assert line is not None, f"no {level} with {text!r} within {timeout} s: {self.lines}"
        return line


@pytest.fixture
def logged() -> Iterator[Logged]:
    handler = Logged()
    log = logging.getLogger("rr_actors")
    level = log.level
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    yield handler
    log.removeHandler(handler)
    log.setLevel(level)


def _router(tls: Any, connect: list[str], system: str = "lab") -> zenoh.Session:
    return zenoh.open(session_config("router", [], connect, 1.0, system=system, tls=tls))


def test_the_watch_names_a_member_that_links_on_both_sides(lab: Lab, logged: Logged) -> None:
    port = free_port()
    robot, operator = lab.tls("robot"), lab.tls("operator")
    with listener(robot, port) as session:
        listening = LinkWatch("lab", session, robot, ())
        connecting_session = _router(operator, [f"tls/127.0.0.1:{port}"])
        connecting = LinkWatch("lab", connecting_session, operator, (f"tls/127.0.0.1:{port}",))
        try:
            logged.wait("INFO", "member 'operator' linked at 127.0.0.1", timeout=10)
            logged.wait("INFO", "member 'robot' linked at 127.0.0.1", timeout=10)
        finally:
            connecting.close()
            listening.close()
            connecting_session.close()  # type: ignore[no-untyped-call]
    assert not [m for lv, m in logged.lines if lv == "WARNING"]


def test_the_watch_warns_once_of_a_ca_signed_non_member_whose_messages_are_dropped(
    lab: Lab, logged: Logged
) -> None:
    port = free_port()
    robot = lab.tls("robot")
    with listener(robot, port) as session:
        watch = LinkWatch("lab", session, robot, ())
        heard = threading.Event()
        subscriber = session.declare_subscriber("rr/lab/**", lambda _sample: heard.set())
        strangers = [_router(lab.tls("stranger"), [f"tls/127.0.0.1:{port}"]) for _ in range(2)]
        try:
            line = logged.wait("WARNING", "'stranger' at 127.0.0.1", timeout=10)
            assert "not in members ['robot', 'operator']" in line
            assert "dropped" in line
            wait_for(lambda: len(session.info.links()) == 2, timeout=10)
            for stranger in strangers:
                stranger.put("rr/lab/reg/erm", b"dropped")
            # a member's put after the strangers' goes through: theirs were dropped, not late
            member = _router(lab.tls("operator"), [f"tls/127.0.0.1:{port}"])
            try:
                wait_for(lambda: len(session.info.links()) == 3, timeout=10)
                assert not heard.is_set()
                # (a link just up may not route a put yet: put until heard, bounded)
                assert any(
                    member.put("rr/lab/reg/erm", b"heard") or heard.wait(0.2) for _ in range(50)
                )
            finally:
                member.close()  # type: ignore[no-untyped-call]
        finally:
            subscriber.undeclare()  # type: ignore[no-untyped-call]
            watch.close()
            for stranger in strangers:
                stranger.close()  # type: ignore[no-untyped-call]
    warnings = [m for lv, m in logged.lines if lv == "WARNING" and "'stranger'" in m]
    assert len(warnings) == 1, warnings  # once per address per minute


def test_the_watch_warns_with_the_reason_when_a_connect_endpoint_stays_unlinked(
    lab: Lab, logged: Logged, tmp_path: Path
) -> None:
    other = pki.make_ca(tmp_path / "other", "other")
    port = free_port()
    endpoint = f"tls/127.0.0.1:{port}"
    refused = lab.tls("operator", ca=other)
    with listener(lab.tls("robot"), port):
        session = _router(refused, [endpoint])
        watch = LinkWatch("lab", session, refused, (endpoint,))
        try:
            line = logged.wait("WARNING", f"no link to connect endpoint {endpoint}", timeout=10)
        finally:
            watch.close()
            session.close()  # type: ignore[no-untyped-call]
    # its own check fails first: the listener's certificate is not of its CA (and the
    # listener would refuse its certificate too)
    assert f"the listener's certificate is not signed by this system's CA {other[0]}" in line
    assert "UnknownRegistrarError" in line


def test_a_tls_network_that_closes_stops_its_watch(lab: Lab) -> None:
    net = rr.ZenohNetwork(
        system=f"t-{uuid.uuid4().hex[:8]}",
        listen=[f"tls/127.0.0.1:{free_port()}"],
        tls=lab.tls("robot"),
    )
    net.names()  # opens
    assert any(t.name == "rr-zenoh-watch" for t in threading.enumerate())
    net.close()
    assert not any(t.name == "rr-zenoh-watch" for t in threading.enumerate())


# -- this host's manager processes -------------------------------------------------------------


def test_a_tls_routers_manager_processes_join_over_its_unix_socket_and_are_admitted(
    lab: Lab, supervisors: Callable[..., rr.Supervisor]
) -> None:
    """The ACL admits `unixsock-stream` links: a supervised manager process serves on a TLS
    network and a registrar of the router's process calls it (no TCP on loopback at all)."""
    net = rr.ZenohNetwork(
        system=f"t-{uuid.uuid4().hex[:8]}",
        listen=[f"tls/127.0.0.1:{free_port()}"],
        tls=lab.tls("robot"),
    )
    try:
        with supervisors([process("erm")], network=net):
            app = rr.ResourceRegistrar.start(rr.RegistrarConfig(name="app"), network=net)
            try:
                query = app.call("erm", "echo", "over the unix socket", timeout=10)
                assert query.response == "over the unix socket"
                app.unload(query.id, timeout=10)
            finally:
                app.stop()
        assert all(
            link.dst.startswith("unixsock-stream/") for link in net.link().session.info.links()
        )
    finally:
        net.close()


# -- Zenoh's own log of refused handshakes -----------------------------------------------------

_LISTENER = """
import sys
import rr_actors as rr
ca, cert, key, port = sys.argv[1:]
tls = rr.ZenohTLS(ca=ca, cert=cert, key=key, members=["robot"])
net = rr.ZenohNetwork(system="lab", listen=[f"tls/127.0.0.1:{port}"], tls=tls)
net.names()
print("ready", flush=True)
sys.stdin.read()
net.close()
"""


def test_rust_log_shows_the_listeners_own_line_for_a_refused_handshake(
    lab: Lab, tmp_path: Path
) -> None:
    """The how-to's `RUST_LOG=zenoh_link_tls=warn`: the router's `ZenohNetwork` starts
    Zenoh's log, which names the reason of each handshake it refused."""
    robot, port = lab.tls("robot"), free_port()
    other = pki.make_ca(tmp_path / "other", "other")
    cert, key = pki.issue(tmp_path / "refused", "operator", ("127.0.0.1",), ca=other)
    refused = types.SimpleNamespace(ca=robot.ca, cert=str(cert), key=str(key))
    lines: queue.Queue[str] = queue.Queue()
    env = {**os.environ, "RUST_LOG": "zenoh_link_tls=warn"}
    with subprocess.Popen(
        [sys.executable, "-c", _LISTENER, robot.ca, robot.cert, robot.key, str(port)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    ) as listening:
        assert listening.stdout is not None
        reader = threading.Thread(target=lambda: [lines.put(line) for line in listening.stdout])  # type: ignore[union-attr]
        reader.start()
        try:
            assert lines.get(timeout=30).strip() == "ready"
            reason = handshake_trouble(refused, "127.0.0.1", port)  # type: ignore[arg-type]
            assert reason == "the listener refused this host's certificate (unknown ca)"
            line = lines.get(timeout=10)
            assert "zenoh_link_tls" in line
            assert "invalid peer certificate: UnknownIssuer" in line
        finally:
            assert listening.stdin is not None
            listening.stdin.close()
            listening.wait(timeout=30)
            reader.join(timeout=10)


# -- rotation ----------------------------------------------------------------------------------


def _put_until_heard(member: zenoh.Session, heard: queue.Queue[bytes], data: bytes) -> bool:
    """Put `data` until it is heard (a link just up may not route a put yet), at most 10 s."""
    for _ in range(50):
        member.put("rr/lab/reg/erm", data)
        with contextlib.suppress(queue.Empty):
            if heard.get(timeout=0.2) == data:
                return True
    return False


def test_a_member_restarted_with_a_new_certificate_of_the_same_ca_rejoins(
    lab: Lab, logged: Logged
) -> None:
    """The how-to's rotation: re-issue (a new key, the same name and CA), restart, rejoin;
    the listener changes nothing."""
    port = free_port()
    robot = lab.tls("robot")
    with listener(robot, port) as session:
        watch = LinkWatch("lab", session, robot, ())
        heard: queue.Queue[bytes] = queue.Queue()
        subscriber = session.declare_subscriber(
            "rr/lab/reg/erm", lambda sample: heard.put(sample.payload.to_bytes())
        )
        try:
            for round_ in ("old", "new"):
                operator = lab.tls("operator")  # a fresh key and certificate each time
                member = _router(operator, [f"tls/127.0.0.1:{port}"])
                try:
                    wait_for(lambda: len(session.info.links()) == 1, timeout=10)
                    assert _put_until_heard(member, heard, round_.encode()), round_
                finally:
                    member.close()  # type: ignore[no-untyped-call]
                wait_for(lambda: session.info.links() == [], timeout=10)
        finally:
            subscriber.undeclare()  # type: ignore[no-untyped-call]
            watch.close()
    joined = [m for lv, m in logged.lines if lv == "INFO" and "member 'operator' linked" in m]
    assert len(joined) == 2, logged.lines
