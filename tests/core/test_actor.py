"""The actor base and its one-shot future keep pykka's contract.

Every future test runs on pykka's own `ThreadingFuture` too, so each expectation is
pykka's behaviour, not one we made up.
"""

from __future__ import annotations

import asyncio
import logging
import queue
import sys
import threading
from collections.abc import Iterator
from typing import Any

import pykka
import pytest

from rr_actors._core.actor import Actor, ContainedError, OneShotFuture, deliver, on_actor_thread


@pytest.fixture(params=[pykka.ThreadingFuture, OneShotFuture], ids=["pykka", "one_shot"])
def future(request: pytest.FixtureRequest) -> pykka.Future[Any]:
    made: pykka.Future[Any] = request.param()
    return made


def _waiters(future: pykka.Future[Any], count: int) -> tuple[list[Any], list[threading.Thread]]:
    """`count` threads blocked in `future.get()`; what each got lands in the list."""
    got: list[Any] = []
    threads = [
        threading.Thread(target=lambda: got.append(future.get(timeout=10))) for _ in range(count)
    ]
    for thread in threads:
        thread.start()
    return got, threads


def test_get_returns_the_value_set_and_returns_it_again(future: pykka.Future[Any]) -> None:
    value = {"cam": 1}
    future.set(value)

    assert value is future.get(timeout=1)
    assert value is future.get()


def test_every_thread_waiting_on_a_future_gets_its_value(future: pykka.Future[Any]) -> None:
    got, threads = _waiters(future, 5)

    future.set("ready")
    for thread in threads:
        thread.join(10)

    assert ["ready"] * 5 == got


def test_get_raises_pykka_timeout_when_nothing_is_set_in_time(future: pykka.Future[Any]) -> None:
    with pytest.raises(pykka.Timeout):
        future.get(timeout=0.01)
    with pytest.raises(pykka.Timeout):
        future.get(timeout=0)
    with pytest.raises(pykka.Timeout):
        future.get(timeout=-1)


def test_a_timeout_beyond_what_a_lock_can_wait_still_waits() -> None:
    # Here pykka's ThreadingFuture raises OverflowError; a registrar call with such a
    # timeout (a finite call_timeout of 1e300, say) must not.
    future: OneShotFuture[Any] = OneShotFuture()
    got: list[Any] = []
    waiting = threading.Thread(target=lambda: got.append(future.get(timeout=1e300)))
    waiting.start()

    future.set(7)
    waiting.join(10)

    assert [7] == got


def test_a_done_callback_runs_once_on_the_thread_that_settles_the_future() -> None:
    future: OneShotFuture[Any] = OneShotFuture()
    ran: list[tuple[str, Any]] = []
    future.add_done_callback(lambda f: ran.append((threading.current_thread().name, f.get())))
    settler = threading.Thread(target=lambda: future.set(3), name="settler")

    settler.start()
    settler.join(5)

    assert [("settler", 3)] == ran


def test_a_done_callback_added_after_the_settle_runs_at_once_on_the_adding_thread() -> None:
    future: OneShotFuture[Any] = OneShotFuture()
    future.set_exception((ValueError, ValueError("no"), None))
    ran: list[str] = []

    future.add_done_callback(lambda _f: ran.append(threading.current_thread().name))

    assert [threading.current_thread().name] == ran


def test_a_done_callback_that_raises_is_logged_and_the_next_one_still_runs(
    caplog: pytest.LogCaptureFixture,
) -> None:
    future: OneShotFuture[Any] = OneShotFuture()
    ran: list[str] = []
    future.add_done_callback(lambda _f: 1 / 0)
    future.add_done_callback(lambda _f: ran.append("second"))

    with caplog.at_level(logging.ERROR, logger="rr_actors"):
        future.set(None)

    assert ["second"] == ran
    assert "a done callback of a future raised" in caplog.text


def test_a_done_callback_racing_the_settle_runs_exactly_once() -> None:
    # Dekker-style: the adder appends then reads `_settled`; the settler writes
    # `_settled` then reads the list. Whichever order the threads interleave in, each
    # callback runs once: run many rounds with both sides released at once.
    for _ in range(300):
        future: OneShotFuture[Any] = OneShotFuture()
        ran: list[int] = []
        go = threading.Barrier(2, timeout=5)

        def add(
            future: OneShotFuture[Any] = future,
            ran: list[int] = ran,
            go: threading.Barrier = go,
        ) -> None:
            go.wait()
            future.add_done_callback(lambda _f: ran.append(1))

        adder = threading.Thread(target=add)
        adder.start()
        go.wait()
        future.set(None)
        adder.join(5)

        assert [1] == ran


class _StagedLock:
    """A one-shot future's hand-off lock, with pauses that stage a race between waiters.

    A timed acquire (the waiter with a timeout) waits for `timed_go` before it tries the
    lock; an untimed one (the other waiter) holds the lock it got until `untimed_go`.
    """

    def __init__(self, lock: Any) -> None:
        self.lock = lock
        self.timed_entered, self.timed_go = threading.Event(), threading.Event()
        self.untimed_holds, self.untimed_go = threading.Event(), threading.Event()

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        if timeout != -1:
            self.timed_entered.set()
            assert self.timed_go.wait(10)
            return bool(self.lock.acquire(blocking, timeout))
        got = bool(self.lock.acquire(blocking, timeout))
        self.untimed_holds.set()
        assert self.untimed_go.wait(10)  # preempted between its acquire and its release
        return got

    def release(self) -> None:
        self.lock.release()


class _StagedFuture(OneShotFuture[Any]):
    def __init__(self) -> None:
        super().__init__()
        self.staged = self._ready = _StagedLock(self._ready)  # type: ignore[assignment]


def test_a_waiter_whose_wait_ran_out_while_another_waiter_passed_the_value_on_gets_it() -> None:
    # Two waiters: the one without a timeout takes the hand-off lock once the future is
    # set, and is preempted before it passes the lock on; the one with a timeout runs out
    # of time on the lock meanwhile. The future was set: it must not raise pykka.Timeout.
    future = _StagedFuture()
    got: list[Any] = []

    def wait_with_a_timeout() -> None:
        try:
            got.append(future.get(timeout=0.2))
        except pykka.Timeout as exc:
            got.append(exc)

    timed = threading.Thread(target=wait_with_a_timeout)
    timed.start()
    assert future.staged.timed_entered.wait(10)  # it saw the future unset
    untimed = threading.Thread(target=future.get)
    untimed.start()

    future.set("ready")
    assert future.staged.untimed_holds.wait(10)
    future.staged.timed_go.set()  # its acquire runs out while the other waiter holds
    timed.join(10)
    future.staged.untimed_go.set()
    untimed.join(10)

    assert ["ready"] == got


def test_a_second_set_raises_queue_full_and_keeps_the_first_value(
    future: pykka.Future[Any],
) -> None:
    future.set(1)

    with pytest.raises(queue.Full):
        future.set(2)
    with pytest.raises(queue.Full):
        future.set_exception((ValueError, ValueError("late"), None))
    with pytest.raises(queue.Full):
        future.set_get_hook(lambda _timeout: 3)
    assert 1 == future.get(timeout=1)


def test_set_after_an_exception_raises_queue_full(future: pykka.Future[Any]) -> None:
    future.set_exception((ValueError, ValueError("first"), None))

    with pytest.raises(queue.Full):
        future.set(2)
    with pytest.raises(ValueError, match="first"):
        future.get(timeout=1)


def _raise_key_error() -> None:
    raise KeyError("missing")


def test_get_raises_the_exception_set_with_its_traceback(future: pykka.Future[Any]) -> None:
    try:
        _raise_key_error()
    except KeyError:
        exc_info = sys.exc_info()
    future.set_exception(exc_info)

    with pytest.raises(KeyError) as raised:
        future.get(timeout=1)

    assert exc_info[1] is raised.value
    assert "_raise_key_error" in {entry.name for entry in raised.traceback}


def test_set_exception_without_arguments_takes_the_exception_being_handled(
    future: pykka.Future[Any],
) -> None:
    error = RuntimeError("handled")
    try:
        raise error
    except RuntimeError:
        future.set_exception()

    with pytest.raises(RuntimeError) as raised:
        future.get(timeout=1)
    assert error is raised.value


def test_an_exception_class_alone_is_raised_as_a_new_instance(future: pykka.Future[Any]) -> None:
    future.set_exception((LookupError, None, None))

    with pytest.raises(LookupError):
        future.get(timeout=1)


def test_a_get_hook_answers_get_and_blocks_a_later_set(future: pykka.Future[Any]) -> None:
    timeouts: list[float | None] = []
    future.set_get_hook(lambda timeout: timeouts.append(timeout) or "hooked")

    assert "hooked" == future.get(timeout=2)
    assert "hooked" == future.get(timeout=3)  # the hook runs once
    assert [2] == timeouts
    with pytest.raises(queue.Full):
        future.set("late")


def test_map_join_filter_and_reduce_build_on_the_same_future_type(
    future: pykka.Future[Any],
) -> None:
    other = type(future)()
    mapped = future.map(lambda value: value * 10)
    joined = future.join(other)
    filtered = other.filter(lambda item: item % 2 == 0)
    reduced = other.reduce(lambda total, item: total + item)
    future.set(4)
    other.set([1, 2, 3, 4])

    assert type(future) is type(mapped)
    assert 40 == mapped.get(timeout=1)
    assert [4, [1, 2, 3, 4]] == joined.get(timeout=1)
    assert [2, 4] == filtered.get(timeout=1)
    assert 10 == reduced.get(timeout=1)


def test_a_get_hook_runs_once_for_two_concurrent_getters(future: pykka.Future[Any]) -> None:
    source = type(future)()
    inside = threading.Semaphore(0)  # released each time a hook starts waiting on `source`
    original_get = source.get

    def counting_get(*, timeout: float | None = None) -> Any:
        inside.release()
        return original_get(timeout=timeout)

    source.get = counting_get  # type: ignore[method-assign]
    runs: list[int] = []
    mapped = source.map(lambda value: runs.append(value) or value)
    results: list[Any] = []
    getters = [
        threading.Thread(target=lambda: results.append(mapped.get(timeout=10))) for _ in "ab"
    ]
    for getter in getters:
        getter.start()
    assert inside.acquire(timeout=10)  # one getter runs the hook...
    second_hook = inside.acquire(timeout=0.5)  # ...and the other waits outside it
    source.set(7)
    for getter in getters:
        getter.join(10)

    assert [7, 7] == results
    assert (False, [7]) == (second_hook, runs)


def test_a_future_can_be_awaited(future: pykka.Future[Any]) -> None:
    async def waiting() -> Any:
        return await future

    future.set("awaited")

    assert "awaited" == asyncio.run(waiting())


# -- the actor --------------------------------------------------------------------------------


class _Echo(Actor):
    def __init__(self, gate: threading.Event | None = None) -> None:
        super().__init__()
        self.gate = gate

    def on_receive(self, message: Any) -> Any:
        if message == "wait" and self.gate is not None:
            assert self.gate.wait(10)
        if message == "fail":
            raise ValueError("asked to fail")
        if message == "exit":
            raise SystemExit("user code said so")
        return message


@pytest.fixture
def echo() -> Iterator[pykka.ActorRef[_Echo]]:
    ref = _Echo.start()
    yield ref
    ref.stop()


def test_an_actor_answers_asks_through_one_shot_futures_from_a_simple_queue(
    echo: pykka.ActorRef[_Echo],
) -> None:
    future = echo.ask("hello", block=False)

    assert isinstance(echo.actor_inbox, queue.SimpleQueue)
    assert isinstance(future, OneShotFuture)
    assert "hello" == future.get(timeout=5)


def test_an_error_in_on_receive_reaches_the_asker(echo: pykka.ActorRef[_Echo]) -> None:
    with pytest.raises(ValueError, match="asked to fail"):
        echo.ask("fail", timeout=5)
    assert "still here" == echo.ask("still here", timeout=5)


def test_a_handler_that_raises_system_exit_stops_its_own_actor_and_no_other(
    echo: pykka.ActorRef[_Echo],
) -> None:
    exiting = _Echo.start()

    with pytest.raises(ContainedError) as raised:
        exiting.ask("exit", timeout=5)  # an ask: the asker gets it
    exiting.tell("exit")  # a tell: the actor fails (pykka would stop every actor)

    assert exiting.actor_stopped.wait(5)
    assert isinstance(raised.value.__cause__, SystemExit)
    assert "still here" == echo.ask("still here", timeout=5)


def test_messages_are_handled_in_the_order_they_were_told() -> None:
    class Recorder(Actor):
        def __init__(self) -> None:
            super().__init__()
            self.seen: list[int] = []

        def on_receive(self, message: Any) -> Any:
            if message == "done":
                return list(self.seen)
            self.seen.append(message)
            return None

    ref = Recorder.start()
    try:
        for number in range(500):
            ref.tell(number)

        assert list(range(500)) == ref.ask("done", timeout=10)
    finally:
        ref.stop()


class _Turns(Actor):
    """Records each turn's messages in `turns`: `on_turn_end` closes the one under way."""

    drain = 3
    drain_seconds = 60.0
    ends_turns = True

    def __init__(self, gate: threading.Event, turns: list[list[Any]]) -> None:
        super().__init__()
        self.gate = gate
        self.turns = turns
        self.current: list[Any] = []

    def on_receive(self, message: Any) -> Any:
        if message == "wait":
            assert self.gate.wait(10)
        self.current.append(message)
        return None

    def on_turn_end(self) -> None:
        if self.current:
            self.turns.append(self.current)
            self.current = []


def test_a_turn_takes_the_messages_waiting_up_to_drain_then_ends_once() -> None:
    gate, turns = threading.Event(), list[list[Any]]()
    ref = _Turns.start(gate, turns)
    busy = ref.ask("wait", block=False)  # the first turn's first message
    for number in range(4):
        ref.tell(number)
    gate.set()
    busy.get(timeout=10)
    ref.stop(timeout=10)  # (its loop ended: `turns` is complete)

    assert [["wait", 0, 1], [2, 3]] == turns


def test_a_turn_is_one_message_with_no_turn_end_by_default() -> None:
    class Plain(_Turns):
        drain = 1
        ends_turns = False

        def on_receive(self, message: Any) -> Any:
            self.turns.append([message])  # (each message: no turn end closes anything)
            return super().on_receive(message)

    gate, turns = threading.Event(), list[list[Any]]()
    gate.set()
    ref = Plain.start(gate, turns)
    for number in range(3):
        ref.tell(number)
    ref.stop(timeout=10)

    assert [[0], [1], [2]] == turns


def test_asks_still_queued_when_the_actor_stops_fail_with_actor_dead_error() -> None:
    gate = threading.Event()
    ref = _Echo.start(gate)
    busy = ref.ask("wait", block=False)
    stopped = ref.stop(block=False)
    queued = ref.ask("after the stop", block=False)
    gate.set()

    assert "wait" == busy.get(timeout=10)
    assert stopped.get(timeout=10) is True
    with pytest.raises(pykka.ActorDeadError):
        queued.get(timeout=10)


def test_an_ask_that_saw_the_actor_alive_just_before_it_stopped_is_answered(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # pykka's `ask` checks `is_alive()`, then puts: the actor may end in between. Faking
    # the check puts the envelope exactly there, after the actor's final drain.
    ref = _Echo.start()
    assert ref.stop(block=True, timeout=10) is True
    monkeypatch.setattr(ref, "is_alive", lambda: True)

    with pytest.raises(pykka.ActorDeadError):
        ref.ask("late", timeout=10)
    assert ref.stop(block=True, timeout=10) is True  # (it saw the actor alive: as pykka's drain)


def test_what_is_told_to_an_ended_actor_is_dropped_without_error(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    ref = _Echo.start()
    ref.stop(block=True, timeout=10)
    monkeypatch.setattr(ref, "is_alive", lambda: True)

    ref.tell("late")  # nobody waits for a tell: nothing to answer

    assert ref.actor_inbox.empty()


class _Waits:
    """An actor body that answers each message once `gate` is set."""

    def __init__(self, gate: threading.Event) -> None:
        super().__init__()
        self.gate = gate

    def on_receive(self, message: Any) -> Any:
        assert self.gate.wait(10)
        return message


class _Busy(_Waits, Actor):
    pass


class _PykkaBusy(_Waits, pykka.ThreadingActor):
    pass


@pytest.mark.parametrize("actor_class", [_PykkaBusy, _Busy], ids=["pykka", "rr_actors"])
def test_a_stop_asked_while_the_actor_was_running_returns_true(
    actor_class: type[pykka.ThreadingActor],
) -> None:
    # pykka: "Returns True if actor is stopped or was being stopped at the time of the
    # call. False if actor was already dead." pykka's drain answers a queued `_ActorStop`
    # with None (True); `Actor._actor_loop_teardown` -> `refuse` answers it with
    # ActorDeadError, so the second of two concurrent stops now says "already dead".
    gate = threading.Event()
    ref = actor_class.start(gate)
    busy = ref.ask("busy", block=False)
    first = ref.stop(block=False)
    second = ref.stop(block=False)  # the actor is alive and running
    gate.set()

    assert "busy" == busy.get(timeout=10)
    assert (True, True) == (first.get(timeout=10), second.get(timeout=10))


# -- 4. the withdrawal Abandon is fire-and-forget: a durable provider that dies first keeps the id


# -- the turn: a carrier's receiving thread handles a message for an idle actor ---------------


class _Turn:
    """A message an actor lets a carrier's thread handle in its turn (`Actor.inline`)."""

    def __init__(self, n: int, hold: threading.Event | None = None) -> None:
        self.n = n
        self.hold = hold
        self.entered = threading.Event()  # set once a held one is being handled


class _Recorder(Actor):
    """Records `(n, thread name, on_actor_thread())` of each message; `_Turn`s may run in
    its turn; a `_Turn` with `hold` waits for it there; `"fail"` raises."""

    inline = frozenset({_Turn})

    def __init__(self) -> None:
        super().__init__()
        self.seen: list[tuple[Any, str, bool]] = []

    def on_receive(self, message: Any) -> Any:
        if message == "seen":
            return list(self.seen)
        if message == "fail" or (isinstance(message, _Turn) and message.n < 0):
            raise ValueError("asked to fail")
        n = message.n if isinstance(message, _Turn) else message
        self.seen.append((n, threading.current_thread().name, on_actor_thread()))
        if isinstance(message, _Turn) and message.hold is not None:
            message.entered.set()
            assert message.hold.wait(10)
        return None


@pytest.fixture
def recorder() -> Iterator[pykka.ActorRef[_Recorder]]:
    ref = _Recorder.start()
    yield ref
    ref.stop()


def _on(name: str, fn: Any) -> None:
    """Run `fn()` on a fresh thread named `name` (a carrier's receiving thread) and wait."""
    thread = threading.Thread(target=fn, name=name)
    thread.start()
    thread.join(10)
    assert not thread.is_alive()


def test_a_message_delivered_to_an_idle_actor_is_handled_on_the_delivering_thread(
    recorder: pykka.ActorRef[_Recorder],
) -> None:
    _on("rr-test-carrier", lambda: deliver(recorder, _Turn(1)))

    assert [(1, "rr-test-carrier", True)] == recorder.ask("seen", timeout=5)
    assert not on_actor_thread()  # (only while it held the turn)


def test_a_kind_the_actor_does_not_let_in_goes_to_its_own_thread(
    recorder: pykka.ActorRef[_Recorder],
) -> None:
    _on("rr-test-carrier", lambda: deliver(recorder, 2))

    [(n, thread, on_actor)] = recorder.ask("seen", timeout=5)
    assert (2, True) == (n, on_actor)
    assert "rr-test-carrier" != thread


def test_a_message_delivered_while_the_actor_is_busy_waits_and_keeps_the_order(
    recorder: pykka.ActorRef[_Recorder],
) -> None:
    held = _Turn(0, threading.Event())
    holder = threading.Thread(target=deliver, args=(recorder, held), name="rr-holder")
    holder.start()
    assert held.entered.wait(10)  # the holder handles it in the actor's turn, and waits
    _on("rr-test-carrier", lambda: [deliver(recorder, _Turn(n)) for n in (1, 2, 3)])
    recorder.tell(4)
    assert held.hold is not None
    held.hold.set()
    holder.join(10)

    seen = recorder.ask("seen", timeout=5)
    assert [0, 1, 2, 3, 4] == [n for n, _, _ in seen]
    assert "rr-holder" == seen[0][1]  # in its turn; the rest on the actor's own thread
    assert all(thread != "rr-test-carrier" for _, thread, _ in seen)


def test_tells_and_deliveries_from_one_thread_are_handled_in_the_order_sent(
    recorder: pykka.ActorRef[_Recorder],
) -> None:
    def mixed() -> None:
        for n in range(300):
            if n % 3 == 0:
                recorder.tell(n)
            else:
                deliver(recorder, _Turn(n))

    _on("rr-test-carrier", mixed)

    assert list(range(300)) == [n for n, _, _ in recorder.ask("seen", timeout=10)]


def test_a_handler_that_fails_in_the_turn_stops_the_actor_and_its_thread_ends() -> None:
    ref = _Recorder.start()
    actor_threads = {t for t in threading.enumerate() if t.name.startswith("_Recorder")}

    _on("rr-test-carrier", lambda: deliver(ref, _Turn(-1)))

    assert ref.actor_stopped.wait(5)
    for thread in actor_threads:
        thread.join(10)
        assert not thread.is_alive()
    with pytest.raises(pykka.ActorDeadError):
        deliver(ref, _Turn(1))
