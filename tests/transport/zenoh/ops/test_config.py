"""A Zenoh session's config (`rr_actors._transport.zenoh.ops.config`) on one host:
endpoints against `tls`, mutual TLS and the access control, against real Zenoh listeners
on loopback; `TestAnotherLocalUser`: what plain TCP and TLS let another user do.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import queue
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import types
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest
import zenoh

import rr_actors as rr
from rr_actors._transport.codec import frame
from rr_actors._transport.zenoh.ops.config import session_config
from rr_actors.testing import RemoteRegistrar
from rr_actors_lab._tools import certs as certs_tool
from rr_actors_lab.observe._links import LinkWatch, handshake_trouble
from tests.support import pki
from tests.support.hosts import free_port
from tests.support.supervising import process
from tests.support.tls_lab import MEMBERS, Lab, Logged, caught_log, listener, open_router
from tests.support.waiting import wait_for

pytestmark = pytest.mark.usefixtures("forkserver")


@pytest.fixture
def lab(tmp_path: Path) -> Lab:
    return Lab(tmp_path)


# -- the watch ---------------------------------------------------------------------------------


@pytest.fixture
def logged() -> Iterator[Logged]:
    with caught_log() as handler:
        yield handler


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


# -- rotation ----------------------------------------------------------------------------------


def _put_until_heard(member: zenoh.Session, heard: queue.Queue[bytes], data: bytes) -> bool:
    """Put `data` until it is heard (a link just up may not route a put yet), at most 10 s."""
    for _ in range(50):
        member.put("rr/lab/reg/erm", data)
        with contextlib.suppress(queue.Empty):
            if heard.get(timeout=0.2) == data:
                return True
    return False


NOBODY = 65534


ROOT = Path(__file__).resolve().parents[4]


_PWNED = threading.Event()


_RAN_AS: list[int] = []


def _pwned() -> None:
    """What the attacker's pickle calls when it is unpickled (in this process)."""
    _RAN_AS.append(os.geteuid())
    _PWNED.set()


class _Payload:
    def __reduce__(self) -> tuple[Any, ...]:
        return (_pwned, ())


ATTACKER = r"""
import json, os, select, sys, zenoh
from rr_actors._transport.zenoh.wire import MESSAGE, header

system, target, body, key = sys.argv[1], sys.argv[2], bytes.fromhex(sys.argv[3]), sys.argv[4]
outcome = {"uid": os.geteuid()}
try:
    open(key, "rb").close()
    outcome["key"] = "read"
except OSError as exc:
    outcome["key"] = type(exc).__name__
for label, config in json.loads(sys.argv[5]):
    try:
        session = zenoh.open(zenoh.Config.from_json5(config))
    except Exception:
        outcome[label] = "refused"
        continue
    zid = str(session.zid())
    token = session.liveliness().declare_token(f"rr/{system}/live/proc/{zid}")
    for _ in range(100):  # until the test says stop (a line on stdin): at most 100 x 0.1 s
        session.put(f"rr/{system}/reg/{target}", header(MESSAGE, zid) + body)
        if select.select([sys.stdin], [], [], 0.1)[0]:
            break
    token.undeclare()
    session.close()
    outcome[label] = "sent"
print(json.dumps(outcome), flush=True)
"""


def _client(endpoint: str, tls: dict[str, Any] | None = None) -> str:
    config: dict[str, Any] = {
        "mode": "client",
        "connect": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
    }
    if tls is not None:
        config["transport"] = {"link": {"tls": tls}}
    return json.dumps(config)


def _hidden_ancestor(path: Path) -> Path | None:
    """The first directory above `path` that others cannot enter, or `None`."""
    for parent in reversed(path.parents):
        if not os.stat(parent).st_mode & 0o001:
            return parent
    return None


def _as_nobody(*argv: str) -> subprocess.Popen[str]:
    """`python -c ATTACKER *argv` as user `nobody`, able to run this interpreter.

    The interpreter's trees (its base installation and, in a virtual environment such as
    CI's, the environment) may lie under directories others cannot enter (/root, a 0700
    temporary directory): then the attacker runs in a mount namespace where a tmpfs lies
    over each such directory with only those trees put back.
    """
    python = [sys.executable, "-c", ATTACKER, *argv]
    setpriv = ["setpriv", f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups"]
    trees: dict[Path, set[Path]] = {}  # a hidden directory -> the trees under it to show
    for prefix in {Path(sys.base_prefix).resolve(), Path(sys.prefix).resolve()}:
        hidden = _hidden_ancestor(prefix)
        if hidden is not None:
            trees.setdefault(hidden, set()).add(hidden / prefix.relative_to(hidden).parts[0])
    if not trees:
        command = [*setpriv, *python]
    else:
        steps = []
        for hidden, shown in sorted(trees.items()):
            stashes = {tree: tempfile.mkdtemp() for tree in sorted(shown)}
            steps += [f'mount --bind "{tree}" "{stash}"' for tree, stash in stashes.items()]
            steps.append(f'mount -t tmpfs -o mode=0755 none "{hidden}"')
            for tree, stash in stashes.items():
                steps += [
                    f'mkdir -p "{tree}"',
                    f'mount --move "{stash}" "{tree}"',
                    f'rmdir "{stash}"',
                ]
        script = " && ".join(steps) + ' ; exec "$@"'
        command = ["unshare", "--mount", "--propagation", "private", "sh", "-c", script, "sh"]
        command += [*setpriv, *python]
    return subprocess.Popen(
        command,
        cwd="/",
        env={"PATH": os.environ["PATH"], "PYTHONPATH": str(ROOT), "HOME": "/"},
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _outcome(attacker: subprocess.Popen[str], *, stop: bool = False) -> dict[str, Any]:
    out, err = attacker.communicate("stop\n" if stop else "", timeout=60)
    assert 0 == attacker.returncode, err
    result: dict[str, Any] = json.loads(out)
    return result


def test_networks_and_their_manager_processes_that_came_and_went_leave_no_file_open() -> None:
    """A session shares no memory: with Zenoh's default, this process kept a segment file
    (/dev/shm/*.zenoh) of each process it had talked with open for good (one more for
    each network here; a supervisor's restarted managers, one each)."""

    def open_files() -> int:  # (segment files only: other tests' threads open and close
        held = 0  # sockets and pipes as they end, which a count of every file would see)
        for fd in os.listdir("/proc/self/fd"):
            with contextlib.suppress(OSError):  # (closed meanwhile)
                held += os.readlink(f"/proc/self/fd/{fd}").startswith("/dev/shm/")  # noqa: S108
        return held

    def network_with_a_manager_process() -> None:
        network = rr.ZenohNetwork(system=f"test-{uuid.uuid4().hex[:8]}", tls=None)
        try:
            name = f"rr-{uuid.uuid4().hex[:8]}"
            RemoteRegistrar.start(rr.RegistrarConfig(name=name), network).stop()
        finally:
            network.close()

    for _ in range(2):  # (Zenoh's runtime, its threads' polls: made once, then kept)
        network_with_a_manager_process()
    before = open_files()
    for _ in range(5):
        network_with_a_manager_process()

    assert before == open_files()


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


def test_a_plain_tcp_peer_cannot_even_open_a_link_to_a_tlsopen_router(lab: Lab) -> None:
    """Protocols are limited to tls and unixsock-stream: a tcp/ connect gets nothing."""
    port = free_port()
    with listener(lab.tls("robot"), port) as router:
        plain = zenoh.open(session_config("peer", [], [f"tcp/127.0.0.1:{port}"], 1.0))
        try:
            assert router.info.links() == []
        finally:
            plain.close()  # type: ignore[no-untyped-call]


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
        with (
            supervisors([process("erm")], network=net),
            rr.ResourceRegistrar.start(rr.RegistrarConfig(name="app"), network=net) as app,
        ):
            query = app.call("erm", "echo", "over the unix socket", timeout=10)
            assert query.response == "over the unix socket"
            app.unload(query.id, timeout=10)
        assert all(
            link.dst.startswith("unixsock-stream/") for link in net.link().session.info.links()
        )
    finally:
        net.close()


MANY_AT_ONCE = 600
"""Sessions opened together through a router (Zenoh's default let in some 400-480 of them)."""
MANY = 1_100
"""Sessions opened through a router in all (Zenoh's default stopped at 1,000)."""


def _open_sessions(endpoint: str, count: int) -> list[zenoh.Session | Exception]:
    """`count` client sessions (a manager process's config) opened at once, by as many
    threads released together."""
    go = threading.Barrier(count)

    def one() -> zenoh.Session | Exception:
        go.wait()
        try:
            return zenoh.open(session_config("client", [], [endpoint], 1.0))
        except Exception as exc:  # (counted: Zenoh raises its own ZError)
            return exc

    with ThreadPoolExecutor(count) as pool:
        return [f.result() for f in [pool.submit(one) for _ in range(count)]]


@pytest.fixture
def files_for_many() -> Iterator[None]:
    """This process may open the files of `MANY` sessions on both of their ends."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < 4 * MANY:
        pytest.skip(f"the open files' hard limit ({hard}) is below {4 * MANY}")
    resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    yield
    resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


@pytest.mark.timeout(300)
@pytest.mark.usefixtures("files_for_many")
def test_a_hosts_router_takes_600_manager_sessions_opening_at_once_and_over_a_thousand_in_all() -> (
    None
):
    """Each manager process of a host joins through its router with a session of its own:
    a tree of a thousand process managers, or 600 of them restarted together, must not be
    refused by the router's session limits (issue 69)."""
    net = rr.ZenohNetwork(system=f"t-{uuid.uuid4().hex[:8]}", listen=[], tls=None)
    opened: list[zenoh.Session] = []
    try:
        endpoint = f"unixsock-stream/{net.address.socket_path}"
        together = _open_sessions(endpoint, MANY_AT_ONCE)
        opened += [s for s in together if isinstance(s, zenoh.Session)]
        refused = [s for s in together if not isinstance(s, zenoh.Session)]
        assert (MANY_AT_ONCE, []) == (len(opened), refused[:1])
        for _ in range(MANY - MANY_AT_ONCE):
            opened.append(zenoh.open(session_config("client", [], [endpoint], 1.0)))

        assert MANY == len(opened)
        assert all(session.info.routers_zid() for session in opened[-3:])
    finally:
        for session in opened:
            session.close()  # type: ignore[no-untyped-call]
        net.close()


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
                member = open_router(operator, [f"tls/127.0.0.1:{port}"])
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


class TestAnotherLocalUser:
    """Another user of this machine and a router on loopback (issue 29, item 2).

    The AF_UNIX carrier lets only this user in (a 0700 runtime directory, a per-system key).
    A `ZenohNetwork` that listens on `tcp/127.0.0.1` lets in everyone on the machine:
    `test_plain_tcp_on_loopback_lets_another_local_user_run_code_here_as_the_warning_says`
    runs a process as user `nobody` that joins such a router and sends a pickle for its
    registrar, which is unpickled here (as this user, root), as the WARNING says.
    `test_with_tls_another_local_user_gets_nothing_unpickled` gives the same process the
    one-machine example of the how-to (`rr-actors certs` files, `tls/127.0.0.1`): it cannot
    read the host's key, and plain TCP to the port, TLS with a certificate of its own CA and
    the router's Unix socket are all refused before anything is unpickled.

    `nobody` must be able to run this Python: where it lives under a directory others
    cannot enter (root's home), the process runs in a mount namespace of its own in which
    that directory is an empty tmpfs holding only the interpreter's tree (`_as_nobody`).
    Everything else, the files of the system included, is as on the machine.
    """

    pytestmark = pytest.mark.skipif(
        os.geteuid() != 0 or not (shutil.which("unshare") and shutil.which("setpriv")),
        reason="runs a process as another user: needs root, unshare and setpriv",
    )

    @pytest.fixture
    def victim_setup(self) -> Iterator[None]:
        _PWNED.clear()
        _RAN_AS.clear()
        yield
        _PWNED.clear()

    def test_plain_tcp_on_loopback_lets_another_local_user_run_code_here_as_the_warning_says(
        self, victim_setup: None, caplog: pytest.LogCaptureFixture
    ) -> None:
        system, port = f"t-{uuid.uuid4().hex[:8]}", free_port()
        with caplog.at_level(logging.WARNING, logger="rr_actors"):
            net = rr.ZenohNetwork(system=system, listen=[f"tcp/127.0.0.1:{port}"], tls=None)
        erm = rr.ResourceRegistrar.start(rr.RegistrarConfig(name="erm"), network=net)
        try:
            attacker = _as_nobody(
                system, "erm", frame(7, _Payload()).hex(), "/nonexistent",
                json.dumps([["tcp", _client(f"tcp/127.0.0.1:{port}")]]),
            )  # fmt: skip
            pwned = _PWNED.wait(30)
            outcome = _outcome(attacker, stop=True)
        finally:
            erm.stop()
            net.close()

        assert (True, [0]) == (pwned, _RAN_AS)  # unpickled here, run as root
        assert (NOBODY, "sent") == (outcome["uid"], outcome["tcp"])
        assert any(
            "every user and process on this machine can connect and run code as this user, root"
            in message
            for message in caplog.messages
        )

    def test_with_tls_another_local_user_gets_nothing_unpickled(
        self, victim_setup: None, tmp_path: Path
    ) -> None:
        # the how-to's one-machine example: its certificates, its endpoint
        certs = tmp_path / "certs"
        certs_tool.init_ca(certs, "docs")
        certs_tool.issue_cert(certs, "laptop", ["127.0.0.1"])
        tls = rr.ZenohTLS(
            ca=certs / "ca.pem", cert=certs / "laptop.pem", key=certs / "laptop.key",
            members=["laptop"],
        )  # fmt: skip
        # what the other user has: the system's ca.pem (public) and a certificate of its own CA
        theirs = Path(tempfile.mkdtemp())
        try:
            shutil.copy(certs / "ca.pem", theirs / "system-ca.pem")
            own_ca = pki.make_ca(theirs / "own", system="docs")
            own_cert, own_key = pki.issue(theirs / "own", "laptop", ("127.0.0.1",), ca=own_ca)
            for path in [theirs, *theirs.rglob("*")]:
                os.chown(path, NOBODY, NOBODY)
            system, port = f"t-{uuid.uuid4().hex[:8]}", free_port()
            net = rr.ZenohNetwork(system=system, listen=[f"tls/127.0.0.1:{port}"], tls=tls)
            erm = rr.ResourceRegistrar.start(rr.RegistrarConfig(name="erm"), network=net)
            try:
                attempts = [
                    ["tcp", _client(f"tcp/127.0.0.1:{port}")],
                    [
                        "tls",
                        _client(
                            f"tls/127.0.0.1:{port}",
                            {
                                "root_ca_certificate": str(theirs / "system-ca.pem"),
                                "connect_certificate": str(own_cert),
                                "connect_private_key": str(own_key),
                                "enable_mtls": True,
                            },
                        ),
                    ],
                    ["unix", _client(f"unixsock-stream/{net.address.socket_path}")],
                ]
                attacker = _as_nobody(
                    system, "erm", frame(7, _Payload()).hex(), str(certs / "laptop.key"),
                    json.dumps(attempts),
                )  # fmt: skip
                outcome = _outcome(attacker)
            finally:
                erm.stop()
                net.close()
        finally:
            shutil.rmtree(theirs)

        assert {
            "uid": NOBODY,
            "key": "PermissionError",
            "tcp": "refused",
            "tls": "refused",
            "unix": "refused",
        } == outcome
        assert not _PWNED.is_set()
