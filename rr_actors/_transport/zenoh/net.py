"""`ZenohNetwork`: a system of registrars across hosts, over Eclipse Zenoh.

A router per host (the process that makes it), its manager processes joined through its
Unix socket (`ZenohMember`). How and why: docs/explanation/inside.md ("A Zenoh network").
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.metadata
import logging
import math
import os
import pickle
import shutil
import socket
import tempfile
import threading
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

import zenoh

from rr_actors import events
from rr_actors._core import wire
from rr_actors._core.bus import DEFAULT_MAXSIZE, Subscription
from rr_actors._core.exit import NETWORKS, stop_at_exit
from rr_actors._core.hlc import CLOCK, MAX_OFFSET, check_max_offset
from rr_actors._platform import forkserver
from rr_actors._transport.messenger import Address, Messenger, Transport
from rr_actors._transport.resolve import Resolve
from rr_actors._transport.zenoh.carrier import ZenohCarrier
from rr_actors._transport.zenoh.ops.config import (
    endpoints,
    session_config,
    warn_plain_tcp,
    warn_unreachable,
)
from rr_actors._transport.zenoh.ops.gate import HandshakeGate, MemberAddresses, open_gates
from rr_actors._transport.zenoh.wire import Keys
from rr_actors.config import check_name
from rr_actors.errors import ConfigError, RegistrarStoppedError, RegistrarUnavailableError
from rr_actors.events.kinds import set_host

if TYPE_CHECKING:
    from rr_actors._transport.zenoh.ops.tls import ZenohTLS

logger = logging.getLogger("rr_actors")


def _zenoh_log_from_env() -> None:
    """Zenoh's own log on standard output when `RUST_LOG` asks for it."""
    if os.environ.get("RUST_LOG"):
        zenoh.try_init_log_from_env()  # type: ignore[no-untyped-call]


def _member_count(tls: ZenohTLS | None) -> int:
    """How many members `tls` names (itself included); 0 without TLS."""
    return 0 if tls is None else len({*tls.members, tls.name})


def _is_tls(tls: object) -> bool:
    try:
        from rr_actors._transport.zenoh.ops.tls import ZenohTLS  # noqa: PLC0415 - cryptography
    except ImportError:  # without cryptography nobody could have made a ZenohTLS
        return False
    return isinstance(tls, ZenohTLS)


# -- what runs beside a session, attached from above ----------------------------------------


class MemberLink(NamedTuple):
    """A member's link to this router as last seen (`Beside.member_links`)."""

    member: str  # its certificate's common name
    up: bool
    since: float  # when it became so (`time.time()` seconds)
    where: str  # its address, as last linked
    why: str  # why there is no link (`""` while up)


@dataclasses.dataclass(frozen=True)
class Opened:
    """A process's opened session, as `Beside` gets it (`connect`: `None` if attached)."""

    system: str
    session: zenoh.Session
    keys: Keys
    tls: ZenohTLS | None
    connect: tuple[str, ...] | None


class Beside(Protocol):
    """What runs beside a process's Zenoh session (an installed package's, `BESIDE_GROUP`,
    attached from above by `attach_beside`): made as the session opens, closed before."""

    def subscribe_events(
        self, callback: Callable[[events.Event], object], window: float, maxsize: int
    ) -> Subscription[events.Event]: ...  # `ZenohNetwork.subscribe_events`, checked
    def unlinked(self) -> list[tuple[str, str]]: ...  # connect endpoints with no link, why
    def member_links(self) -> list[MemberLink]: ...
    def close(self) -> None: ...  # (idempotent: before the session closes)


_BESIDE: list[Callable[[Opened], Beside]] = []  # the maker of what runs beside (one slot)


def attach_beside(make: Callable[[Opened], Beside]) -> None:
    """Run `make(opened)` beside every session opened from now on (the last call wins)."""
    _BESIDE[:] = [make]


BESIDE_GROUP = "rr_actors.zenoh"
"""The entry-point group of what runs beside a session: an installed package offers one by
naming a module there that attaches it as it is imported (`attach_beside`; the lab's
event feed across hosts, in this project's pyproject.toml). The runtime names no tool."""


def _beside() -> Callable[[Opened], Beside] | None:
    """What runs beside a session opened now: the one attached, else the one an installed
    package offers (`BESIDE_GROUP`; one whose imports are missing offers none), else `None`."""
    if not _BESIDE:
        for point in importlib.metadata.entry_points(group=BESIDE_GROUP):
            try:
                point.load()
            except ImportError as exc:  # (an extra not installed)
                logger.debug("%s %s offers nothing beside a session: %s", BESIDE_GROUP, point, exc)
    return _BESIDE[0] if _BESIDE else None


def _check_window(window: object) -> float:
    if isinstance(window, bool) or not isinstance(window, int | float) or not 0 <= window <= 60:
        raise ConfigError(f"window must be seconds from 0 to 60, not {window!r}")
    return float(window)


# -- one system per process ----------------------------------------------------------------------

_MEMBER: ZenohMember | ZenohNetwork | None = None
_MEMBER_OWNER: object = None
_MEMBER_LOCK = threading.Lock()
_OPENED: list[str] = []  # the systems this process opened a Zenoh session for


def _refuse_in_child() -> None:
    if _OPENED:
        forkserver.refuse(
            f"had opened a Zenoh session (system {_OPENED[0]!r}), whose runtime threads "
            f"do not exist in a forked child"
        )


forkserver.after_fork_in_child("the Zenoh carrier", _refuse_in_child)


def _join(
    system: str, owner: object, open_member: Callable[[], ZenohMember | ZenohNetwork]
) -> ZenohMember | ZenohNetwork:
    """This process's membership of `system`, or `open_member()`; else `ConfigError`."""
    global _MEMBER, _MEMBER_OWNER
    forkserver.check_usable(f"a member of system {system!r}")
    with _MEMBER_LOCK:
        member = _MEMBER
        if member is not None and not member.closed:
            if member.system != system:
                raise ConfigError(
                    f"this process is a member of system {member.system!r}; a process "
                    f"belongs to one system (the registrar directory is per process), so it "
                    f"cannot serve on system {system!r}"
                )
            if owner is None or owner is _MEMBER_OWNER:
                return member
            raise ConfigError(
                f"this process already joined system {system!r} through another "
                f"ZenohNetwork or address; use that one"
            )
        member = open_member()
        _MEMBER, _MEMBER_OWNER = member, owner
        _OPENED.append(system)
        return member


def _left(member: Messenger) -> None:
    global _MEMBER, _MEMBER_OWNER
    with _MEMBER_LOCK:
        if _MEMBER is member:
            _MEMBER, _MEMBER_OWNER = None, None


def _close_at_exit(what: str, member: Messenger, close: Callable[[], None]) -> None:
    """Close `member`'s session when the main thread ends (Zenoh's threads are not daemons)."""
    stop_at_exit(NETWORKS, what, lambda: not member.closed, lambda _timeout: close())


def _no_link(unlinked: list[tuple[str, str]]) -> str:
    """The end of an error about a name not seen: the connect endpoints with no link."""
    if not unlinked:
        return ""
    links = "; ".join(f"{endpoint} ({reason})" for endpoint, reason in unlinked)
    return (
        f"; this process has no link to connect endpoint {links}, so a registrar served "
        f"there is not seen"
    )


@dataclasses.dataclass(frozen=True)
class ZenohAddress:
    """How a process of this host joins the system: through its router's Unix socket.

    Attributes:
        system: the system's name.
        socket_path: the router's Unix socket (in its 0700 runtime directory).
        lease: seconds after which a silent peer counts as gone.
        router: the router process's Zenoh id.
        router_pid: its pid (a manager it started names `router` its supervisor).
        member: this host's member name (`""` without TLS).
        max_offset: the network's `max_offset`, which that process's clock takes.
        tls: the network's `ZenohTLS` (`None`: plain TCP).
        resolve: the network's `resolve` (rule 22); a function crosses cloudpickled.
        beside: what the router runs beside its session (`attach_beside`), or `None`.
    """

    system: str
    socket_path: str
    lease: float
    router: str
    router_pid: int = 0
    member: str = ""
    max_offset: float = MAX_OFFSET
    tls: ZenohTLS | None = None
    resolve: Resolve = "first_served"
    beside: Callable[[Opened], Beside] | None = None

    def __reduce__(self) -> tuple[Any, ...]:
        """A function `resolve` by value (a manager's start arguments use plain pickle)."""
        fields = {field.name: getattr(self, field.name) for field in dataclasses.fields(self)}
        if callable(self.resolve):
            del fields["resolve"]
            return (_address_by_value, (fields, wire.dumps(self.resolve)))
        return (ZenohAddress, tuple(fields.values()))

    def attach(self) -> ZenohMember | ZenohNetwork:
        """Join from this process (idempotent); `ConfigError`, `RegistrarUnavailableError`."""
        return _join(self.system, None, lambda: ZenohMember(self))


def _address_by_value(fields: dict[str, Any], resolve: bytes) -> ZenohAddress:
    return ZenohAddress(**fields, resolve=pickle.loads(resolve))


class ZenohMember(Messenger):
    """A manager process's membership, joined through its host's router (CLIENT mode)."""

    def __init__(self, address: ZenohAddress) -> None:
        super().__init__(address.system, resolve=address.resolve)
        self._address = address
        set_host(address.member or socket.gethostname())
        CLOCK.max_offset = address.max_offset
        config = session_config(
            "client", [], [f"unixsock-stream/{address.socket_path}"], address.lease
        )
        try:
            session = zenoh.open(config)
        except Exception as exc:
            raise RegistrarUnavailableError(
                f"cannot join system {address.system!r} through {address.socket_path!r}: {exc}"
            ) from exc
        make = address.beside
        opened = Opened(address.system, session, Keys(address.system), address.tls, None)
        self.beside: Beside | None = None if make is None else make(opened)
        self.joined(
            ZenohCarrier(
                self,
                session,
                speakers={address.router_pid: address.router},
                on_close=lambda: _left(self),
                router=address.router,
                on_leave=None if self.beside is None else self.beside.close,
                members=_member_count(address.tls),
            )
        )
        _close_at_exit(f"the membership of system {address.system!r}", self, self.close)

    @property
    def address(self) -> ZenohAddress:
        return self._address


@dataclasses.dataclass(frozen=True)
class Services:
    """What rr_actors' own services get of a router; declare only `keys`' observer keys.
    `member` is `None` and `links` empty without TLS."""

    session: zenoh.Session
    keys: Keys
    member: str | None
    lease: float
    links: Callable[[], list[MemberLink]]
    on_leave: Callable[[Callable[[], object]], Callable[[], None]] = lambda _close: _nothing


def _nothing() -> None:
    """What forgets a `close` given to a session of no carrier (tests')."""


class ZenohNetwork(Messenger):
    """A system of registrars across hosts over Eclipse Zenoh (`pip install rr-actors[zenoh]`).

    Hand it to `ResourceRegistrar.start(..., network=net)` and
    `Supervisor(..., network=net)`: the process that makes it is its host's router; it
    opens its Zenoh session at first use. All arguments are keyword-only; what each
    means in practice: docs/how-to/two-machines.md.

    Args:
        system: the system's name, as a registrar name (`rr_actors.config.NAME`); every
            key expression starts with `rr/<system>/`.
        listen: Zenoh endpoints to listen on, `tls/<address>:<port>` with `tls`,
            `tcp/<address>:<port>` without (then a WARNING each names who can reach it
            and run code as this process's user).
        connect: endpoints of other hosts' routers, in the same form. One that cannot be
            reached yet is no error (Zenoh keeps trying): a WARNING names it, with TLS
            the reason from a handshake of our own, at most once a minute.
        tls: required. A `ZenohTLS`: mutual TLS on every link and Zenoh's access control
            (only `members` and this host's manager processes reach `rr/<system>/`).
            `None`: plain TCP, for one trusted network only: anyone who reaches a port
            can send pickles, which run as code.
        lease: seconds (default 1.0) after which a silent peer counts as gone.
        max_offset: seconds (default 60.0) a message's clock stamp may be ahead of this
            host's clock and still be taken in by the hybrid logical clock (Kulkarni et
            al. 2014; CockroachDB's `max-offset`); one further ahead is refused with a
            WARNING a minute. Set it above the most the hosts' clocks may differ by.
        resolve: which of two registrars serving one name is kept when a healed cut
            shows both (rule 22; the other yields): `"first_served"` (default),
            `"majority"` (the one whose side held more than half the members when it
            began to serve; neither: first served; both: the later), or a deterministic
            function `(first, second) -> the one kept` of two `rr.Claimant`s (one that
            raises or answers neither: first served, with a WARNING). The same on every
            host; what each loses: docs/explanation/failure-semantics.md.

    Raises:
        ConfigError: a bad `system` (or one longer than 64 characters), a malformed
            endpoint, a `tcp/` endpoint with `tls` or a `tls/` one without, a `tls` that
            is neither `None` nor a `ZenohTLS`, a `lease` that is not a positive number
            of seconds, a `max_offset` that is not seconds above 0 and at most a year,
            a `resolve` that is neither a strategy's name nor a function, or a
            function that cannot be pickled (even by cloudpickle: the processes that
            join through this host's router take it).
    """

    def __init__(
        self,
        *,
        system: str,
        listen: Iterable[str] = (),
        connect: Iterable[str] = (),
        tls: ZenohTLS | None,
        lease: float = 1.0,
        max_offset: float = MAX_OFFSET,
        resolve: Resolve = "first_served",
    ) -> None:
        super().__init__(check_name("system", system, "a system name"), resolve=resolve)
        if callable(resolve):
            try:  # (it crosses to the manager processes, in `ZenohAddress`)
                wire.dumps(resolve)
            except Exception as exc:
                raise ConfigError(
                    f"resolve must be a function that can be pickled (by cloudpickle: the "
                    f"processes that join through this host take it), not {resolve!r}: {exc}"
                ) from exc
        if tls is not None and not _is_tls(tls):
            raise ConfigError(
                f"tls must be rr.ZenohTLS(ca=..., cert=..., key=..., members=[...]) or None "
                f"(plain TCP), not {tls!r}"
            )
        self.tls = tls
        self.listen = endpoints("listen", listen, tls=tls is not None)
        self.connect = endpoints("connect", connect, tls=tls is not None)
        if (
            isinstance(lease, bool)
            or not isinstance(lease, int | float)
            or not math.isfinite(lease)
            or not 0.01 <= lease <= 3600
        ):
            raise ConfigError(f"lease must be seconds from 0.01 to 3600, not {lease!r}")
        self.lease = float(lease)
        self.max_offset = check_max_offset(max_offset)
        if tls is None:
            warn_plain_tcp(system, self.listen, self.connect)
        self._open_lock = threading.Lock()
        self._opened: ZenohCarrier | None = None
        self._runtime_dir: str | None = None
        self._address: ZenohAddress | None = None
        self.beside: Beside | None = None
        self._gate: HandshakeGate | None = None
        self._members: MemberAddresses | None = None

    def __repr__(self) -> str:
        return (
            f"ZenohNetwork(system={self.system!r}, listen={list(self.listen)!r}, "
            f"connect={list(self.connect)!r}, tls={self.tls!r}, lease={self.lease!r}, "
            f"max_offset={self.max_offset!r}, resolve={self.resolution.resolve!r})"
        )

    # -- opening ---------------------------------------------------------------------------

    def link(self) -> ZenohCarrier:
        """The router's carrier: its session opens here, at first use."""
        carrier = self._opened
        if carrier is not None:
            return carrier
        with self._open_lock:
            if self._opened is None:
                _join(self.system, self, self._open_router)
            assert self._opened is not None
            return self._opened

    def _open_router(self) -> ZenohNetwork:
        set_host(self.tls.name if self.tls is not None else socket.gethostname())
        CLOCK.max_offset = self.max_offset
        runtime_dir = tempfile.mkdtemp(prefix="rr-zenoh-")  # mode 0700
        path = os.path.join(runtime_dir, "router.sock")
        config = session_config(
            "router",
            [*self.listen, f"unixsock-stream/{path}"],
            list(self.connect),
            self.lease,
            system=self.system,
            tls=self.tls,
        )
        _zenoh_log_from_env()
        try:
            session = zenoh.open(config)
        except Exception as exc:
            shutil.rmtree(runtime_dir, ignore_errors=True)
            raise ConfigError(
                f"ZenohNetwork {self.system!r} cannot listen on {list(self.listen)!r}: {exc}"
            ) from exc
        make = _beside()
        try:
            if self.tls is None:
                warn_unreachable(self.system, self.connect)
            else:  # who links: a flood's gate never drops a member
                self._members = MemberAddresses(self.system, session, self.tls)
                self._gate = HandshakeGate(self.system, open_gates(self.listen), self._members.now)
            if make is not None:  # (the event feed across hosts, the link watch)
                opened = Opened(self.system, session, Keys(self.system), self.tls, self.connect)
                self.beside = make(opened)
            beside, members, gate = self.beside, self._members, self._gate
            self._runtime_dir = runtime_dir
            self._address = ZenohAddress(
                self.system,
                path,
                self.lease,
                str(session.zid()),
                os.getpid(),
                "" if self.tls is None else self.tls.name,
                self.max_offset,
                self.tls,
                self.resolution.resolve,
                make,
            )

            def closed() -> None:
                for part in (beside, gate, members):
                    if part is not None:
                        part.close()
                _left(self)
                shutil.rmtree(runtime_dir, ignore_errors=True)

            self._opened = ZenohCarrier(
                self,
                session,
                on_close=closed,
                link_trouble=lambda: _no_link(self._unlinked()),
                on_leave=None if beside is None else beside.close,
                members=_member_count(self.tls),
            )
            self.joined(self._opened)
            _close_at_exit(f"ZenohNetwork {self.system!r}", self, self.close)
        except BaseException:  # nothing of a network that did not open is left behind:
            self._opened = None
            self._unopened(session, runtime_dir)  # (Zenoh's threads would hold the exit)
            raise
        return self

    def _unopened(self, session: zenoh.Session, runtime_dir: str) -> None:
        """Close what `_open_router` made before it failed."""
        for part in (self.beside, self._gate, self._members):
            if part is not None:
                with contextlib.suppress(Exception):
                    part.close()
        self.beside = self._gate = self._members = None
        with contextlib.suppress(Exception):
            session.close()  # type: ignore[no-untyped-call]
        shutil.rmtree(runtime_dir, ignore_errors=True)

    # -- what a network has besides the Transport surface --------------------------------

    @property
    def address(self) -> ZenohAddress:
        """What manager processes of this host join through (opens the session)."""
        self.link()
        assert self._address is not None
        return self._address

    @property
    def runtime_dir(self) -> str | None:
        """The private directory of the router's Unix socket, once open."""
        return self._runtime_dir

    def services(self) -> Services:
        """The router's session, for rr_actors' own services (opens it).

        Raises:
            RegistrarStoppedError: this process left the system (`close()`).
        """
        carrier = self.link()
        if self.closed:
            raise RegistrarStoppedError(f"this process left system {self.system!r}")
        beside = self.beside
        return Services(
            session=carrier.session,
            keys=carrier.keys,
            member=None if self.tls is None else self.tls.name,
            lease=self.lease,
            links=(list) if beside is None else beside.member_links,
            on_leave=carrier.on_leave,
        )

    def subscribe_events(
        self,
        callback: Callable[[events.Event], object],
        *,
        window: float = 0.5,
        maxsize: int = DEFAULT_MAXSIZE,
    ) -> Subscription[events.Event]:
        """Call `callback(event)` for every event of every host of the system from now on.

        Events cross as JSON lines (never pickles), between members only, and only while
        someone subscribes (another process's from about when the subscription reached
        it). Each carries `host` (its member name) and `hlc` (its hybrid logical clock
        stamp): events are held `window` seconds and handed over in `hlc` order, a cause
        on one host before its effect on another. The callback runs on a subscriber
        thread of its own, one event at a time; past `maxsize` queued events new ones are
        dropped, counted and reported by one `EventsDropped`.

        Args:
            callback: `callback(event)`; what it raises is logged.
            window: seconds an event is held for others to overtake it (0: in the order
                they arrive). An event that arrives more than `window` after one with a
                greater stamp was handed over comes late (out of `hlc` order).
            maxsize: events queued for the callback before new ones are dropped.

        Returns:
            The subscription; `close()` it, or use it as a context manager.

        Raises:
            ConfigError: `callback` is not callable, `window` not seconds from 0 to 60,
                or `maxsize` not a positive int; or the event feed is not attached (the
                runtime alone, without `rr_actors_lab.observe`).
            RegistrarStoppedError: this process left the system (`close()`).
        """
        if not callable(callback):  # (before the session opens)
            raise ConfigError(f"callback must be callable, got {callback!r}")
        window = _check_window(window)
        self.link()
        if self.closed:
            raise RegistrarStoppedError("this process left the system")
        if self.beside is None:
            raise ConfigError(
                "the event stream across hosts is the observer's: import rr_actors_lab.observe "
                "before the network opens (rr.ZenohNetwork does)"
            )
        return self.beside.subscribe_events(callback, window, maxsize)

    def wait_for(self, name: str, *, timeout: float) -> None:
        """Wait until registrar `name` is served on this system (by any host).

        For a program whose other machine may start after it. Opens the session.

        Args:
            name: the registrar's name.
            timeout: seconds to wait at most.

        Raises:
            RegistrarUnavailableError: `name` is not served within `timeout`; the message
                names each `connect` endpoint this process has no link to, with the
                reason the link watch found (with `tls`: the TLS handshake's verdict).
            RegistrarStoppedError: this process left the system (`close()`).
            ConfigError: `name` is not a registrar name (`rr.config.NAME`: it could never
                be served), or `timeout` not a number of seconds >= 0.
        """
        check_name("name", name, "a registrar name")
        if (
            isinstance(timeout, bool)
            or not isinstance(timeout, int | float)
            or not math.isfinite(timeout)
            or timeout < 0
        ):
            raise ConfigError(f"timeout must be seconds >= 0, not {timeout!r}")
        carrier = self.link()
        if self.closed:
            raise RegistrarStoppedError(f"this process left system {self.system!r}")
        if carrier.wait_served(name, timeout=timeout):
            return
        if self.closed:
            raise RegistrarStoppedError(f"this process left system {self.system!r}")
        raise RegistrarUnavailableError(
            f"no registrar named {name!r} was served on system {self.system!r} within "
            f"{timeout:g} s" + _no_link(self._unlinked())
        )

    def _unlinked(self) -> list[tuple[str, str]]:
        beside = self.beside
        return [] if beside is None else beside.unlinked()

    def close(self) -> None:
        """Leave the system: stop serving, fail what waits, close the session, and wait
        (at most 2 s) for the threads that call Zenoh. Idempotent. Stop registrars first
        to release what they hold elsewhere."""
        if self._gate is not None:
            self._gate.close()  # (its duplicate of a listening socket, too)
        if self._opened is not None:
            super().close()

    def __enter__(self) -> ZenohNetwork:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


if TYPE_CHECKING:  # mypy checks that the carrier implements the interface
    _network: type[Transport] = ZenohNetwork
    _member: type[Transport] = ZenohMember
    _address: type[Address] = ZenohAddress
