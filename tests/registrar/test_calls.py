"""Tests of `rr_actors/_registrar/calls.py`: the call protocol on the caller's thread.

One attempt's states (`TestCallAttempt`, without threads), a plain call's outcome recorded
before the registrar's next message (`TestOutcomes`), timeouts and providers that die
(`TestTimeouts`, rule 17), and calls racing a stop, a give-up, a retry (`TestRaces`).
"""

from __future__ import annotations

import asyncio
import itertools
import signal
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pykka
import pytest

import rr_actors as rr
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.membership import Membership
from rr_actors._registrar.calls import BACKLOG
from rr_actors._registrar.messages import Load
from rr_actors.testing import (
    AttemptState,
    CallAttempt,
    actor_ref,
    call_futures,
    catalog_snapshot,
    crash,
    expect_restart,
    intercept,
    pending_work,
    run_on_actor,
)
from tests.registrar.conftest import Starter
from tests.support.gating import GatedLoad

# -- for TestCallAttempt -------------------------------------------------------------------

SENT = AttemptState.SENT


RECORDING = AttemptState.RECORDING


ANSWERED = AttemptState.ANSWERED


FAILED = AttemptState.FAILED


WITHDRAWN = AttemptState.WITHDRAWN


LOAD_ERROR = rr.ResourceLoadError(
    (rr.ErrorFrame("prov", "leaf", "ValueError", "bad request", traceback=""),)
)


PROVIDER_DIED = rr.RegistrarUnavailableError("registrar 'prov' died")


STOPPED = rr.RegistrarStoppedError("registrar 'cons' stopped during the call")


NOT_WRITTEN = rr.CatalogWriteError("state/cons.db", "disk full")


STEPS: dict[str, Callable[[CallAttempt], AttemptState]] = {
    "sent": CallAttempt.sent,  # the caller: its Load leaves
    "answer": lambda a: a.answer("loaded"),  # the answering thread (a plain call)
    "take": CallAttempt.take,  # the actor, a durable call's answer: commit it
    "committed": lambda a: a.settle("loaded"),  # the actor: the record is on disk
    "not kept": lambda a: a.settle(error=NOT_WRITTEN),  # the actor: the write failed
    "load error": lambda a: a.fail(LOAD_ERROR),  # the answering thread: load raised
    "provider died": lambda a: a.fail(PROVIDER_DIED),  # the answering thread
    "stop": lambda a: a.fail(STOPPED),  # the actor stops: it fails durable calls in flight
    "timeout": CallAttempt.withdraw,  # the caller's time runs out (or it is interrupted)
}


TIMED_OUT = "timed out"  # the caller withdrew: CallTimeoutError, the id given back


WAITS = "waits"  # the caller waits on (for the commit)


ROWS: list[tuple[str, list[tuple[str, AttemptState]], Any]] = [
    # -- a plain call: the answering thread hands the answer to the caller, who records it
    ("plain: answered", [("sent", SENT), ("answer", ANSWERED)], "loaded"),
    ("plain: load error", [("sent", SENT), ("load error", FAILED)], LOAD_ERROR),
    ("plain: provider died", [("sent", SENT), ("provider died", FAILED)], PROVIDER_DIED),
    ("plain: timeout", [("sent", SENT), ("timeout", WITHDRAWN)], TIMED_OUT),
    (
        "plain: timeout, then the answer (dropped: the caller gave the id back)",
        [("sent", SENT), ("timeout", WITHDRAWN), ("answer", WITHDRAWN)],
        TIMED_OUT,
    ),
    (
        "plain: the answer, then the timeout (the answer won: the caller reads it)",
        [("sent", SENT), ("answer", ANSWERED), ("timeout", ANSWERED)],
        "loaded",
    ),
    (
        "plain: timeout, then the provider died (not a failure: withdrawn)",
        [("sent", SENT), ("timeout", WITHDRAWN), ("provider died", WITHDRAWN)],
        TIMED_OUT,
    ),
    (
        "plain: an error, then the timeout (a failed call is not withdrawn)",
        [("sent", SENT), ("load error", FAILED), ("timeout", FAILED)],
        LOAD_ERROR,
    ),
    (
        "plain: interrupted before its Load left",
        [("timeout", WITHDRAWN), ("sent", WITHDRAWN)],
        TIMED_OUT,
    ),
    # -- a durable call: the actor takes the answer, commits it, then settles the attempt
    (
        "durable: answered",
        [("sent", SENT), ("take", RECORDING), ("committed", ANSWERED)],
        "loaded",
    ),
    (
        "durable: the answer cannot be written",
        [("sent", SENT), ("take", RECORDING), ("not kept", FAILED)],
        NOT_WRITTEN,
    ),
    ("durable: load error", [("sent", SENT), ("load error", FAILED)], LOAD_ERROR),
    ("durable: provider died", [("sent", SENT), ("provider died", FAILED)], PROVIDER_DIED),
    ("durable: timeout", [("sent", SENT), ("timeout", WITHDRAWN)], TIMED_OUT),
    (
        "durable: timeout, then the answer (not kept: the actor drops it)",
        [("sent", SENT), ("timeout", WITHDRAWN), ("take", WITHDRAWN)],
        TIMED_OUT,
    ),
    (
        "durable: the timeout while it is committed (the caller waits for the commit)",
        [("sent", SENT), ("take", RECORDING), ("timeout", RECORDING)],
        WAITS,
    ),
    (
        "durable: the timeout while it is committed, then the commit",
        [("sent", SENT), ("take", RECORDING), ("timeout", RECORDING), ("committed", ANSWERED)],
        "loaded",
    ),
    (
        "durable: the registrar stops and dies while it commits (its holder settles it)",
        [("sent", SENT), ("take", RECORDING), ("stop", RECORDING), ("not kept", FAILED)],
        NOT_WRITTEN,
    ),
    (
        "durable: the registrar stops before the Load left (nothing is sent)",
        [("stop", FAILED), ("sent", FAILED)],
        STOPPED,
    ),
    (
        "durable: the registrar stops after the Load left, then the answer (dropped)",
        [("sent", SENT), ("stop", FAILED), ("take", FAILED), ("timeout", FAILED)],
        STOPPED,
    ),
    (
        "durable: timeout, then the registrar stops (withdrawn stays withdrawn)",
        [("sent", SENT), ("timeout", WITHDRAWN), ("stop", WITHDRAWN), ("take", WITHDRAWN)],
        TIMED_OUT,
    ),
    (
        "durable: answered, then a late failure changes nothing",
        [("sent", SENT), ("take", RECORDING), ("committed", ANSWERED), ("stop", ANSWERED)],
        "loaded",
    ),
]


def _outcome(attempt: CallAttempt) -> Any:
    """What the caller gets, as `Calls.call` reads it once it stops waiting."""
    if attempt.state is WITHDRAWN:
        return TIMED_OUT
    if not attempt.wait(0):
        return WAITS
    try:
        return attempt.get(timeout=0)
    except rr.RrError as exc:
        return exc


# -- for TestOutcomes ----------------------------------------------------------------------


class Pair:
    def __init__(self) -> None:
        uid = uuid.uuid4().hex[:8]
        self.provider = rr.ResourceRegistrar.start(f"prov-{uid}")
        self.consumer = rr.ResourceRegistrar.start(f"cons-{uid}")
        self.provider.register_server("leaf", load=lambda r: f"got {r}", unload=_no_unload)

    def call(self, request: object, **kwargs: object) -> rr.Query:
        return self.consumer.call(self.provider.name, "leaf", request, **kwargs)  # type: ignore[arg-type]


def _no_unload(_request: object, _response: object) -> None:
    return None


# -- for TestTimeouts ----------------------------------------------------------------------

QUERY_ID = "0b4f8b8e-9a1e-4c55-8f43-2a7f3b1d6e10"


class _AnswerThenTimeout(CallAttempt):
    """A caller's future whose bounded wait runs out just after its answer arrived."""

    def wait(self, timeout=None):
        if timeout is None:
            return super().wait()
        assert super().wait(10)  # the answer lands...
        return False  # ...as the caller's wait runs out


# -- for TestRaces -------------------------------------------------------------------------


def _in_thread(fn: Callable[[], Any]) -> tuple[threading.Thread, list[Any]]:
    outcome: list[Any] = []

    def run() -> None:
        try:
            outcome.append(fn())
        except Exception as exc:  # the test inspects what was raised
            outcome.append(exc)

    thread = threading.Thread(target=run)
    thread.start()
    return thread, outcome


def _gated_server(registrar: rr.ResourceRegistrar) -> tuple[threading.Event, threading.Event]:
    """A server `slow` whose load waits for the returned gate; `entered` is set on entry."""
    load = GatedLoad(threading.Event(), threading.Event(), lambda request: f"loaded {request}")
    registrar.register_server("slow", load=load, unload=lambda r, s: None)
    return load.started, load.gate


def _wait_for(condition: Callable[[], bool], timeout: float = 5.0) -> bool:
    """Ask `condition()` again until it holds (each ask is a round trip to an actor)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
    return False


def _left_behind(registrar: rr.ResourceRegistrar) -> tuple[set[str], set[str]]:
    """Query ids the registrar still expects an answer for, and ones notices wait for."""
    work = pending_work(registrar, timeout=10)
    return set(work.answers_due), set(work.parked_notices)


def _blocked_in_wait(ident: int) -> bool:
    """Whether the thread `ident` blocks in a future's wait (its innermost frame)."""
    frame = sys._current_frames().get(ident)
    return frame is not None and frame.f_code is CallAttempt._wait.__code__


def _busy(registrar: rr.ResourceRegistrar) -> tuple[threading.Event, pykka.Future[bool]]:
    """Keep the registrar's actor busy until the returned gate is set (a slow provider)."""
    gate = threading.Event()
    return gate, run_on_actor(registrar, lambda: gate.wait(10))


class _ErrorAsTheWaitRunsOut(CallAttempt):
    """A caller's attempt whose wait runs out while an error answer is being set."""

    def __init__(self) -> None:
        super().__init__()
        self.erring = threading.Event()
        self.withdrawn = threading.Event()

    def wait(self, timeout: float | None = None) -> bool:
        if timeout is None:
            return super().wait()
        assert self.erring.wait(10)  # the error answer is on its way...
        return False  # ...as the caller's wait runs out

    def withdraw(self) -> AttemptState:
        state = super().withdraw()
        self.withdrawn.set()
        return state

    def fail(self, error: BaseException) -> AttemptState:
        self.erring.set()
        assert self.withdrawn.wait(10)  # the caller withdraws first
        return super().fail(error)


class _ErrorLandsAsTheWaitRunsOut(CallAttempt):
    """The error answer has settled the attempt as the caller's wait runs out."""

    def __init__(self) -> None:
        super().__init__()
        self.erring = threading.Event()  # the attempt failed (the error is in it)

    def wait(self, timeout: float | None = None) -> bool:
        if timeout is None:
            return super().wait()
        assert self.erring.wait(10)
        return False  # the caller's wait runs out; its withdraw() will lose

    def fail(self, error: BaseException) -> AttemptState:
        state = super().fail(error)
        self.erring.set()
        return state


class _CommitRacesTheTimeout(CallAttempt):
    """A durable caller's attempt whose wait runs out while the registrar commits its answer."""

    def __init__(self) -> None:
        super().__init__()
        self.reserved = threading.Event()  # the registrar took it, to commit the answer
        self.tried = threading.Event()  # the caller tried to withdraw it

    def take(self) -> AttemptState:
        taken = super().take()
        self.reserved.set()
        assert self.tried.wait(10)  # the caller's time runs out before the commit
        return taken

    def wait(self, timeout: float | None = None) -> bool:
        if timeout is None:
            return super().wait()
        assert self.reserved.wait(10)
        return False

    def withdraw(self) -> AttemptState:
        state = super().withdraw()
        self.tried.set()
        return state


class TestCallAttempt:
    """One call attempt's state machine, driven without threads (`CallAttempt`).

    Each row is one order in which the parties of a call act: its caller (`sent`, and
    `withdraw` when its time runs out), the thread that brings the answer (`answer` for a
    plain call, an error or a provider's death as `fail`), and its registrar's actor (`take`
    and `settle` for a durable call's answer, `fail` when it stops). Each step names the
    state the transition must return (what that party acts on), and the row ends with what
    the caller gets. The threads themselves race in `TestRaces` and
    `TestTimeouts`; here every interleaving is written out.
    """

    @pytest.mark.parametrize(
        ("steps", "expected"), [row[1:] for row in ROWS], ids=[r[0] for r in ROWS]
    )
    def test_each_party_acts_on_the_state_its_transition_returns(
        self, steps: list[tuple[str, AttemptState]], expected: Any
    ) -> None:
        attempt = CallAttempt()
        assert AttemptState.SENDING is attempt.state

        returned = [(step, STEPS[step](attempt)) for step, _ in steps]

        assert steps == returned
        assert expected == _outcome(attempt)

    def test_an_attempt_nobody_settled_keeps_its_caller_waiting(self) -> None:
        attempt = CallAttempt()
        attempt.sent()

        assert not attempt.wait(0)
        with pytest.raises(pykka.Timeout):
            attempt.get(timeout=0)

    @pytest.mark.parametrize(
        "settled_by",
        [["answer"], ["load error"], ["take", "committed"], ["take", "not kept"], ["timeout"]],
    )
    def test_an_attempt_is_settled_once_whatever_comes_after(self, settled_by: list[str]) -> None:
        attempt = CallAttempt()
        attempt.sent()
        for step in settled_by:
            STEPS[step](attempt)
        settled = attempt.state

        for step in ["answer", "take", "committed", "not kept", "load error", "stop", "timeout"]:
            assert settled is STEPS[step](attempt)
        assert settled is attempt.state


class TestOutcomes:
    """A plain call's answer is recorded before its registrar's next message, without a wake
    of its own.

    The caller hands the answer over (`DueAnswers.outcomes`, see `_registrar/calls.py`); the
    registrar actor takes the outcomes waiting before every message it handles, and is woken
    for them only when something waits: a failure, a notice held back for that answer, a
    dependency's answer, or a full backlog.
    """

    @pytest.fixture
    def pair(self) -> Iterator[Pair]:
        made = Pair()
        yield made
        made.consumer.stop()
        made.provider.stop()

    def test_answers_are_recorded_before_the_next_message_and_wake_nobody_on_their_own(
        self,
        pair: Pair,
    ) -> None:
        pair.call("first")  # (its client is started: the calls below ask the actor nothing)
        steps: list[str] = []
        intercept(pair.consumer, "client_loaded", before=lambda _m: steps.append("client_loaded"))
        intercept(pair.consumer, "take_outcomes", before=lambda _m: steps.append("take_outcomes"))
        intercept(pair.consumer, "client_queries", before=lambda _m: steps.append("client_queries"))

        queries = [pair.call("shared") for _ in range(3)]
        assert [] == steps  # nothing woke the consumer's actor

        held = pair.consumer.client_queries()

        assert ["client_loaded"] * 3 + ["client_queries"] == steps
        assert {q.id for q in queries} <= {q.id for q in held}

    def test_a_provider_is_monitored_both_ways_by_the_first_call_of_a_life_only(
        self, pair: Pair, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        # issue 71 item 5: each call asked the membership again (three monitors a hit), which
        # keeps them for the process's life: the caller's two as it opens its client, the
        # provider's once a life; a restart is still heard (rule 20: guarded by test_tree's
        # test_a_restart_wakes_only_the_manager_processes_that_monitor_it)
        asked: list[tuple[str, ...]] = []
        monitor = Membership.monitor

        def counted(membership: Membership, watcher: str, *targets: str) -> None:
            asked.append((watcher, *targets))
            monitor(membership, watcher, *targets)

        monkeypatch.setattr(Membership, "monitor", counted)
        for _ in range(3):
            pair.call("shared")

        consumer, provider = pair.consumer.name, pair.provider.name
        assert sorted([(consumer, provider), (provider, consumer), (provider, consumer)]) == sorted(
            asked
        )  # the caller's two, the provider's one, all at the first call

    def test_an_unload_right_after_a_call_finds_its_record(self, pair: Pair) -> None:
        for _ in range(20):
            query = pair.call("shared")
            pair.consumer.unload(query.id)

        assert [] == pair.provider.server_queries("leaf")
        assert () == catalog_snapshot(pair.consumer).clients

    def test_a_full_backlog_of_answers_wakes_the_registrar(self, pair: Pair) -> None:
        pair.call("first")
        woken = threading.Event()
        intercept(pair.consumer, "take_outcomes", before=lambda _m: woken.set())

        for _ in range(BACKLOG - 1):
            pair.call("shared")
        assert not woken.is_set()
        pair.call("shared")

        assert woken.wait(5)

    def test_a_status_notice_that_overtakes_the_answer_is_delivered_once_the_caller_has_it(
        self,
        pair: Pair,
    ) -> None:
        # The caller is held between its answer and handing it over; meanwhile the provider
        # sends a status about that query, which the consumer holds back (its answer is
        # due). Handing the answer over must wake the consumer: `send_status` waits for the
        # delivery, and nothing else would come.
        answered, release, notice_held = threading.Event(), threading.Event(), threading.Event()

        class HeldAfterItsAnswer(CallAttempt):
            def wait(self, timeout: float | None = None) -> bool:
                done = super().wait(timeout)
                answered.set()
                assert release.wait(5)
                return done

        updates: list[rr.StatusUpdate] = []
        pair.call("first")  # (its client is started)
        intercept(pair.consumer, "status_notice", after=lambda _m: notice_held.set())
        with ThreadPoolExecutor(2) as pool, call_futures(pair.consumer, HeldAfterItsAnswer):
            query_id = str(uuid.uuid4())
            call = pool.submit(
                pair.call, "watched", query_id=query_id, on_status=lambda _q, u: updates.append(u)
            )
            assert answered.wait(5)
            sent = pool.submit(
                pair.provider.send_status, query_id, rr.Status.UPDATE, "hi", timeout=5
            )
            assert notice_held.wait(5)
            release.set()

            assert query_id == call.result(5).id
            sent.result(5)  # delivered (it raises CallTimeoutError otherwise)
        assert ["hi"] == [u.message for u in updates]


class TestTimeouts:
    """Timeouts on blocking calls, and calls to registrars that die (DESIGN rule 17)."""

    pytestmark = pytest.mark.both_apis  # the rules, against the async API too (conftest)

    def test_a_call_whose_load_hangs_raises_call_timeout_error(
        self, make_registrar, serve, gated_load
    ):
        provider, consumer = make_registrar("provider"), make_registrar("consumer")
        serve(provider, "leaf", gated_load(wait=20))

        with pytest.raises(rr.CallTimeoutError) as info:
            consumer.call(provider.name, "leaf", "x", timeout=0.3)

        assert isinstance(info.value, TimeoutError)

    def test_the_default_timeout_comes_from_the_registrar_config(
        self, make_registrar, serve, gated_load
    ):
        provider, consumer = (
            make_registrar("provider"),
            make_registrar("consumer", call_timeout=0.3),
        )
        serve(provider, "leaf", gated_load(wait=20))
        began = time.monotonic()

        with pytest.raises(rr.CallTimeoutError):
            consumer.call(provider.name, "leaf", "x")

        assert time.monotonic() - began < 5.0

    def test_a_load_that_completes_after_its_caller_timed_out_is_released(
        self, make_registrar, serve, gated_load, eventually
    ):
        provider, consumer = make_registrar("provider"), make_registrar("consumer")
        stuck = gated_load(wait=20)
        leaf = serve(provider, "leaf", stuck)
        with pytest.raises(rr.CallTimeoutError):
            consumer.call(provider.name, "leaf", "x", timeout=0.3)

        stuck.gate.set()

        assert leaf.unloaded.wait(5)
        assert [("x", "x")] == leaf.unloads
        # the unload callback has run; the registrar drops the row when it hears so
        assert eventually(lambda: () == catalog_snapshot(provider).resources)
        assert () == catalog_snapshot(consumer).clients

    def test_a_timed_out_waiter_does_not_take_the_resource_from_a_patient_caller(
        self, make_registrar, serve, gated_load, eventually
    ):
        provider, consumer = make_registrar("provider"), make_registrar("consumer")
        stuck = gated_load(wait=20)
        leaf = serve(provider, "leaf", stuck)
        with ThreadPoolExecutor(1) as pool:
            patient = pool.submit(consumer.call, provider.name, "leaf", "x", timeout=20)
            assert stuck.started.wait(5)
            with pytest.raises(rr.CallTimeoutError):
                consumer.call(provider.name, "leaf", "x", timeout=0.3)
            stuck.gate.set()
            query = patient.result(timeout=20)

        def held() -> list[str]:  # (the timed-out id's release is on its way: under CI's
            return [q.id for q in provider.server_queries("leaf")]  # load it came after)

        assert eventually(lambda: [query.id] == held())
        assert [query] == consumer.client_queries()
        assert [] == leaf.unloads

    def test_a_timed_out_call_inside_a_load_leaves_no_dependency_behind(
        self, make_registrar, serve, gated_load, eventually
    ):
        provider, consumer = make_registrar("provider"), make_registrar("consumer")
        stuck = gated_load(wait=20)
        slow = serve(provider, "slow", stuck)

        def impatient(request):
            return provider.call(provider.name, "slow", request, timeout=0.3)

        serve(provider, "composite", impatient)
        with pytest.raises(rr.ResourceLoadError) as info:
            consumer.call(provider.name, "composite", "x", timeout=10)
        stuck.gate.set()

        assert "CallTimeoutError" == info.value.stack[0].exc_type
        assert slow.unloaded.wait(5)

        def empty() -> bool:
            snapshot = catalog_snapshot(provider)
            return ((), ()) == (snapshot.resources, snapshot.clients)

        assert eventually(empty)  # the registrar drops the rows once it hears of the unload

    def test_an_unload_whose_callback_hangs_raises_call_timeout_error(self, make_registrar, gates):
        provider, consumer = make_registrar("provider"), make_registrar("consumer")
        gate = gates()
        provider.register_server("leaf", load=lambda r: r, unload=lambda r, s: gate.wait(20))
        query = consumer.call(provider.name, "leaf", "x")

        with pytest.raises(rr.CallTimeoutError):
            consumer.unload(query.id, timeout=0.3)

    def test_unregister_server_with_a_hanging_unload_raises_call_timeout_error(
        self, make_registrar, gates
    ):
        provider, consumer = make_registrar("provider"), make_registrar("consumer")
        gate = gates()
        provider.register_server("leaf", load=lambda r: r, unload=lambda r, s: gate.wait(20))
        consumer.call(provider.name, "leaf", "x")

        with pytest.raises(rr.CallTimeoutError):
            provider.unregister_server("leaf", timeout=0.3)

    def test_a_call_in_flight_to_a_registrar_that_dies_fails_at_once(
        self, make_registrar, serve, gated_load
    ):
        provider, consumer = make_registrar("provider"), make_registrar("consumer")
        stuck = gated_load(wait=20)
        serve(provider, "leaf", stuck)
        with ThreadPoolExecutor(1) as pool:
            call = pool.submit(consumer.call, provider.name, "leaf", "x", timeout=30)
            assert stuck.started.wait(5)
            began = time.monotonic()

            crash(provider)

            assert isinstance(call.exception(timeout=10), rr.RegistrarUnavailableError)
            assert time.monotonic() - began < 10.0

    @pytest.mark.parametrize("timeout", [0, -1.0, True, "1"])
    def test_an_invalid_timeout_is_a_config_error(self, make_registrar, serve, timeout):
        provider = make_registrar("provider")
        serve(provider, "leaf")

        with pytest.raises(rr.ConfigError):
            provider.call(provider.name, "leaf", "x", timeout=timeout)

    def test_retrying_a_timed_out_call_with_its_query_id_gets_the_resource(
        self, make_registrar, serve, gated_load, arrived
    ):
        provider, consumer = make_registrar("provider"), make_registrar("consumer")
        stuck = gated_load(wait=20)
        leaf = serve(provider, "leaf", stuck)
        with pytest.raises(rr.CallTimeoutError):
            consumer.call(provider.name, "leaf", "x", timeout=0.3, query_id=QUERY_ID)
        with ThreadPoolExecutor(1) as pool:
            retry = pool.submit(
                consumer.call, provider.name, "leaf", "x", timeout=10, query_id=QUERY_ID
            )
            assert arrived(provider, [QUERY_ID, QUERY_ID])  # the retry joined the running load
            stuck.gate.set()
            query = retry.result(timeout=20)

        assert (QUERY_ID, "x") == (query.id, query.response)
        assert [QUERY_ID] == [q.id for q in provider.server_queries("leaf")]
        assert 1 == len(leaf.loads)

    def test_a_huge_finite_timeout_waits_and_a_non_finite_one_is_refused(self, served_pair):
        provider, consumer, _leaf = served_pair

        query = consumer.call(provider.name, "leaf", "x", timeout=1e300)  # beyond a lock's wait
        consumer.unload(query.id, timeout=1e300)
        for timeout in (float("inf"), float("nan")):
            with pytest.raises(rr.ConfigError, match="timeout"):
                consumer.call(provider.name, "leaf", "x", timeout=timeout)
        assert [] == consumer.client_queries()

    @pytest.mark.thread_only("replaces the caller's future class in this process")
    def test_an_answer_that_lands_as_the_wait_times_out_is_taken_not_lost(self, served_pair):
        provider, consumer, _leaf = served_pair

        with call_futures(consumer, _AnswerThenTimeout):
            query = consumer.call(provider.name, "leaf", "x", timeout=1.0)

        assert [query.id] == [q.id for q in consumer.client_queries()]
        assert [query.id] == [q.id for q in provider.server_queries("leaf")]
        consumer.unload(query.id)
        assert [] == provider.server_queries("leaf")


class TestRaces:
    """Calls racing a stop, a give-up, a retry, or a store that cannot hold a value."""

    @pytest.fixture
    def started(self, named_registrars: Starter) -> Starter:
        return named_registrars  # (conftest's)

    def test_stopping_a_provider_fails_the_calls_waiting_on_its_loads_at_once(
        self, started: Any
    ) -> None:
        provider, consumer = started("erm"), started("app")
        entered, gate = _gated_server(provider)
        try:
            thread, outcome = _in_thread(
                lambda: consumer.call(provider.name, "slow", 1, timeout=30)
            )
            assert entered.wait(5)
            began = time.monotonic()
            provider.stop(timeout=5)
            thread.join(5)

            assert [rr.RegistrarStoppedError] == [type(o) for o in outcome]
            assert time.monotonic() - began < 5.0  # not the call's 30 s timeout
        finally:
            gate.set()

    def test_stopping_a_durable_consumer_fails_its_call_in_flight_and_frees_the_id(
        self, started: Any, tmp_path: Path
    ) -> None:
        provider = started("erm")
        consumer = started("app", backup_path=tmp_path / "app.db", save_on_modify=True)
        entered, gate = _gated_server(provider)
        thread, outcome = _in_thread(lambda: consumer.call(provider.name, "slow", 1, timeout=30))
        assert entered.wait(5)
        consumer.stop(timeout=5)
        thread.join(5)
        gate.set()

        assert [rr.RegistrarStoppedError] == [type(o) for o in outcome]
        catalog_snapshot(provider)  # its invariants hold
        assert _wait_for(lambda: [] == provider.server_queries("slow"))

    def test_a_timed_out_call_held_during_setup_is_never_loaded(self, started: Any) -> None:
        consumer = started("app")
        name = f"erm-{uuid.uuid4().hex[:8]}"
        in_setup, finish_setup = threading.Event(), threading.Event()
        loads: list[Any] = []

        def setup(registrar: rr.ResourceRegistrar) -> None:
            in_setup.set()
            assert finish_setup.wait(10)
            registrar.register_server(
                "s", load=lambda r: loads.append(r) or r, unload=lambda r, s: None
            )

        starter, providers = _in_thread(lambda: rr.ResourceRegistrar.start(name, setup=setup))
        try:
            assert in_setup.wait(5)
            with pytest.raises(rr.CallTimeoutError):
                consumer.call(name, "s", 1, timeout=0.3)
            finish_setup.set()
            starter.join(5)
            provider = providers[0]
            later = consumer.call(name, "s", 2, timeout=5)  # a call after the give-up arrived

            assert ([2], [later.id]) == (loads, [q.id for q in provider.server_queries("s")])
        finally:
            finish_setup.set()
            starter.join(5)
            for provider in providers:
                if isinstance(provider, rr.ResourceRegistrar):
                    provider.stop()

    def test_a_retry_with_the_same_query_id_after_a_timeout_is_held_once_and_unloads(
        self,
        started: Any,
    ) -> None:
        provider, consumer = started("erm"), started("app")
        entered, gate = _gated_server(provider)
        with pytest.raises(rr.CallTimeoutError):
            consumer.call(provider.name, "slow", 1, timeout=0.3, query_id="q-1")
        assert entered.wait(5)
        gate.set()
        retried = consumer.call(provider.name, "slow", 1, timeout=5, query_id="q-1")

        assert ["q-1"] == [q.id for q in consumer.client_queries()]
        assert ["q-1"] == [q.id for q in provider.server_queries("slow")]
        consumer.unload(retried.id)
        assert [] == provider.server_queries("slow")

    def test_an_unpicklable_response_fails_that_load_and_a_durable_provider_keeps_serving(
        self, started: Any, tmp_path: Path
    ) -> None:
        provider = started("erm", backup_path=tmp_path / "erm.db", save_on_modify=True)
        consumer = started("app")
        provider.register_server("lock", load=lambda r: threading.Lock(), unload=lambda r, s: None)
        provider.register_server("echo", load=lambda r: r, unload=lambda r, s: None)

        with pytest.raises(rr.ResourceLoadError, match="cannot be pickled"):
            consumer.call(provider.name, "lock", 1, timeout=5)
        assert "fine" == consumer.call(provider.name, "echo", "fine", timeout=5).response
        assert [] == provider.server_queries("lock")

    def test_an_unpicklable_request_to_a_durable_provider_is_a_config_error(
        self, started: Any, tmp_path: Path
    ) -> None:
        provider = started("erm", backup_path=tmp_path / "erm.db", save_on_modify=True)
        consumer = started("app")
        provider.register_server("echo", load=lambda r: "ok", unload=lambda r, s: None)

        with pytest.raises(rr.ConfigError, match="cannot be pickled"):
            consumer.call(provider.name, "echo", threading.Lock(), timeout=5)
        assert provider.is_alive()

    def test_a_pykka_ask_that_arrives_while_the_registrar_stops_is_answered(
        self,
        started: Callable[..., rr.ResourceRegistrar],
    ) -> None:
        # The handle's stop() ends with pykka's `ref.stop()`, an ask; `op_stop` drains the
        # mailbox to fail whoever waits. An ask in that mailbox must hear, not be dropped.
        registrar = started("stopping")
        gate = threading.Event()
        busy = run_on_actor(registrar, lambda: gate.wait(10))
        ref = actor_ref(registrar)
        stopper = threading.Thread(target=registrar.stop)
        stopper.start()
        assert _wait_for(lambda: ref.actor_inbox.qsize() >= 1)  # the stop's request is queued
        asked = ref.ask("anything", block=False)  # queued behind the stop

        gate.set()

        assert busy.get(timeout=10) is True
        stopper.join(10)
        assert not stopper.is_alive()
        with pytest.raises(pykka.ActorDeadError):
            asked.get(timeout=10)

    @pytest.mark.parametrize("missed", [False, True], ids=["wakes_the_wait", "missed_by_the_wait"])
    def test_a_call_interrupted_by_ctrl_c_leaves_nothing_behind(
        self,
        started: Callable[..., rr.ResourceRegistrar],
        missed: bool,
    ) -> None:
        # The interrupted caller never records its answer: it withdraws the call (withdraws its
        # attempt, tells its registrar, sends the provider an Abandon) before the exception
        # leaves `call`. Its answer, when it comes, is dropped. `missed`: the SIGINT is taken
        # by another thread while the caller blocks in its wait, so the wait is not woken
        # (CPython checks for signals between bytecodes: one that lands as the caller's
        # thread goes to block, after its last check, is missed the same way); the caller
        # raises it at its next check, not when the call's wait ends.
        assert threading.current_thread() is threading.main_thread()
        provider, consumer = started("provider"), started("consumer")
        entered, release = threading.Event(), threading.Event()

        def load(request: Any) -> Any:
            entered.set()
            assert release.wait(10)
            return f"loaded {request}"

        provider.register_server("slow", load=load, unload=lambda _request, _response: None)

        calling = threading.Event()
        calling.set()
        caller = threading.main_thread().ident
        assert caller is not None
        sent: list[float] = []

        def interrupt() -> None:
            assert entered.wait(10)
            taker = caller
            if missed:  # (seen while this thread runs: the caller's frame waits on its lock)
                assert _wait_for(lambda: _blocked_in_wait(caller), 10)
                taker = threading.get_ident()
            if calling.is_set():  # (a call that failed otherwise is reported, not interrupted)
                sent.append(time.monotonic())
                signal.pthread_kill(taker, signal.SIGINT)

        interrupter = threading.Thread(target=interrupt)
        interrupter.start()
        try:
            with pytest.raises(KeyboardInterrupt):
                consumer.call(provider.name, "slow", "x", timeout=30)
        finally:
            calling.clear()
        interrupted = time.monotonic()
        interrupter.join(10)
        assert interrupted - sent[0] < 5.0  # not the call's 30 s timeout, nor the load's 10 s
        release.set()
        second = consumer.call(provider.name, "slow", "x", timeout=10)  # the same load's answer

        assert [second.id] == [q.id for q in provider.server_queries("slow")]
        assert [second.id] == [q.id for q in consumer.client_queries()]
        assert (set(), set()) == _left_behind(consumer)
        provider.send_status(second.id, rr.Status.WARNING, "hot", timeout=5)
        provider.unregister_server("slow", timeout=5)
        assert [] == consumer.client_queries()

    @pytest.mark.parametrize("durable", [False, True], ids=["plain", "save_on_modify"])
    def test_a_timed_out_retry_of_a_held_id_leaves_both_ends_agreeing(
        self, started: Callable[..., rr.ResourceRegistrar], tmp_path: Path, durable: bool
    ) -> None:
        provider = started("provider")
        config = {"backup_path": tmp_path / "c.db", "save_on_modify": True} if durable else {}
        consumer = started("consumer", **config)
        provider.register_server("leaf", load=lambda r: f"loaded {r}", unload=lambda _q, _r: None)
        first = consumer.call(provider.name, "leaf", "x")
        gate, busy = _busy(provider)  # the provider answers the retry only after its timeout

        with pytest.raises(rr.CallTimeoutError):
            consumer.call(provider.name, "leaf", "x", query_id=first.id, timeout=0.3)
        gate.set()
        assert busy.get(timeout=10) is True

        provider_holds = [q.id for q in provider.server_queries("leaf")]  # after Load, Abandon
        assert provider_holds == [q.id for q in consumer.client_queries()]  # after the answer
        assert (set(), set()) == _left_behind(consumer)

    def test_an_error_answer_that_loses_to_the_timeout_leaves_nothing_behind(
        self, started: Callable[..., rr.ResourceRegistrar], monkeypatch: pytest.MonkeyPatch
    ) -> None:
        provider, consumer = started("provider"), started("consumer")

        def load(request: Any) -> Any:
            raise ValueError(request)

        provider.register_server("bad", load=load, unload=lambda _request, _response: None)

        with call_futures(consumer, _ErrorAsTheWaitRunsOut), pytest.raises(rr.CallTimeoutError):
            consumer.call(provider.name, "bad", "x", timeout=5)

        assert [] == consumer.client_queries()
        assert (set(), set()) == _left_behind(consumer)

    def test_an_answer_recorded_as_the_consumer_stops_is_given_back(
        self, started: Callable[..., rr.ResourceRegistrar], monkeypatch: pytest.MonkeyPatch
    ) -> None:
        # The caller tells its registrar the answer while the actor, stopping, is past its
        # last look at the mailbox (it took the stop message) but not yet marked stopped:
        # the tell lands after the loop ended, and the id must still be given back.
        provider, consumer = started("provider"), started("consumer")
        entered, release = threading.Event(), threading.Event()
        in_stop, resume = threading.Event(), threading.Event()

        def load(request: Any) -> Any:
            entered.set()
            assert release.wait(10)
            return request

        provider.register_server("slow", load=load, unload=lambda _request, _response: None)

        def paused_stop(_: Any) -> None:
            in_stop.set()
            assert resume.wait(10)

        intercept(consumer, "stop_drained", before=paused_stop)
        outcome: list[Any] = []
        caller = threading.Thread(
            target=lambda: outcome.append(consumer.call(provider.name, "slow", "x", timeout=10))
        )
        caller.start()
        assert entered.wait(10)
        stopper = threading.Thread(target=consumer.stop)
        stopper.start()
        assert in_stop.wait(10)
        release.set()
        caller.join(10)  # its _ClientLoaded went into the mailbox of an actor still "alive"
        resume.set()
        stopper.join(10)

        assert isinstance(outcome[0], rr.Query)
        assert [] == provider.server_queries("slow")

    def test_stopping_a_durable_consumer_before_its_callers_load_leaves_leaves_no_id_behind(
        self,
        started: Callable[..., rr.ResourceRegistrar],
        tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch,
    ) -> None:
        # A durable call's Load leaves once its pending record is committed. If the consumer's
        # stop runs just before the Load leaves, it fails the call and sends the provider an
        # Abandon *before* the Load: the Abandon finds nothing, the Load then adds the id. The
        # answer reaches the consumer while it still stops; it must give the id back.
        provider = started("prov")
        other = started("other")
        consumer = started("cons", backup_path=tmp_path / "c.db", save_on_modify=True)
        unload_entered, unload_gate = threading.Event(), threading.Event()

        def sticky_unload(_request: Any, _response: Any) -> None:
            unload_entered.set()  # the consumer's op_stop is past its pending records
            assert unload_gate.wait(10)

        provider.register_server("leaf", load=lambda r: f"loaded {r}", unload=lambda _q, _r: None)
        provider.register_server("sticky", load=lambda r: r, unload=sticky_unload)
        held = other.call(provider.name, "leaf", "x")  # the consumer's Load will be a dedup hit
        consumer.call(provider.name, "sticky", "s")  # keeps the consumer's stop busy
        consumer.client_queries()  # (its client for leaf is started below, before the stop)

        qid = str(uuid.uuid4())
        expecting = threading.Event()

        def hold_load(load: Any) -> None:
            if load.query_id == qid:
                expecting.set()  # its record is committed; hold its Load until the stop ran
                assert unload_entered.wait(10)

        intercept(consumer, "send_load", before=hold_load)

        def call() -> rr.Query:
            return consumer.call(provider.name, "leaf", "x", query_id=qid, timeout=10)

        caller, outcome = _in_thread(call)
        assert expecting.wait(10)
        stopper, stopped = _in_thread(lambda: consumer.stop(timeout=20))
        caller.join(10)  # its Load is in the provider's mailbox
        assert [rr.RegistrarStoppedError] == [type(o) for o in outcome]
        provider.server_queries("leaf")  # the provider handled that Load (and answered it)
        unload_gate.set()  # the consumer's stop ends after it handled the answer
        stopper.join(20)

        assert [None] == stopped
        assert not consumer.is_alive()
        assert [held.id] == [q.id for q in provider.server_queries("leaf")]

    def test_a_failed_call_whose_error_races_the_timeout_is_not_withdrawn(
        self, started: Callable[..., rr.ResourceRegistrar], monkeypatch: pytest.MonkeyPatch
    ) -> None:
        # DESIGN/failure-semantics: "A call that *failed* is not withdrawn" (a retry with the
        # same id must find an id committed at a restarted provider). The error settles the
        # call's attempt as the caller's wait runs out: the caller's withdraw() then finds
        # it FAILED and raises its error; it must not withdraw the failed call (a second
        # `CallFailed` and an `Abandon`).
        provider, consumer = started("prov"), started("cons")

        def load(request: Any) -> Any:
            raise ValueError(request)

        provider.register_server("bad", load=load, unload=lambda _q, _r: None)
        abandons: list[str] = []
        intercept(provider, "abandon", before=lambda message: abandons.append(message.query_id))

        with (
            call_futures(consumer, _ErrorLandsAsTheWaitRunsOut),
            pytest.raises(rr.ResourceLoadError),
        ):
            consumer.call(provider.name, "bad", "x", query_id="q-failed", timeout=5)
        provider.server_queries("bad")  # whatever the caller sent the provider was handled

        assert [] == abandons

    def test_a_request_that_lands_as_op_stop_finishes_is_answered_not_left_to_time_out(
        self,
        started: Callable[..., rr.ResourceRegistrar],
    ) -> None:
        # stop(): ... reply, fail the waiting callers (drains the mailbox), then the actor
        # ends. Whatever is put between the drain and the end (a handle request whose
        # `is_alive()` check passed) must be refused (`on_late`), not handled by a registrar
        # whose servers, clients, saver and directory entry are gone, nor dropped.
        provider, consumer = started("prov"), started("cons")
        provider.register_server("leaf", load=lambda r: r, unload=lambda _q, _r: None)
        held = consumer.call(provider.name, "leaf", "x")
        in_gap, resume = threading.Event(), threading.Event()

        def pause(_: Any) -> None:
            in_gap.set()  # stop() drained the mailbox and the actor has not ended yet
            assert resume.wait(10)

        intercept(provider, "stop_drained", before=pause)
        stopper, stopped = _in_thread(lambda: provider.stop(timeout=10))
        assert in_gap.wait(10)
        inbox = actor_ref(provider).actor_inbox
        updater, outcome = _in_thread(lambda: provider.update_response(held.id, "new", timeout=3))
        assert _wait_for(lambda: inbox.qsize() >= 1)  # its request landed in the gap
        resume.set()
        updater.join(10)
        stopper.join(10)

        assert [None] == stopped
        assert [rr.RegistrarStoppedError] == [type(o) for o in outcome]

    def test_a_fetch_that_lands_after_its_client_ended_is_answered_not_left_to_time_out(
        self, started: Callable[..., rr.ResourceRegistrar], monkeypatch: pytest.MonkeyPatch
    ) -> None:
        # fetch_queries tells the cached ClientActor a `_FetchVia(reply)`. If the client ends
        # (its registrar stops) between the is_alive() checks and the put, the envelope goes
        # to ClientActor.on_late, the default `refuse`, which answers asks only: the reply is
        # dropped and fetch_queries waits out its whole timeout.
        provider, consumer = started("prov"), started("cons")
        provider.register_server("leaf", load=lambda r: r, unload=lambda _q, _r: None)
        consumer.call(provider.name, "leaf", "x")
        client = actor_ref(consumer, client=(provider.name, "leaf"))
        consumer.stop()
        monkeypatch.setattr(client, "is_alive", lambda: True)  # both checks passed just before

        with pytest.raises(rr.RrError) as raised:
            consumer.fetch_queries(provider.name, "leaf", timeout=2)
        assert not isinstance(raised.value, rr.CallTimeoutError)

    def test_a_durable_caller_whose_time_runs_out_as_its_answer_is_committed_gets_it(
        self,
        started: Callable[..., rr.ResourceRegistrar],
        tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch,
    ) -> None:
        # The registrar takes the caller's future before it commits the answer, so a caller
        # whose time runs out meanwhile reads the answer (there is no window in which a
        # committed answer is then withdrawn, which a crash could turn into a phantom record).
        provider = started("provider")
        consumer = started("consumer", backup_path=tmp_path / "c.db", save_on_modify=True)
        provider.register_server("leaf", load=lambda r: f"loaded {r}", unload=lambda _q, _r: None)
        with call_futures(consumer, _CommitRacesTheTimeout):
            query = consumer.call(provider.name, "leaf", "x", timeout=5)

        assert "loaded x" == query.response
        assert [query.id] == [q.id for q in consumer.client_queries()]
        assert [query.id] == [q.id for q in provider.server_queries("leaf")]

    def test_a_late_failure_of_a_withdrawn_attempt_leaves_the_retry_due_and_kept(
        self,
        started: Callable[..., rr.ResourceRegistrar],
        tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch,
    ) -> None:
        provider, other = started("prov"), started("other")
        consumer = started("cons", backup_path=tmp_path / "c.db", save_on_modify=True)
        unloading, gate = threading.Event(), threading.Event()

        def gated_unload(_request: Any, _response: Any) -> None:
            unloading.set()
            assert gate.wait(10)

        provider.register_server("leaf", load=lambda r: f"loaded {r}", unload=gated_unload)
        held = other.call(provider.name, "leaf", "x")
        unloader = threading.Thread(target=lambda: other.unload(held.id, timeout=20))
        unloader.start()
        assert unloading.wait(10)  # "x" is unloading: a Load for it is parked until it is gone

        qid = str(uuid.uuid4())
        retry_sent, stale_handled = threading.Event(), threading.Event()
        failures: list[Any] = []
        sent: list[Any] = []

        def send_load(message: Any) -> None:  # (on the caller's thread, as its Load leaves)
            if message.query_id == qid:
                sent.append(message.reply.attempt)
                if len(sent) == 2:
                    retry_sent.set()  # nothing is written first (presumed abort)

        def failed(message: Any) -> None:
            if message.query_id == qid:
                failures.append(message.attempt)
                if len(failures) == 2:  # the provider's error answer to the first attempt
                    stale_handled.set()

        def abandon(message: Any) -> None:
            if message.query_id == qid:  # the provider is slow to take the withdrawal
                assert retry_sent.wait(10)

        intercept(consumer, "send_load", after=send_load)
        intercept(consumer, "call_failed", after=failed)
        intercept(provider, "abandon", before=abandon)

        with pytest.raises(rr.CallTimeoutError):  # parked: the first attempt times out
            consumer.call(provider.name, "leaf", "x", query_id=qid, timeout=0.5)
        outcome: list[Any] = []
        retry = threading.Thread(
            target=lambda: outcome.append(
                consumer.call(provider.name, "leaf", "x", query_id=qid, timeout=20)
            )
        )
        retry.start()
        assert stale_handled.wait(10)
        assert failures[1] is sent[0]  # (a stale failure of the first attempt)

        try:
            # the retry's Load is out (parked at the provider): it is still due, nothing
            # of it written (its answer is committed before its caller gets it)
            assert qid not in [c.query.id for c in catalog_snapshot(consumer).clients]
        finally:
            gate.set()
            retry.join(20)
            unloader.join(20)
        assert [qid] == [q.id for q in outcome]
        assert [qid] == [q.id for q in consumer.client_queries()]

    def test_a_failed_retry_of_a_held_id_keeps_the_held_record(
        self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        def serve(registrar: rr.ResourceRegistrar) -> None:
            registrar.register_server(
                "leaf", load=lambda r: f"loaded {r}", unload=lambda _q, _r: None
            )

        name = f"prov-{uuid.uuid4().hex[:8]}"
        config = rr.RegistrarConfig(name=name, backup_path=tmp_path / "p.db", save_on_modify=True)
        provider = rr.ResourceRegistrar.start(config, setup=serve)
        consumer = rr.ResourceRegistrar.start(f"cons-{uuid.uuid4().hex[:8]}")
        restarted: list[rr.ResourceRegistrar] = []
        try:
            held = consumer.call(name, "leaf", "x")
            with expect_restart(name):  # (as a supervisor does)
                crash(provider)

            with pytest.raises(rr.RegistrarUnavailableError):  # an idempotent retry fails
                consumer.call(name, "leaf", "x", query_id=held.id, timeout=5)

            restarted.append(rr.ResourceRegistrar.start(config, setup=serve))
            at_provider = [q.id for q in restarted[0].server_queries("leaf")]
            at_consumer = [q.id for q in consumer.client_queries()]
            assert at_provider == at_consumer
            consumer.unload(held.id)
        finally:
            consumer.stop()
            for registrar in restarted:
                registrar.stop()


# -- for TestOverloadPause -----------------------------------------------------------------


class _RefusesEveryLoad:
    """A provider (a peer in this process's directory) that refuses every load for
    overload, telling when to ask again (`retry_after`; `None`: it does not say), and
    notes when each try came (`tries`, monotonic seconds); `answer_after`: seconds each
    refusal takes to come back (a slow link, or a loaded machine)."""

    def __init__(self, retry_after: float | None, answer_after: float = 0.0) -> None:
        self.name = f"full-{uuid.uuid4().hex[:8]}"
        self.retry_after, self.answer_after = retry_after, answer_after
        self.tries: list[float] = []

    def tell(self, message: Any) -> None:
        if not isinstance(message, Load):  # (a withdrawal: nothing is held)
            return
        self.tries.append(time.monotonic())
        refused = rr.errors.OverloadedError(
            "full", self.name, message.server, 1, retry_after=self.retry_after
        )
        if self.answer_after:
            threading.Timer(self.answer_after, message.reply.set_error, [refused]).start()
        else:
            message.reply.set_error(refused)

    deliver = tell


class TestOverloadPause:
    """Issue 53: a call refused for overload asks again after the pause its provider
    tells (`OverloadedError.retry_after`: when it expects a slot), not one it guesses;
    told a pause past its timeout, it gives up at once."""

    @pytest.fixture
    def refusing(self) -> Iterator[Callable[..., _RefusesEveryLoad]]:
        made: list[_RefusesEveryLoad] = []

        def make(retry_after: float | None, answer_after: float = 0.0) -> _RefusesEveryLoad:
            provider = _RefusesEveryLoad(retry_after, answer_after)
            DIRECTORY.register(provider)
            made.append(provider)
            return provider

        yield make
        for provider in made:
            DIRECTORY.unregister(provider, "stopped")

    @pytest.mark.thread_only("its provider is a peer of this process's directory")
    @pytest.mark.parametrize("awaited", [False, True], ids=["blocking", "awaited"])
    def test_a_refused_call_asks_again_after_the_pause_its_provider_tells(
        self, make_registrar, refusing, awaited: bool
    ):
        provider, consumer = refusing(0.5), make_registrar("consumer")

        def call() -> Any:
            if awaited:
                return asyncio.run(consumer.acall(provider.name, "leaf", "x", timeout=2.0))
            return consumer.call(provider.name, "leaf", "x", timeout=2.0)

        with pytest.raises(rr.errors.OverloadedError) as refused:
            call()

        assert 0.5 == refused.value.retry_after
        # at 0, 0.5, 1.0 and 1.5 s (then 0.5 s left: no more than the pause and an
        # answer's time); its own pauses (5 ms doubling to 100 ms) ask about 20 times
        assert 2 <= len(provider.tries) <= 4, provider.tries
        pauses = [b - a for a, b in itertools.pairwise(provider.tries)]
        assert all(pause >= 0.49 for pause in pauses), pauses

    @pytest.mark.thread_only("its provider is a peer of this process's directory")
    def test_a_provider_that_tells_no_pause_is_asked_again_after_a_doubling_one(
        self, make_registrar, refusing
    ):
        provider, consumer = refusing(None), make_registrar("consumer")

        with pytest.raises(rr.errors.OverloadedError):
            consumer.call(provider.name, "leaf", "x", timeout=1.0)

        assert len(provider.tries) > 3, provider.tries  # (5, 10, 20, 40, 80, 100 ms...)

    @pytest.mark.thread_only("its provider is a peer of this process's directory")
    def test_a_call_whose_refusals_come_slowly_is_refused_not_timed_out(
        self, make_registrar, refusing
    ):
        """Each refusal takes 0.6 s to come back (as under load): the call asks again only
        while twice that is left, so it ends with the provider's `OverloadedError`. (It
        kept 0.1 s for the last answer: its last try was cut off, a `CallTimeoutError`.)"""
        provider, consumer = refusing(None, answer_after=0.6), make_registrar("consumer")

        with pytest.raises(rr.errors.OverloadedError, match="full"):
            consumer.call(provider.name, "leaf", "x", timeout=2.0)

        assert 1 <= len(provider.tries) <= 2, provider.tries

    @pytest.mark.thread_only("its provider is a peer of this process's directory")
    def test_a_call_told_a_pause_past_its_timeout_gives_up_at_once(self, make_registrar, refusing):
        provider, consumer = refusing(30.0), make_registrar("consumer")

        with pytest.raises(rr.errors.OverloadedError, match="full"):
            consumer.call(provider.name, "leaf", "x", timeout=10.0)

        assert 1 == len(provider.tries)
