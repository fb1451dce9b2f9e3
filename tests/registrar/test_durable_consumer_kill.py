"""A durable consumer's manager process SIGKILLed while a call is on its way, then restarted.

Real manager processes under a supervisor (`state_dir`: `save_on_modify`), a real SIGKILL.
Code run in the consumer's process (`Supervisor.run_in`) holds its actor at one point of
the interleaving (the actor being slow there, as under load); the kill comes from the
test once shared events say the interleaving was reached.
"""

from __future__ import annotations

import sys
import threading
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.testing import SharedObjects
from tests.support.supervising import kill_and_wait_restarted

pytestmark = [
    pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals"),
    pytest.mark.usefixtures("by_value"),  # (tests/conftest.py)
]


def _provider_setup(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("leaf", load=lambda r: f"loaded {r}", unload=lambda _q, _r: None)


def _pair(
    supervisors: Callable[..., rr.Supervisor], tmp_path: Path
) -> tuple[rr.Supervisor, str, str]:
    uid = uuid.uuid4().hex[:8]
    p, c = f"p-{uid}", f"c-{uid}"
    sup = supervisors(
        [
            rr.ManagerSpec(p, _provider_setup, isolation="process"),
            rr.ManagerSpec(c, None, isolation="process", heartbeat=None),
        ],
        state_dir=tmp_path / "state",
    ).start()
    return sup, p, c


def _both_ends(sup: rr.Supervisor, p: str, c: str) -> tuple[list[str], list[str]]:
    held_at_provider = sup.run_in(p, lambda r: [q.id for q in r.server_queries("leaf")])
    held_by_consumer = sup.run_in(c, lambda r: [q.id for q in r.client_queries()])
    return held_at_provider, held_by_consumer


def test_a_durable_call_leaves_only_after_its_pending_record_is_committed(
    supervisors: Callable[..., rr.Supervisor], tmp_path: Path, process_helpers: SharedObjects
) -> None:
    # If the Load left before the pending record was committed, a dedup hit could be
    # answered (so the provider's release of an undelivered answer never fires) while the
    # record is not on disk yet; killed then, the restarted consumer would know nothing of
    # an id the provider holds for good (a restart is expected: no death watch).
    sup, p, c = _pair(supervisors, tmp_path)
    qid = str(uuid.uuid4())
    pending_reached = process_helpers.event()

    def arm(registrar: rr.ResourceRegistrar) -> None:
        import threading  # noqa: PLC0415 - runs in the consumer's process

        from rr_actors.testing import intercept  # noqa: PLC0415

        def busy_pending(message: Any) -> None:
            if message.record.query.id == qid:
                pending_reached.set()
                threading.Event().wait()  # busy until the process dies

        intercept(registrar, "pending", before=busy_pending)
        threading.Thread(
            target=lambda: registrar.call(p, "leaf", "x", query_id=qid, timeout=60), daemon=True
        ).start()

    sup.run_in(c, arm)
    assert pending_reached.wait(10)
    assert qid not in sup.run_in(p, lambda r: [q.id for q in r.server_queries("leaf")])
    kill_and_wait_restarted(sup, c)

    held_at_provider, held_by_consumer = _both_ends(sup, p, c)
    assert held_at_provider == held_by_consumer


def test_a_withdrawn_call_is_abandoned_at_its_provider_before_its_record_goes(
    supervisors: Callable[..., rr.Supervisor],
    tmp_path: Path,
    process_helpers: SharedObjects,
    eventually: Callable[..., bool],
) -> None:
    # A durable call's answer reaches the consumer; its actor is slow to take it, so the
    # caller's time runs out: the caller withdraws its call attempt. Its
    # pending record must stay on disk until the provider was told the Abandon: killed
    # just before that, the restarted consumer finds the record and gives the id back
    # (were the record gone, the provider would hold the id for good: a restart is
    # expected, so no death watch; the answer was delivered, so the provider's release
    # of an undelivered answer does not fire).
    sup, p, c = _pair(supervisors, tmp_path)
    qid = str(uuid.uuid4())
    reached = process_helpers.event()

    def arm(registrar: rr.ResourceRegistrar) -> None:
        import threading  # noqa: PLC0415 - runs in the consumer's process

        from rr_actors.testing import (  # noqa: PLC0415
            AttemptState,
            CallAttempt,
            call_futures,
            intercept,
        )

        claimed, answer_handled = threading.Event(), threading.Event()

        class Future(CallAttempt):
            def withdraw(self) -> AttemptState:
                state = super().withdraw()
                claimed.set()
                return state

        call_futures(registrar, Future)  # (until the process dies)

        def slow_loaded(message: Any) -> None:
            if message.record.query.id == qid:  # the actor is slow: the caller's time
                assert claimed.wait(30)  # runs out first, so it finds the call withdrawn

        def loaded(message: Any) -> None:
            if message.record.query.id == qid:
                answer_handled.set()

        intercept(registrar, "client_loaded", before=slow_loaded, after=loaded)

        def hold_withdrawal(query: Any) -> None:
            if query.id == qid:
                # the caller is about to tell the provider its Abandon; the actor has
                # handled the answer (and what the caller told it before this)
                assert answer_handled.wait(30)
                reached.set()
                threading.Event().wait()  # held until the process dies

        intercept(registrar, "withdraw", before=hold_withdrawal)

        def run() -> None:
            registrar.call(p, "leaf", "x", query_id=qid, timeout=1.0)

        threading.Thread(target=run, daemon=True).start()

    sup.run_in(c, arm)
    assert reached.wait(20)
    assert qid in sup.run_in(p, lambda r: [q.id for q in r.server_queries("leaf")])
    assert [] == sup.run_in(c, lambda r: [q.id for q in r.client_queries()])
    kill_and_wait_restarted(sup, c)

    # (the restarted consumer's Abandon travels on a connection of its own)
    assert eventually(lambda: ([], []) == _both_ends(sup, p, c), timeout=10)


def _gated_provider_setup(unloading: Any, gate: Any) -> Callable[[rr.ResourceRegistrar], None]:
    def setup(registrar: rr.ResourceRegistrar) -> None:
        def unload(_request: Any, _response: Any) -> None:
            unloading.set()
            assert gate.wait(30)

        registrar.register_server("leaf", load=lambda r: f"loaded {r}", unload=unload)

    return setup


def test_a_stale_failure_of_an_earlier_attempt_leaves_a_retrys_record_on_disk(
    supervisors: Callable[..., rr.Supervisor],
    tmp_path: Path,
    process_helpers: SharedObjects,
    eventually: Callable[..., bool],
) -> None:
    # The first attempt's Load is parked at the provider (its resource is unloading); the
    # caller's time runs out, it withdraws, and retries with the same query id. The
    # provider answers the parked Load with an error when the Abandon unparks it; that
    # error reaches the consumer as a `_CallFailed` of the first attempt after the retry
    # committed its pending record, and `_on_call_failed` removes that record. The retry's
    # answer then reaches the consumer, whose actor is slow to record it; killed then, the
    # restarted consumer has no record to give back, the provider holds the id.
    uid = uuid.uuid4().hex[:8]
    p, c = f"p-{uid}", f"c-{uid}"
    unloading, gate = process_helpers.event(), process_helpers.event()
    retry_pending, stale_handled = process_helpers.event(), process_helpers.event()
    answer_arrived = process_helpers.event()
    sup = supervisors(
        [
            rr.ManagerSpec(p, _gated_provider_setup(unloading, gate), isolation="process"),
            rr.ManagerSpec(c, None, isolation="process", heartbeat=None),
        ],
        state_dir=tmp_path / "state",
    ).start()
    qid = str(uuid.uuid4())
    app = sup.registrar(f"app-{uid}")
    held = app.call(p, "leaf", "x")

    def arm_provider(registrar: rr.ResourceRegistrar) -> None:
        from rr_actors.testing import intercept  # noqa: PLC0415 - runs in the provider's process

        def slow_abandon(message: Any) -> None:
            if message.query_id == qid:  # slow to take the withdrawal
                assert retry_pending.wait(30)

        intercept(registrar, "abandon", before=slow_abandon)

    def arm_consumer(registrar: rr.ResourceRegistrar) -> None:
        import threading  # noqa: PLC0415 - runs in the consumer's process

        from rr_actors.testing import intercept  # noqa: PLC0415

        seen = {"pending": 0, "failed": 0}

        def pending(message: Any) -> None:
            if message.record.query.id == qid:
                seen["pending"] += 1
                if seen["pending"] == 2:
                    retry_pending.set()

        def failed(message: Any) -> None:
            if message.query_id == qid:
                seen["failed"] += 1
                if seen["failed"] == 2:  # the provider's error answer to the first attempt
                    stale_handled.set()

        def loaded(message: Any) -> None:
            if message.record.query.id == qid:
                answer_arrived.set()
                threading.Event().wait()  # slow to record the retry's answer: killed first

        intercept(registrar, "pending", after=pending)
        intercept(registrar, "call_failed", after=failed)
        intercept(registrar, "client_loaded", before=loaded)

        def run() -> None:
            try:
                registrar.call(p, "leaf", "x", query_id=qid, timeout=1.0)
            except rr.CallTimeoutError:  # parked: the first attempt times out
                registrar.call(p, "leaf", "x", query_id=qid, timeout=60)

        threading.Thread(target=run, daemon=True).start()

    unloader = threading.Thread(target=lambda: app.unload(held.id, timeout=60))
    unloader.start()
    try:
        assert unloading.wait(10)  # "x" is unloading at the provider: Loads for it park
        sup.run_in(p, arm_provider)
        sup.run_in(c, arm_consumer)
        assert stale_handled.wait(20)
    finally:
        gate.set()
        unloader.join(30)
    assert answer_arrived.wait(20)  # the retry's answer was delivered to the consumer
    kill_and_wait_restarted(sup, c)

    # The retry's pending record survived the stale failure, so the restarted consumer
    # gives the id back (its Abandon travels on a connection of its own).
    assert eventually(lambda: ([], []) == _both_ends(sup, p, c), timeout=10)
