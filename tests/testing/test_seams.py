"""The testing seams (`rr_actors.testing.seams`): named steps that fail loudly when a name is
wrong, and snapshots."""

from __future__ import annotations

import threading
import uuid
from collections.abc import Iterator
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.testing import (
    STEPS,
    actor_ref,
    call_futures,
    intercept,
    pending_work,
    run_on_actor,
)


@pytest.fixture
def pair() -> Iterator[tuple[rr.ResourceRegistrar, rr.ResourceRegistrar]]:
    uid = uuid.uuid4().hex[:8]
    provider = rr.ResourceRegistrar.start(f"prov-{uid}")
    consumer = rr.ResourceRegistrar.start(f"cons-{uid}")
    provider.register_server("leaf", load=lambda r: f"loaded {r}", unload=lambda _q, _r: None)
    yield provider, consumer
    consumer.stop()
    provider.stop()


def test_an_unknown_step_name_is_a_config_error_not_a_silent_no_op(pair: Any) -> None:
    provider, _ = pair

    with pytest.raises(rr.ConfigError, match="no registrar step is named 'abandoned'") as caught:
        intercept(provider, "abandoned", before=lambda _: None)

    assert "'abandoned'; did you mean 'abandon'? (known: 'abandon', 'answer'," in str(caught.value)


def test_every_message_the_actor_handles_is_a_step_that_intercept_reaches(pair: Any) -> None:
    provider, consumer = pair
    seen: list[str] = []
    for step in ("load", "unload"):
        intercept(provider, step, before=lambda _m, step=step: seen.append(step))
    intercept(consumer, "release", before=lambda _m: seen.append("release"))

    query = consumer.call(provider.name, "leaf", "x")
    consumer.unload(query.id)

    assert ["load", "unload"] == [step for step in seen if step != "release"]
    assert "release" in seen  # (the handle asked its own actor for the unload)
    assert {"load", "unload", "abandon", "withdraw", "stop_drained"} <= STEPS


def test_closed_hooks_run_no_more(pair: Any) -> None:
    provider, consumer = pair
    loads: list[str] = []
    with intercept(provider, "load", after=lambda m: loads.append(m.query_id)):
        first = consumer.call(provider.name, "leaf", "x")
    consumer.call(provider.name, "leaf", "y")

    assert [first.id] == loads


def test_run_on_actor_holds_the_registrar_until_the_function_returns(pair: Any) -> None:
    provider, consumer = pair
    gate, pause = threading.Event(), threading.Event()
    loads: list[str] = []
    intercept(provider, "load", before=lambda m: loads.append(m.query_id))
    held = run_on_actor(provider, lambda: gate.wait(10))
    outcome: list[Any] = []
    caller = threading.Thread(
        target=lambda: outcome.append(consumer.call(provider.name, "leaf", 1, timeout=10))
    )
    caller.start()
    inbox = actor_ref(provider).actor_inbox
    for _ in range(5000):  # bounded: until the Load is queued behind the held function
        if inbox.qsize() >= 1:
            break
        pause.wait(0.001)

    assert [] == loads  # queued, not handled
    gate.set()
    caller.join(10)
    assert held.get(timeout=10) is True
    assert ["loaded 1"] == [q.response for q in outcome]
    assert [q.id for q in outcome] == loads


def test_pending_work_lists_a_caller_waiting_for_a_load(pair: Any) -> None:
    provider, consumer = pair
    entered, gate = threading.Event(), threading.Event()

    def load(request: Any) -> Any:
        entered.set()
        assert gate.wait(10)
        return request

    provider.register_server("slow", load=load, unload=lambda _q, _r: None)
    qid = str(uuid.uuid4())
    caller = threading.Thread(target=lambda: consumer.call(provider.name, "slow", 1, query_id=qid))
    caller.start()
    assert entered.wait(10)

    assert {qid: 1} == dict(pending_work(provider).waiting_loads)
    assert {qid} == pending_work(consumer).answers_due
    gate.set()
    caller.join(10)
    assert not pending_work(provider).waiting_loads
    assert not pending_work(consumer).answers_due


def test_call_futures_rejects_a_class_that_is_not_a_one_shot_future(pair: Any) -> None:
    _, consumer = pair

    with pytest.raises(rr.ConfigError, match="OneShotFuture"):
        call_futures(consumer, threading.Event)  # type: ignore[arg-type]


def test_the_seams_that_need_this_process_refuse_a_remote_registrar_clearly() -> None:
    remote = rr.testing.RemoteRegistrar("elsewhere", address=None)  # type: ignore[arg-type]

    with pytest.raises(rr.ConfigError, match="registrar of this process"):
        intercept(remote, "load", before=lambda _: None)  # type: ignore[arg-type]
    with pytest.raises(rr.ConfigError, match="registrar of this process"):
        actor_ref(remote)  # type: ignore[arg-type]
