"""The AF_UNIX carrier: authenticated channels between the registrars of one machine.

A *system* is a private runtime directory (mode 0700) plus a random authkey. Every process
that takes part `attach`es it; each registrar it
`serve`s listens on
`<runtime_dir>/<registrar>.sock` (AF_UNIX) and holds an exclusive `flock` on
`<runtime_dir>/<registrar>.lock` for as long as it listens, so one name has one owner.
Another process reaches that registrar through a
`RemotePeer` (`outbound.py`), which the directory resolver hands out
for names that are not registered locally, so the registrar code sends a `Load` the same
way whether its target lives in this process or another one.

Each listener also publishes its registrar's `max_message_bytes` in
`<runtime_dir>/<registrar>.limit`, so that a sender refuses a message that is too large
before it sends anything of it (the listener refuses such a frame unread, too), and who
speaks for it if its process dies in `<runtime_dir>/<registrar>.restart` (rule 19: a
registrar gone that nobody restarts is *lost*; how a process finds out, and the limits,
are in `rr_actors._transport.base`).

Wire format: one frame per message (`multiprocessing.connection` framing), `8-byte token
(little endian) + cloudpickle payload`. A message's `reply` never crosses: the sender keeps
it in a table under the token (0: no answer wanted) and the receiver substitutes a reply
that sends `token + pickle((value, error))` back over the same connection. Nothing is
unpickled from a connection before it passed the authkey handshake
(`multiprocessing.connection.deliver_challenge` / `answer_challenge`, run on a thread of
the connection, bounded by a timeout).

Sending never blocks on the other process: a sender writes a frame itself only when the
socket takes it at once, otherwise it queues the frame for the connection's writer thread
(frames of one connection leave in the order they were sent). A frozen peer therefore
stalls only its own writer thread; callers still time out on their own timeouts.

Failure: when a connection ends (the peer process died or its registrar stopped), every
answer still outstanding on it fails at once with `RegistrarUnavailableError` (or
`RegistrarStoppedError` if the registrar was stopped cleanly); the next message connects
again, so a restarted registrar that binds the same path is reached. Low-level errors
(`EOFError`, `BrokenPipeError`, `ConnectionResetError`, `OSError`, pickling errors) are
translated into rr_actors errors with `raise ... from exc` and never reach a caller.

Fork: a child forked from a process that joined a system is a member of it too (same
runtime directory, same authkey), but none of the parent's listeners, connections or
threads are its own. At the fork (`rr_actors._platform.fork`) each attached system drops
them in the child: the child's copies of their descriptors are closed (never shut down,
which would end them for the parent; the name locks' descriptors too, which would
otherwise keep the parent's names locked after the parent died). The child then serves
its own registrars and connects anew; and only the process that created a `System`
removes its files at `close()`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import logging
import os
import tempfile
import threading
import time
from collections.abc import Callable
from typing import Any

from rr_actors._core.directory import DIRECTORY, Peer
from rr_actors._core.membership import MEMBERSHIP
from rr_actors._platform import PLATFORM, fork
from rr_actors._transport.base import Endpoint
from rr_actors._transport.messenger import tell_lost
from rr_actors._transport.unix.inbound import Listener
from rr_actors._transport.unix.outbound import RemotePeer
from rr_actors.errors import (
    ConfigError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    UnknownServerError,
    _known_names,
)

__all__ = ["AttachedSystem", "System", "SystemAddress", "attach"]

logger = logging.getLogger("rr_actors")

_MAX_SOCKET_PATH = 107  # sun_path is 108 bytes with the terminating NUL (Linux)
_RUNTIME_SUFFIXES = (".sock", ".stopped", ".lock", ".limit", ".restart")  # a system's files

ENDING_GRACE = 0.5
"""Seconds a registrar whose connection ended may still hold its lock (its process is
still exiting) before the process that holds it counts as serving it."""

AWAIT_POLL = 0.1
"""Seconds between two looks at a registrar awaited (gone, its speaker alive): served
again, stopped, or its speaker gone too (then it is lost)."""

NOBODY = "0"
"""What a `.restart` file holds when nobody speaks for the registrar: it is lost when
its process dies."""


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
        """The path registrar `name` listens on."""
        return os.path.join(self.runtime_dir, f"{name}.sock")

    def tombstone_path(self, name: str) -> str:
        """A file that says registrar `name` was stopped cleanly (not crashed)."""
        return os.path.join(self.runtime_dir, f"{name}.stopped")

    def lock_path(self, name: str) -> str:
        """The file whose `flock` the process serving registrar `name` holds."""
        return os.path.join(self.runtime_dir, f"{name}.lock")

    def limit_path(self, name: str) -> str:
        """A file that holds registrar `name`'s `max_message_bytes` (decimal), for senders."""
        return os.path.join(self.runtime_dir, f"{name}.limit")

    def restart_path(self, name: str) -> str:
        """A file that says who speaks for registrar `name` if its process dies: `0` for
        nobody, else `<pid> <start time>` of that process (rule 19)."""
        return os.path.join(self.runtime_dir, f"{name}.restart")

    def attach(self) -> AttachedSystem:
        """Join this system from the calling process (see `attach`)."""
        return attach(self)


class AttachedSystem:
    """This process's membership of a system: the resolver, the peers and the listeners.

    Get one with [`attach`][rr_actors._transport.attach] (or `System.create`, which
    attaches the creating process).
    """

    def __init__(self, address: SystemAddress) -> None:
        self.address = address
        self.closed = False
        self._lock = threading.Lock()
        self._peers: dict[str, RemotePeer] = {}
        self._listeners: dict[str, Listener] = {}
        self._speaker: str | None = None  # who restarts what this process serves
        # rule 19: registrars of other processes whose end is being judged
        self._presence = threading.Condition()
        self._judging: dict[str, float] = {}  # name -> end of its ENDING_GRACE
        self._awaited: set[str] = set()  # gone, their speaker alive
        self._lost: set[str] = set()  # reported lost (until served again)
        self._judge_thread: threading.Thread | None = None
        DIRECTORY.add_resolver(self.resolve, self.names)

    def serve(self, endpoint: Endpoint) -> None:
        """Make a registrar of this process reachable from the other processes of the system.

        Listening stops by itself when the registrar stops or dies. Serving a name again
        (a registrar restarted in this process) replaces the old listener.

        Args:
            registrar: a running registrar of this process.

        Raises:
            DuplicateNameError: a living process of the system already serves that name
                (it holds the `flock` on `<runtime_dir>/<name>.lock`).
            ConfigError: the socket path is too long or cannot be bound, or the lock
                file cannot be opened.
            RegistrarStoppedError: the system was closed.
        """
        name = endpoint.name
        path = self.address.socket_path(name)
        if len(os.fsencode(path)) > _MAX_SOCKET_PATH:
            raise ConfigError(
                f"socket path {path!r} for registrar {name!r} is longer than "
                f"{_MAX_SOCKET_PATH} bytes; use a shorter runtime_dir or name"
            )
        with self._lock:
            if self.closed:
                raise RegistrarStoppedError("the system was closed")
            old = self._listeners.pop(name, None)
            peer = self._peers.pop(name, None)
        if old is not None:
            old.close(stopped=False)
        if peer is not None:
            peer.close(RegistrarUnavailableError(f"registrar {name!r} moved into this process"))
        listener = Listener(self, endpoint)
        with self._lock:
            self._listeners[name] = listener
        threading.Thread(
            target=self._watch, args=(endpoint, listener), name=f"rr-watch-{name}", daemon=True
        ).start()
        endpoint.listening()  # (it listens: Listener binds in its constructor)

    def run(self, registrar_name: str, fn: Callable[[Any], Any], *, timeout: float) -> Any:
        """Run `fn(registrar)` where registrar `registrar_name` lives and return the result.

        For a registrar served by this process, `fn` runs in the calling thread;
        otherwise see [`RemotePeer.run`][rr_actors._transport.RemotePeer.run].

        Raises:
            UnknownServerError: no registrar of that name is served on the system.
            CallTimeoutError: no result within `timeout` seconds.
            RegistrarUnavailableError: its process died or cannot be reached.
            RegistrarStoppedError: it was stopped.
        """
        with self._lock:
            listener = self._listeners.get(registrar_name)
        if listener is not None:
            return listener.endpoint.run(fn)
        peer = self.resolve(registrar_name)
        if peer is None:
            raise UnknownServerError(
                f"no registrar named {registrar_name!r} on this system"
                + _known_names(registrar_name, self.names())
            )
        assert isinstance(peer, RemotePeer)
        return peer.run(fn, timeout=timeout)

    def supervised_by(self, pid: int | None) -> None:
        """Say that process `pid` speaks for the registrars this process serves from now
        on when this process dies: it restarts them, or sends their death watch (a manager
        process's supervisor, or the owner of a `RemoteRegistrar`); `None`: nobody.

        Published in each one's `.restart` file: while that process lives, the others do
        not count them lost (rule 19); once it is gone too, they do.
        """
        self._speaker = None if pid is None else _identity(pid)

    def supervisor(self, name: str) -> str:
        """What registrar `name`, served here, publishes in its `.restart` file: the
        speaker set by `supervised_by`, else this process while
        `DIRECTORY.restart_expected(name)` (a thread manager), else `0` (nobody)."""
        if self._speaker is not None:
            return self._speaker
        if DIRECTORY.restart_expected(name):
            return _identity(os.getpid())
        return NOBODY

    def peer_ended(self, name: str) -> None:
        """The connection to registrar `name` ended, or a connect to it failed: judge, on
        the system's presence thread, whether it is lost (rule 19)."""
        with self._presence:
            if self.closed:
                return
            self._judging.setdefault(name, time.monotonic() + ENDING_GRACE)
            if self._judge_thread is None:
                self._judge_thread = threading.Thread(
                    target=self._judge_loop, name="rr-unix-presence", daemon=True
                )
                self._judge_thread.start()
            self._presence.notify_all()

    def serving_trouble(self, name: str) -> tuple[float, str] | None:
        """For how long (seconds) and why registrar `name` has been unable to take new
        connections here; `None` if it can (or this process does not serve it).

        A manager process reports it with each heartbeat answer, so its supervisor can
        restart a manager that stays unable to accept (out of file descriptors, say).
        """
        listener = self._listeners.get(name)
        return None if listener is None else listener.trouble()

    def close(self) -> None:
        """Leave the system: stop listening, close every connection (idempotent).

        Answers still outstanding fail with `RegistrarStoppedError`. Registrars are not
        stopped; stop them first.
        """
        with self._lock:
            if self.closed:
                return
            self.closed = True
            listeners = list(self._listeners.values())
            peers = list(self._peers.values())
            self._listeners.clear()
            self._peers.clear()
        DIRECTORY.remove_resolver(self.resolve)
        with self._presence:
            self._presence.notify_all()  # the presence thread ends
        for listener in listeners:
            listener.close(stopped=listener.endpoint.stopped_cleanly())
        for peer in peers:
            peer.close(RegistrarStoppedError("this process closed its system"))
        with _ATTACHED_LOCK:
            if _ATTACHED.get(self.address.runtime_dir) is self:
                del _ATTACHED[self.address.runtime_dir]

    def forget_in_child(self) -> None:
        """In a forked child: drop the parent's listeners, connections and presence
        thread; stay attached (see the module's "Fork"). Takes no lock: makes them new."""
        self._lock = threading.Lock()
        self._presence = threading.Condition()
        listeners, peers = list(self._listeners.values()), list(self._peers.values())
        self._listeners.clear()
        self._peers.clear()
        self._judging.clear()
        self._awaited.clear()
        self._lost.clear()
        self._judge_thread = None
        self._speaker = None  # whoever restarts the parent's registrars knows not the child's
        for listener in listeners:
            listener.forget_in_child()
        for peer in peers:
            peer.forget_in_child()

    def __enter__(self) -> AttachedSystem:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    # -- plumbing ------------------------------------------------------------------------

    def resolve(self, name: str) -> Peer | None:
        """The directory resolver: a peer for a registrar of another process, or None."""
        peer = self._peers.get(name)
        if peer is not None:
            return peer
        if self.closed or name in self._listeners:
            return None  # served here: the directory's own record says stopped or died
        if not (
            os.path.exists(self.address.socket_path(name))
            or os.path.exists(self.address.tombstone_path(name))
        ):
            return None
        with self._lock:
            return self._peers.setdefault(name, RemotePeer(self, name))

    def names(self) -> list[str]:
        """The names of the registrars that listen in the system now (any process)."""
        if self.closed:
            return []
        try:
            entries = os.listdir(self.address.runtime_dir)
        except OSError:
            return []
        return [e.removesuffix(".sock") for e in entries if e.endswith(".sock")]

    # -- rule 19: is a registrar of another process lost? --------------------------------

    def _judge_loop(self) -> None:
        """The presence thread: judges ended registrars and polls the awaited ones."""
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
        """`served` (here, or by a process that holds its lock), `stopped`, `lost`,
        `awaited` (its speaker lives), `ours` (this process speaks for it) or `unknown`
        (it published no `.restart` file)."""
        address = self.address
        if name in self._listeners:
            return "served"
        if os.path.exists(address.tombstone_path(name)):
            return "stopped"
        if _lock_held(address.lock_path(name)):
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
            peer = self._peers.get(name)
            if awaited and peer is not None and any(n != name for n in self._listeners):
                peer.connect()  # restarted: connect now, so that its next end is seen too
        elif verdict == "awaited":
            with self._presence:
                self._awaited.add(name)
        elif verdict == "lost" and name not in self._lost:
            self._lost.add(name)
            self._lose(name)

    def _lose(self, name: str) -> None:
        """Registrar `name` is gone for good: every endpoint served here hears it."""
        listeners = list(self._listeners.values())
        tell_lost([listener.endpoint for listener in listeners], name, self.address.runtime_dir)

    def _watch(self, endpoint: Endpoint, listener: Listener) -> None:
        endpoint.wait_ended()  # the carrier watches the registrar's end
        # Close before letting go: while it is still listed, the system's own close()
        # finds it and waits for this close to finish (a process may exit right after).
        listener.close(stopped=endpoint.stopped_cleanly())
        with self._lock:
            if self._listeners.get(listener.name) is listener:
                del self._listeners[listener.name]


def _identity(pid: int) -> str:
    """`<pid> <start time>` of process `pid` (just the pid where `/proc` does not say)."""
    start = _start_time(pid)
    return f"{pid} {start}" if start else f"{pid}"


def _start_time(pid: int) -> str | None:
    """Process `pid`'s start time (Linux `/proc/<pid>/stat`, field 22); `None` if unknown
    (no `/proc`) or it is not running (gone, or a zombie: it speaks for nobody)."""
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


def _lock_held(path: str) -> bool:
    """Whether a process holds the name lock at `path` (a listener serves the name).

    Probes with a shared `flock` held for microseconds; a listener taking the lock meanwhile
    retries (`inbound.LOCK_RETRY`). When it cannot tell, it says held (never a false loss).
    """
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return False
    except OSError:
        return True
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)  # (closing releases the probe's lock)
    return False


_ATTACHED: dict[str, AttachedSystem] = {}
_ATTACHED_LOCK = threading.Lock()


def _forget_in_child() -> None:
    global _ATTACHED_LOCK  # a thread of the parent may have held it at the fork
    _ATTACHED_LOCK = threading.Lock()
    for attached in list(_ATTACHED.values()):
        attached.forget_in_child()


fork.after_fork_in_child("the AF_UNIX carrier", _forget_in_child)


def attach(address: SystemAddress) -> AttachedSystem:
    """Join the system at `address` from this process (idempotent per process).

    Installs the directory resolver, so registrars of this process reach the system's
    registrars in other processes by name.

    Returns:
        This process's `AttachedSystem` for that address (the same one if already attached).
    """
    with _ATTACHED_LOCK:
        attached = _ATTACHED.get(address.runtime_dir)
        if attached is None or attached.closed:
            attached = AttachedSystem(address)
            _ATTACHED[address.runtime_dir] = attached
        return attached


class System(AttachedSystem):
    """A system of registrars across processes, as its owner (the main process) holds it.

    It is an `AttachedSystem` of the creating process; `close()` also removes the files the
    system put in the runtime directory, and the directory itself if `create` made it (in
    the creating process only: in a child forked from it, `close()` just leaves).
    Hand `address` to the processes that should join.
    """

    _made_dir = False
    _owner = 0  # the pid of the process that created it

    @classmethod
    def create(cls, runtime_dir: str | None = None) -> System:
        """Create the private runtime directory and a random authkey, and attach.

        Args:
            runtime_dir: directory to use (created with mode 0700 if missing; an existing
                one must belong to this user and is made 0700, and `close()` leaves it and
                whatever else it holds in place); default: a fresh directory in a memory-backed
                one where the platform has it (`$XDG_RUNTIME_DIR`, `/dev/shm`, unless
                `TMPDIR` is set), else in the temporary directory.

        Raises:
            ConfigError: `runtime_dir` cannot be used.
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
        """Leave the system and remove its files (idempotent).

        Removes the sockets, tombstones and lock files of the runtime directory, then the
        directory itself if `create` made it and nothing else is left in it. In a child
        forked from the creating process it only leaves the system (as `AttachedSystem`).
        """
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
