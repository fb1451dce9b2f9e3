"""The Zenoh link: frames both ways, one writer thread per destination key and one
decode thread per sending process.

How and why: docs/explanation/inside.md ("The Zenoh link").
"""

from __future__ import annotations

import contextlib
import functools
import logging
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

import zenoh

from rr_actors._core.hlc import CLOCK
from rr_actors._core.serial import SerialExecutor, Task
from rr_actors._core.throttle import LogThrottle, short
from rr_actors._transport.codec import NO_REPLY
from rr_actors._transport.messenger import Listening, Lost, Messenger, Replies, run_lost
from rr_actors._transport.zenoh import callbacks
from rr_actors._transport.zenoh.wire import (
    ANSWER,
    MESSAGE,
    VERSION,
    Header,
    Keys,
    parse,
    payload_of,
    versions_text,
)
from rr_actors.errors import RrError

logger = logging.getLogger("rr_actors")


HEAL_TIMEOUT = 2.0
"""Seconds the first message to a process just seen waits for its answer to a ping."""

DRAIN_TIMEOUT = 1.0
"""Seconds a process that leaves gives its writers, together, to put what they hold."""


class Outbox:
    """The writer of one destination key: its thread puts payloads in the order sent."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        ready: Callable[[], None] | None = None,
        *,
        declared: bool = True,
    ) -> None:
        self.key = key
        self.pinged: str | None = None  # the process a task of `run` pinged (its thread's)
        self.refusal: RrError | None = None  # why it was retired (the carrier's `retire`)
        self._ready = ready  # runs on the writer thread before the first put
        self._session = session
        self._publisher: zenoh.Publisher | None = None
        name = f"rr-zput-{key.rsplit('/', 1)[-1]}"
        self._queue = SerialExecutor(name, on_drop=self._lost, on_end=self._let_go)
        if callbacks.worker(session, self._queue) and declared:  # (joined by the close)
            with contextlib.suppress(callbacks.SessionEndedError):  # (then its puts fail)
                self.declare()

    @property
    def closed(self) -> bool:
        return self._queue.closed

    def send(self, data: bytes, on_lost: Lost | None = None) -> bool:
        """Queue `data`; False (nothing sent) if the outbox is closed."""
        return self._queue.submit(functools.partial(self.put, data, on_lost))

    def run(self, task: Callable[[], None]) -> bool:
        """Run `task` on the writer thread, in order (it may wait, and `put`); False if closed."""
        return self._queue.submit(task)

    def declare(self) -> None:
        """Declare the publisher, if not yet (at creation, or on the writer thread)."""
        if self._publisher is None:
            with callbacks.calling(self._session):  # (at creation: a caller's thread)
                self._publisher = self._session.declare_publisher(
                    self.key,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    express=True,
                    reliability=zenoh.Reliability.RELIABLE,
                )

    def put(self, data: bytes, on_lost: Lost | None = None) -> bool:
        """Put `data` now (writer thread only); False if the session closed."""
        ready, self._ready = self._ready, None
        if ready is not None:
            ready()
        try:
            self.declare()
            assert self._publisher is not None
            self._publisher.put(data)
        except Exception as exc:  # noqa: BLE001 - the session closed: the frame is lost
            logger.debug("a put on %s failed: %s", self.key, exc)
            if on_lost is not None:
                run_lost([on_lost])
            return False
        return True

    def close(self, timeout: float = 0.0) -> None:
        """Stop sending: what is queued gets `timeout` seconds, then is lost (`on_lost`);
        the publisher goes once the task under way ended (`_let_go`)."""
        self._queue.close(timeout=timeout)  # (each dropped frame's `on_lost` runs: `_lost`)

    def _let_go(self) -> None:
        """The queue's last step (on the writer thread; the closer's if it never had one):
        the publisher is undeclared and freed here, not wherever the outbox goes last (a
        publisher's free releases the GIL: docs/explanation/inside.md)."""
        publisher, self._publisher = self._publisher, None
        with contextlib.suppress(Exception), callbacks.calling(self._session):
            if publisher is not None:
                publisher.undeclare()  # type: ignore[no-untyped-call]
            publisher = None  # (freed while counted, if the session is still open)

    @staticmethod
    def _lost(task: Task) -> None:
        if isinstance(task, functools.partial) and task.args[1] is not None:
            run_lost([task.args[1]])
        dropped = getattr(task, "dropped", None)
        if dropped is not None:
            run_lost([dropped])


class Outboxes:
    """The outboxes of one process's session, by destination key."""

    def __init__(self, session: zenoh.Session, keys: Keys) -> None:
        self._session = session
        self._keys = keys
        self._lock = threading.Lock()
        self._outboxes: dict[str, Outbox] = {}
        self._closed = False
        self._pings_end = False  # `until_answered` gives up (`close`)

    def get(self, key: str, first_to: str | None = None, *, declared: bool = True) -> Outbox:
        """The outbox of `key`; a new one's first put waits for `first_to` to answer a ping."""
        outbox = self._outboxes.get(key)
        if outbox is not None and not outbox.closed:
            return outbox
        ready = functools.partial(self.until_answered, first_to) if first_to else None
        # (made before our lock is taken: no Zenoh call under it, its callbacks take it)
        fresh = Outbox(self._session, key, ready, declared=declared)
        with self._lock:
            outbox = self._outboxes.get(key)
            if self._closed:
                outbox = None  # (closed meanwhile: a writer made now would never end)
            elif outbox is None or outbox.closed:
                self._outboxes[key] = outbox = fresh
        if outbox is not fresh:
            fresh.close()
        if outbox is None:
            return fresh  # closed: it drops what it is given
        return outbox

    def pop(self, key: str) -> Outbox | None:  # (its destination went; the caller closes it)
        with self._lock:
            return self._outboxes.pop(key, None)

    def retire(self, outbox: Outbox) -> None:
        """Forget `outbox` (if still its key's) and close it: what is queued is dropped."""
        with self._lock:
            if self._outboxes.get(outbox.key) is outbox:
                del self._outboxes[outbox.key]
        outbox.close()

    def close(self, drain: float = 0.0) -> None:
        """Close every outbox: what is queued gets `drain` seconds in all, then is lost."""
        with self._lock:
            self._closed = True
            outboxes = list(self._outboxes.values())
        if drain > 0:
            self._pings_end = True
        deadline = time.monotonic() + drain
        for outbox in outboxes:
            outbox.close(max(0.0, deadline - time.monotonic()))
        self._pings_end = True

    def until_answered(self, zid: str) -> None:
        """Ping process `zid` until it answers (at most `HEAL_TIMEOUT` s; writer thread)."""
        deadline = time.monotonic() + HEAL_TIMEOUT
        pause = threading.Event()
        while not self._pings_end and time.monotonic() < deadline:
            try:
                replies = self._session.get(self._keys.ping(zid), timeout=0.25)
                if any(reply.ok is not None for reply in replies):
                    return
            except Exception:  # noqa: BLE001 - the session closed: the put fails too
                return
            pause.wait(0.01)  # (no queryable seen yet: a get returns at once)


STRANGER_GRACE = 2.0
"""Seconds a frame of a process whose liveliness token is not here (yet, or for this
long) waits for it before it is dropped (docs/explanation/inside.md, "The Zenoh link")."""

STRANGERS_HELD = (10_000, 64 * 1024 * 1024)  # frames and bytes of such processes, at most


class InboxOwner(Protocol):
    """What the inbox asks of its carrier (`carrier.ZenohCarrier`)."""

    @property
    def messenger(self) -> Messenger: ...
    @property
    def session(self) -> zenoh.Session: ...  # its close joins the decode threads
    def member(self, zid: str) -> bool: ...  # process `zid`'s token is here now
    def refuse_version(self, sender: str, token: int) -> None: ...  # tell it: not read


class Inbox:
    """The decode queues of one process, one per sending process and kind."""

    def __init__(self, owner: InboxOwner) -> None:
        self._owner = owner
        self._messenger = owner.messenger
        self._session = owner.session
        self.replies = Replies()
        self._lock = threading.Lock()
        self._closed = False
        self._inboxes: dict[tuple[str, int], SerialExecutor] = {}
        self._warned: set[str] = set()
        self._strangers = SerialExecutor("rr-zread-strangers")
        callbacks.worker(self._session, self._strangers)
        self._pending: dict[tuple[str, int], int] = {}  # frames on `_strangers`, by stream
        self._held = (0, 0)  # frames and bytes on `_strangers`
        self._arrived: set[str] = set()  # tokens that came while `_strangers` held frames
        self._left: dict[str, float] = {}  # tokens that went in the last STRANGER_GRACE s
        self._joined = threading.Condition(threading.Lock())
        self._dropped = LogThrottle(logger)

    def finish(self, sender: str) -> None:
        """Process `sender` went: what it sent is still decoded, then its threads end."""
        for kind in (MESSAGE, ANSWER):
            inbox = self._inboxes.pop((sender, kind), None)
            if inbox is not None:
                inbox.finish()

    def process_token(self, zid: str, present: bool) -> None:
        """Process `zid`'s token came or went (Zenoh's thread): its strangers may go on."""
        now = time.monotonic()
        with self._lock:
            if not present:
                self._left = {z: t for z, t in self._left.items() if now - t < STRANGER_GRACE}
                self._left[zid] = now
            elif self._held[0]:
                self._arrived.add(zid)
        with self._joined:
            self._joined.notify_all()

    def close(self) -> None:  # (what is queued is dropped)
        with self._lock:
            self._closed = True
            inboxes = [*self._inboxes.values(), self._strangers]
        with self._joined:
            self._joined.notify_all()
        for inbox in inboxes:
            inbox.close(timeout=0)

    def _receive(self, head: Header, kind: int, item: Any, size: int) -> None:
        """Hand `item` to the decode thread of (sender, `kind`) (Zenoh's callbacks)."""
        key = (head.sender, kind)
        task = functools.partial(self._deliver if kind == MESSAGE else self._answered, item)
        for _attempt in (1, 2):  # (its inbox may have just finished: the sender went)
            inbox = self._inboxes.get(key)
            if inbox is None or inbox.closed:
                with self._lock:
                    if self._closed:
                        return
                    inbox = self._inboxes.get(key)
                    if inbox is None or inbox.closed:
                        if key in self._pending or not self._owner.member(head.sender):
                            self._wait_for_token(key, item, size)
                            return
                        inbox = SerialExecutor(f"rr-zread-{head.sender[:8]}-{kind}")
                        callbacks.worker(self._session, inbox)
                        self._inboxes[key] = inbox
            if inbox.submit(task):
                return

    def _heard(self, sender: str) -> bool:
        """Whether `sender`'s token is here, came since, or went within `STRANGER_GRACE`."""
        if self._owner.member(sender) or sender in self._arrived:
            return True
        left = self._left.get(sender)
        return left is not None and time.monotonic() - left < STRANGER_GRACE

    def _wait_for_token(self, key: tuple[str, int], item: Any, size: int) -> None:
        """Queue `item` on the strangers' thread (hold `_lock`), or drop it if too many."""
        count, held = self._held
        if count >= STRANGERS_HELD[0] or held + size > STRANGERS_HELD[1]:
            self._dropped.warning(
                "dropped a message from process %s: %d messages (%d bytes) of processes "
                "whose liveliness token is not here already wait for it",
                short(key[0]),
                count,
                held,
            )
            return
        self._held = (count + 1, held + size)
        self._pending[key] = self._pending.get(key, 0) + 1
        entry = (time.monotonic() + STRANGER_GRACE, key, item, size)
        self._strangers.submit(functools.partial(self._stranger, entry))

    def _stranger(self, entry: tuple[float, tuple[str, int], Any, int]) -> None:
        """The strangers' thread: one frame, once its sender's token comes, else dropped."""
        deadline, (sender, kind), item, size = entry
        try:
            with self._joined:
                while not self._heard(sender) and not self._closed:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        break
                    self._joined.wait(left)
            if self._heard(sender):
                (self._deliver if kind == MESSAGE else self._answered)(item)
            elif not self._closed:
                self._dropped.warning(
                    "dropped a message from process %s: no liveliness token of it came "
                    "within %g s (it is not a member of this system, its link went, or a "
                    "buggy member wrote another sender id in its header)",
                    short(sender),
                    STRANGER_GRACE,
                )
        finally:
            with self._lock:
                count, held = self._held
                self._held = (count - 1, held - size)
                if count == 1:
                    self._arrived.clear()
                left_of_it = self._pending.pop((sender, kind)) - 1
                if left_of_it:
                    self._pending[(sender, kind)] = left_of_it

    def on_message(self, local: Listening, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        head = parse(data)
        if head is not None:
            self._receive(head, MESSAGE, (local, data, head), len(data))

    def on_answer(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        head = parse(data)
        if head is not None:
            self._receive(head, ANSWER, (data, head), len(data))

    def _deliver(self, item: tuple[Listening, bytes, Header]) -> None:  # (its decode thread)
        local, data, head = item
        token, payload = payload_of(data, head)
        if not head.ours:
            self._refuse_version(local.name, head, token)
            return
        if head.stamp is not None:
            CLOCK.receive(head.stamp, head.sender)  # (before the registrar hears of it)
        self._messenger.message(local.endpoint, head.sender, token, payload)

    def _refuse_version(self, name: str, head: Header, token: int) -> None:
        if head.sender not in self._warned:
            self._warned.add(head.sender)
            logger.warning(
                "registrar %s refused a message of process %s: %s; pickles do not cross "
                "versions, so nothing of it was read",
                name,
                head.sender,
                versions_text(head),
            )
        if token != NO_REPLY:
            self._owner.refuse_version(head.sender, token)

    def _answered(self, item: tuple[bytes, Header]) -> None:  # (its decode thread)
        data, head = item
        token, payload = payload_of(data, head)
        if head.kind == VERSION or not head.ours:
            self.replies.refused(token, versions_text(head))
            return
        if head.stamp is not None and token in self.replies:
            CLOCK.receive(head.stamp, head.sender)  # (an answer someone waits for)
        self.replies.answered(token, payload)
