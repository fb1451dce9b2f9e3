"""The Zenoh carrier's receiving side: messages for the registrars served here, answers
for the replies waiting here.

```
 put rr/<s>/reg/<name> ─► subscriber callback (Zenoh's thread: never blocks, never decodes)
                            │ sender's token not here: the strangers' thread waits for it
                            ▼ else queued                (bounded; then dropped, a WARNING)
                 inbox (sender, message): decode thread (SerialExecutor)
                   version refused? too large? unpickle; stand-in reply;
                   tell the registrar ─► reply.set_result ─► owner.answer_to(sender)

 put rr/<s>/ans/<zid> ─► answers callback ─► inbox (sender, answer): decode thread
                           Replies.answered (the messenger): reply.set_result(value)
```

Each process decodes on one thread per sending process and kind (messages, answers: a
held answer never holds up a notice), and only for processes whose liveliness token is
here (`Presence.member`): the sender id in a header is whatever the sender wrote, so a
thread per claimed id would let one buggy member start threads without bound. The frames
of any other sender wait on one thread for strangers, for its token (`STRANGER_GRACE`:
Zenoh sends declarations ahead of data, so a frame may come before its sender's token,
or after the token's end), and are dropped if it does not come. Nothing is
unpickled on Zenoh's thread: unpickling may run code of the sender's choosing (a frame's
flags say nothing a buggy sender cannot get wrong), and a blocked Zenoh thread stalls
every message of its link.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from typing import Any, Protocol

import zenoh

from rr_actors._core.hlc import CLOCK
from rr_actors._core.serial import SerialExecutor
from rr_actors._core.throttle import LogThrottle, short
from rr_actors._transport.base import Endpoint
from rr_actors._transport.codec import NO_REPLY
from rr_actors._transport.messenger import Lost, Messenger, Replies
from rr_actors._transport.zenoh.wire import (
    ANSWER,
    MESSAGE,
    VERSION,
    Header,
    parse,
    payload_of,
    versions_text,
)

__all__ = ["STRANGERS_HELD", "STRANGER_GRACE", "Inbox", "InboxOwner", "Local"]

logger = logging.getLogger("rr_actors")

STRANGER_GRACE = 2.0
"""Seconds a frame of a process whose liveliness token is not here waits for the token
(Zenoh may hand this process a frame before the token its sender declared first); then
it is dropped. A frame of a process whose token went less than this long ago is
delivered (Zenoh may hand it over after the token's end, sent later)."""

STRANGERS_HELD = (10_000, 64 * 1024 * 1024)
"""Frames and bytes of such processes held at most; beyond, new ones are dropped."""


class Local:
    """A registrar served by this process: its subscriber and token, the clock stamp of
    when it began to serve, and whether it yielded its name (rule 22, `carrier`)."""

    def __init__(self, endpoint: Endpoint) -> None:
        self.endpoint = endpoint
        self.name = endpoint.name
        self.max_message_bytes = endpoint.max_message_bytes
        self.subscriber: Any = None
        self.token: Any = None
        self.stamp = 0
        self.lock = threading.Lock()
        self.ended = False
        self.yielded = False


class InboxOwner(Protocol):
    """What the inbox asks of its member: sending (the messenger's `Link`)."""

    def answer_to(self, sender: str, data: bytes, on_lost: Lost | None) -> bool:
        """Send an answer frame to process `sender`; False if it is gone (not sent)."""

    def member(self, zid: str) -> bool:
        """Whether process `zid`'s liveliness token is here now (Zenoh's threads)."""

    def refuse_version(self, sender: str, token: int) -> None:
        """Tell process `sender` that its message `token` was of another version."""


class Inbox:
    """The decode queues of one process (one per sending process and kind); what they
    decode goes to the messenger: messages for the registrars served here, answers for
    the replies waiting here (`replies`, by token: every route's `pending`).

    Args:
        owner: what sends answers (the member).
    """

    def __init__(self, owner: InboxOwner) -> None:
        self._owner = owner
        self._messenger = Messenger(owner)
        self.replies = Replies()
        self._lock = threading.Lock()
        self._closed = False
        self._inboxes: dict[tuple[str, int], SerialExecutor] = {}
        self._warned: set[str] = set()
        self._strangers = SerialExecutor("rr-zread-strangers")
        self._pending: dict[tuple[str, int], int] = {}  # frames on `_strangers`, by stream
        self._held = (0, 0)  # frames and bytes on `_strangers`
        self._arrived: set[str] = set()  # tokens that came while `_strangers` held frames
        self._left: dict[str, float] = {}  # tokens that went in the last STRANGER_GRACE s
        self._joined = threading.Condition(threading.Lock())
        self._dropped = LogThrottle(logger)

    # -- the queues --------------------------------------------------------------------------

    def finish(self, sender: str) -> None:
        """Process `sender` went: what it sent before is still decoded, then its threads end."""
        for kind in (MESSAGE, ANSWER):
            inbox = self._inboxes.pop((sender, kind), None)
            if inbox is not None:
                inbox.finish()

    def process_token(self, zid: str, present: bool) -> None:
        """Process `zid`'s token came (`present`) or went (Zenoh's thread): what of it
        waits on the strangers' thread may go on. (A frame may still come after its token
        went: Zenoh sends a declaration before data sent earlier.)"""
        now = time.monotonic()
        with self._lock:
            if not present:
                self._left = {z: t for z, t in self._left.items() if now - t < STRANGER_GRACE}
                self._left[zid] = now
            elif self._held[0]:
                self._arrived.add(zid)
        with self._joined:
            self._joined.notify_all()

    def close(self) -> None:
        """Stop decoding: what is queued is dropped."""
        with self._lock:
            self._closed = True
            inboxes = [*self._inboxes.values(), self._strangers]
        with self._joined:
            self._joined.notify_all()
        for inbox in inboxes:
            inbox.close(timeout=0)

    def _receive(self, head: Header, kind: int, item: Any, size: int) -> None:
        """Hand `item` (`size` bytes) to the decode thread of (sender, `kind`) (Zenoh's
        callbacks).

        A sender whose process token is not here (yet) gets no thread of its own: its
        frames wait on the one thread for strangers (`_stranger`), as do its later frames
        until those before them are done (then they keep their order).
        """
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
                        self._inboxes[key] = inbox
            if inbox.submit(task):
                return

    def _heard(self, sender: str) -> bool:
        """Whether process `sender`'s token is here, came since a frame of it waits, or
        went less than `STRANGER_GRACE` seconds ago."""
        if self._owner.member(sender) or sender in self._arrived:
            return True
        left = self._left.get(sender)
        return left is not None and time.monotonic() - left < STRANGER_GRACE

    def _wait_for_token(self, key: tuple[str, int], item: Any, size: int) -> None:
        """Queue `item` of a sender whose token is not here on the strangers' thread (hold
        `_lock`); over `STRANGERS_HELD`, drop it."""
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
        """Handle one frame of a sender whose token was not here (the strangers' thread):
        once its token comes, as its own thread would; dropped if it does not come within
        `STRANGER_GRACE` seconds of the frame."""
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

    # -- decoding ----------------------------------------------------------------------------

    def on_message(self, local: Local, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        head = parse(data)
        if head is not None:
            self._receive(head, MESSAGE, (local, data, head), len(data))

    def on_answer(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        head = parse(data)
        if head is not None:
            self._receive(head, ANSWER, (data, head), len(data))

    def _deliver(self, item: tuple[Local, bytes, Header]) -> None:
        """Decode one message for a registrar of this process and tell it (its sender's
        decode thread)."""
        local, data, head = item
        token, payload = payload_of(data, head)
        if not head.ours:
            self._refuse_version(local.name, head, token)
            return
        if head.stamp is not None:
            CLOCK.receive(head.stamp, head.sender)  # (before the registrar hears of it)
        self._messenger.message(local.endpoint, head.sender, token, payload)

    def _refuse_version(self, name: str, head: Header, token: int) -> None:
        """A message of another version: not unpickled; its sender is told why."""
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

    def _answered(self, item: tuple[bytes, Header]) -> None:
        """Decode one answer and resolve the reply waiting for it (its sender's decode
        thread)."""
        data, head = item
        token, payload = payload_of(data, head)
        if head.kind == VERSION or not head.ours:
            self.replies.refused(token, versions_text(head))
            return
        if head.stamp is not None and token in self.replies:
            CLOCK.receive(head.stamp, head.sender)  # (an answer someone waits for)
        self.replies.answered(token, payload)
