"""The AF_UNIX carrier: a system of registrars on one machine, met in a runtime directory.

Its files say who serves what and who is lost for good (rule 19): see
docs/explanation/inside.md ("The AF_UNIX carrier").
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import tempfile
import threading
import time

from rr_actors._core.directory import DIRECTORY
from rr_actors._core.membership import MEMBERSHIP
from rr_actors._platform import PLATFORM, forkserver
from rr_actors._transport.messenger import Endpoint, Listening, Lost, Messenger, Route
from rr_actors._transport.resolve import Sided
from rr_actors._transport.unix.link import Dial, Listener, _Accepted, _Channel, lock_held
from rr_actors.errors import ConfigError, RegistrarStoppedError, RegistrarUnavailableError, RrError

logger = logging.getLogger("rr_actors")

_MAX_SOCKET_PATH = 107  # sun_path is 108 bytes with the terminating NUL (Linux)
_RUNTIME_SUFFIXES = (".sock", ".stopped", ".lock", ".limit", ".restart")  # a system's files

ENDING_GRACE = 0.5
"""Seconds a registrar whose connection ended may hold its lock (its process exiting)
before the lock's holder counts as serving it."""

AWAIT_POLL = 0.1
"""Seconds between two looks at a registrar gone whose speaker lives."""

NOBODY = "0"
"""A `.restart` file's "nobody speaks for it": it is lost when its process dies."""


@dataclasses.dataclass(frozen=True)
class SystemAddress:
    """How a process joins a system: pass it (it pickles) to the processes you start.

    Attributes:
        runtime_dir: the private directory that holds the registrars' sockets.
        authkey: the system's secret; a connection that cannot prove it is refused.
    """

    runtime_dir: str
    authkey: bytes = dataclasses.field(repr=False)

    def socket_path(self, name: str) -> str:
        return os.path.join(self.runtime_dir, f"{name}.sock")

    def tombstone_path(self, name: str) -> str:
        """Says registrar `name` was stopped cleanly (not crashed)."""
        return os.path.join(self.runtime_dir, f"{name}.stopped")

    def lock_path(self, name: str) -> str:
        """Its `flock` is held by the process serving registrar `name`."""
        return os.path.join(self.runtime_dir, f"{name}.lock")

    def limit_path(self, name: str) -> str:
        """Holds registrar `name`'s `max_message_bytes` (decimal), for senders."""
        return os.path.join(self.runtime_dir, f"{name}.limit")

    def restart_path(self, name: str) -> str:
        """Who speaks for `name` if its process dies: `0`, or `<pid> <start time>`."""
        return os.path.join(self.runtime_dir, f"{name}.restart")

    def attach(self) -> AttachedSystem:
        """Join this system from the calling process (see `attach`)."""
        return attach(self)


class UnixCarrier:
    """The AF_UNIX `Carrier`: inside.md ("Judging who is lost on one machine")."""

    def __init__(self, messenger: Messenger, address: SystemAddress) -> None:
        self.messenger = messenger
        self.address = address
        self._presence = threading.Condition()
        self._judging: dict[str, float] = {}  # name -> end of its ENDING_GRACE
        self._awaited: set[str] = set()  # gone, their speaker alive
        self._lost: set[str] = set()  # reported lost (until served again)
        self._judge_thread: threading.Thread | None = None
        self._dials: dict[str, Dial] = {}  # name -> its connection (`route`)

    @property
    def closed(self) -> bool:
        return self.messenger.closed

    def knows(self, name: str) -> bool:
        """Whether registrar `name` listens in the directory, or was stopped."""
        address = self.address
        return os.path.exists(address.socket_path(name)) or os.path.exists(
            address.tombstone_path(name)
        )

    def route(self, name: str, server: Sided | None = None) -> _Channel:
        """Its connection (made now, connected on its writer thread); a name's socket is
        its one server, so none other (`server`, rule 22's) is reached."""
        if server is not None:
            raise RegistrarUnavailableError(f"no second server of {name!r} is seen here")
        dial = self._dials.get(name)
        if dial is None:
            with self._presence:
                dial = self._dials.setdefault(name, Dial(self, name))
        return dial.route()

    def send(self, route: Route, data: bytes) -> None:
        assert isinstance(route, _Channel)
        assert route.dial is not None
        route.dial.send(route, data)

    def serve(self, endpoint: Endpoint) -> Listener:
        """Listen on `<runtime_dir>/<name>.sock`, holding `<name>.lock`."""
        name = endpoint.name
        self._drop(name, RegistrarUnavailableError(f"registrar {name!r} moved into this process"))
        path = self.address.socket_path(endpoint.name)
        if len(os.fsencode(path)) > _MAX_SOCKET_PATH:
            raise ConfigError(
                f"socket path {path!r} for registrar {endpoint.name!r} is longer than "
                f"{_MAX_SOCKET_PATH} bytes; use a shorter runtime_dir or name"
            )
        return Listener(self, endpoint)

    def unserve(self, listening: Listening, *, stopped: bool) -> None:
        assert isinstance(listening, Listener)
        listening.stop(stopped=stopped)

    def answer(self, process: _Accepted, data: bytes, on_lost: Lost | None) -> bool:
        return process.send(data, on_lost)

    def names(self) -> list[str]:
        try:
            entries = os.listdir(self.address.runtime_dir)
        except OSError:
            return []
        return [e.removesuffix(".sock") for e in entries if e.endswith(".sock")]

    def leave(self) -> None:
        self._drop(
            None, RegistrarStoppedError(f"this process left system {self.messenger.system!r}")
        )
        with self._presence:
            self._presence.notify_all()  # the presence thread ends
        with _ATTACHED_LOCK:
            if _ATTACHED.get(self.address.runtime_dir) is self.messenger:
                del _ATTACHED[self.address.runtime_dir]

    def speaker(self, name: str) -> str:
        """The `.restart` file of `name`: `supervised_by`'s, else this one, else nobody."""
        supervisor = self.messenger.supervisor
        if supervisor is not None:
            return _identity(supervisor)
        if DIRECTORY.restart_expected(name):
            return _identity(os.getpid())
        return NOBODY

    def ended(self, name: str) -> None:
        with self._presence:
            if self.closed:
                return
            self._judging.setdefault(name, time.monotonic() + ENDING_GRACE)
            if self._judge_thread is None:
                judge = threading.Thread(
                    target=self._judge_loop, name="rr-unix-presence", daemon=True
                )
                judge.start()  # (RuntimeError, no thread: the next end tries again)
                self._judge_thread = judge
            self._presence.notify_all()

    def _drop(self, name: str | None, error: RrError) -> None:
        """Close the connection to `name` (`None`: every one); what waits fails with `error`."""
        with self._presence:
            if name is None:
                dials, self._dials = list(self._dials.values()), {}
            else:
                dials = [self._dials.pop(name)] if name in self._dials else []
        for dial in dials:
            dial.close(error)

    def forget_in_child(self) -> None:
        for dial in self._dials.values():
            dial.forget_in_child()
        self._dials = {}
        self._presence = threading.Condition()
        self._judging.clear()
        self._awaited.clear()
        self._lost.clear()
        self._judge_thread = None

    def _judge_loop(self) -> None:
        """The presence thread: judge ended registrars, poll the awaited ones."""
        while True:
            with self._presence:
                if self.closed:
                    return
                judging = dict(self._judging)
                awaited = set(self._awaited)
            for name, grace_until in judging.items():
                verdict = self._verdict(name)
                if verdict == "served" and time.monotonic() < grace_until:
                    continue  # its process may still be exiting: look again soon
                with self._presence:
                    if self._judging.get(name) == grace_until:
                        del self._judging[name]
                self._act(name, verdict, awaited=False)
            for name in awaited - set(judging):
                verdict = self._verdict(name)
                if verdict != "awaited":
                    with self._presence:
                        self._awaited.discard(name)
                    self._act(name, verdict, awaited=True)
            with self._presence:
                if self.closed:
                    return
                if self._judging:
                    self._presence.wait(0.01)
                elif self._awaited:
                    self._presence.wait(AWAIT_POLL)
                else:
                    self._presence.wait()

    def _verdict(self, name: str) -> str:
        """`served`, `stopped`, `lost`, `awaited`, `ours` or `unknown` (no `.restart`)."""
        address = self.address
        if self.messenger.serving(name) is not None:
            return "served"
        if os.path.exists(address.tombstone_path(name)):
            return "stopped"
        if lock_held(address.lock_path(name)):
            return "served"
        try:
            with open(address.restart_path(name), encoding="ascii") as published:
                speaker = published.read(64).strip()
        except (OSError, ValueError):
            return "unknown"
        return _verdict_of(speaker)

    def _act(self, name: str, verdict: str, *, awaited: bool) -> None:
        if verdict == "served":
            self._lost.discard(name)
            MEMBERSHIP.back(name)  # served (again): no longer gone for good
            if (
                awaited
                and self.messenger.peer(name) is not None
                and any(n != name for n in self.messenger.served())
            ):
                with contextlib.suppress(RrError):  # restarted: connect now, so that
                    self.route(name)  # its next end is seen too
        elif verdict == "awaited":
            with self._presence:
                self._awaited.add(name)
        elif verdict == "lost" and name not in self._lost:
            self._lost.add(name)
            self.messenger.lost(name)


def _identity(pid: int) -> str:
    """`<pid> <start time>` of process `pid` (the pid alone where `/proc` does not say)."""
    start = _start_time(pid)
    return f"{pid} {start}" if start else f"{pid}"


def _start_time(pid: int) -> str | None:
    """Process `pid`'s start time; `None` if unknown, `""` for a zombie."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as stat:
            fields = stat.read().rsplit(b")", 1)[1].split()
    except (OSError, IndexError):
        return None
    if fields[0] in (b"Z", b"X"):
        return ""
    return fields[19].decode("ascii")


def _speaks(speaker: str) -> bool:
    """Whether the process a `.restart` file names (`<pid> [<start time>]`) still runs."""
    parts = speaker.split()
    try:
        pid = int(parts[0])
    except (IndexError, ValueError):
        return False  # a malformed file: nobody
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # it exists (another user's: a reused pid, most likely)
    start = _start_time(pid)
    if start == "":
        return False  # a zombie
    return start is None or len(parts) < 2 or start == parts[1]


def _verdict_of(speaker: str) -> str:
    """What a `.restart` file's `speaker` makes of a registrar gone from a free lock."""
    if speaker.split()[:1] == [str(os.getpid())]:
        return "ours"  # this process restarts it, or sends its death watch
    if speaker == NOBODY or not _speaks(speaker):
        return "lost"
    return "awaited"


class AttachedSystem(Messenger):
    """This process's messenger over the AF_UNIX carrier (`attach`, `System.create`)."""

    def __init__(self, address: SystemAddress) -> None:
        super().__init__(address.runtime_dir)
        self._address = address
        self._unix = UnixCarrier(self, address)
        self.joined(self._unix)

    @property
    def address(self) -> SystemAddress:
        return self._address

    def forget_in_child(self) -> list[Listening]:
        """In a forked child: drop the parent's listeners, connections, presence thread."""
        served = super().forget_in_child()
        for listening in served:
            assert isinstance(listening, Listener)
            listening.forget_in_child()
        self._unix.forget_in_child()
        return served

    def __enter__(self) -> AttachedSystem:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


_ATTACHED: dict[str, AttachedSystem] = {}
_ATTACHED_LOCK = threading.Lock()


def _forget_in_child() -> None:
    global _ATTACHED_LOCK  # a thread of the parent may have held it at the fork
    _ATTACHED_LOCK = threading.Lock()
    for attached in list(_ATTACHED.values()):
        attached.forget_in_child()


forkserver.after_fork_in_child("the AF_UNIX carrier", _forget_in_child)


def attach(address: SystemAddress) -> AttachedSystem:
    """Join the system at `address` from this process (idempotent)."""
    with _ATTACHED_LOCK:
        attached = _ATTACHED.get(address.runtime_dir)
        if attached is None or attached.closed:
            attached = AttachedSystem(address)
            _ATTACHED[address.runtime_dir] = attached
        return attached


class System(AttachedSystem):
    """A system of registrars across processes, as its owner holds it; hand `address` on."""

    _made_dir = False
    _owner = 0  # the pid of the process that created it

    @classmethod
    def create(cls, runtime_dir: str | None = None) -> System:
        """Create the private runtime directory (0700) and a random authkey, and attach.

        `runtime_dir` given is kept on `close()`; default: a fresh one in memory-backed
        storage where there is one. Raises `ConfigError` if it cannot be used.
        """
        if runtime_dir is None:
            runtime_dir = tempfile.mkdtemp(prefix="rr-", dir=PLATFORM.runtime_parent())  # 0700
            made = True
        else:
            try:
                made = not os.path.isdir(runtime_dir)
                os.makedirs(runtime_dir, mode=0o700, exist_ok=True)
                if os.stat(runtime_dir).st_uid != os.getuid():
                    raise ConfigError(f"runtime_dir {runtime_dir!r} belongs to another user")
                os.chmod(runtime_dir, 0o700)
            except OSError as exc:
                raise ConfigError(f"runtime_dir {runtime_dir!r} cannot be used: {exc}") from exc
        address = SystemAddress(os.path.abspath(runtime_dir), os.urandom(32))
        with _ATTACHED_LOCK:
            system = cls(address)
            system._made_dir = made
            system._owner = os.getpid()
            _ATTACHED[address.runtime_dir] = system
        return system

    def close(self) -> None:
        """Leave and remove its files, and the directory if `create` made it (idempotent)."""
        super().close()
        if self._owner != os.getpid():
            return  # a forked child's copy: the files are its parent's system's
        directory = self.address.runtime_dir
        with contextlib.suppress(OSError):
            for entry in os.listdir(directory):
                if entry.endswith(_RUNTIME_SUFFIXES):
                    with contextlib.suppress(OSError):
                        os.unlink(os.path.join(directory, entry))
        if self._made_dir:
            try:
                os.rmdir(directory)
            except FileNotFoundError:
                pass
            except OSError as exc:
                logger.debug("runtime directory %s kept: %s", directory, exc)
