"""Replies and joins that status acknowledgements use from any thread."""

from __future__ import annotations

import logging
import threading
from typing import Any

import pytest

from rr_actors._core import runtime
from rr_actors._core.actor import OneShotFuture
from rr_actors._core.replies import (
    CallbackReply,
    SharedJoin,
    Steps,
    asked,
    on_own_thread,
    run_steps,
)
from rr_actors.errors import CallTimeoutError


def _race(parts: int) -> tuple[list[str], set[str]]:
    """Finish `parts` parts on as many threads while sealing: who ran `then`, who could."""
    fired: list[str] = []
    join = SharedJoin(lambda: fired.append(threading.current_thread().name))
    dones = [join.add() for _ in range(parts)]
    start = threading.Barrier(parts + 1)

    def finish(done: Any) -> None:
        start.wait(5)
        done()

    threads = [
        threading.Thread(target=finish, args=(done,), name=f"part-{n}")
        for n, done in enumerate(dones)
    ]
    for thread in threads:
        thread.start()
    start.wait(5)
    join.seal()  # races with the parts: fires on whichever thread ends it
    for thread in threads:
        thread.join(5)
    return fired, {t.name for t in threads} | {threading.current_thread().name}


def test_a_shared_join_fires_once_after_its_last_part_whatever_thread_finishes_it() -> None:
    for _ in range(200):
        fired, threads = _race(8)

        assert len(fired) == 1
        assert fired[0] in threads


def test_a_shared_join_waits_for_its_seal_and_fires_at_once_without_parts() -> None:
    fired: list[int] = []
    join = SharedJoin(lambda: fired.append(1))
    join.add()()
    assert fired == []  # not sealed: more parts may come
    join.seal()
    assert fired == [1]

    empty = SharedJoin(lambda: fired.append(2))
    empty.seal()
    assert fired == [1, 2]


def test_a_callback_reply_runs_its_continuation_for_the_first_answer_only() -> None:
    answers: list[tuple[Any, BaseException | None]] = []
    reply = CallbackReply(lambda value, error: answers.append((value, error)))

    reply.set_result(1)
    reply.set_error(RuntimeError("late"))
    reply.set_result(2)

    assert answers == [(1, None)]


def test_a_callback_reply_logs_what_its_continuation_raises_instead_of_raising_it(
    caplog: pytest.LogCaptureFixture,
) -> None:
    def broken(_value: Any, _error: BaseException | None) -> None:
        raise ValueError("boom")

    with caplog.at_level(logging.ERROR, logger="rr_actors"):
        CallbackReply(broken).set_result(None)  # the answering thread is not hurt

    assert "continuation raised" in caplog.text
    assert "boom" in caplog.text


def _two_waits(
    first: OneShotFuture[Any], second: OneShotFuture[Any], seen: list[Any]
) -> Steps[str]:
    """Steps that wait for two futures; what each wait was told goes to `seen`."""
    try:
        seen.append((yield first, None))
        seen.append((yield second, 0.0))  # (a deadline long past)
    except BaseException as exc:
        seen.append(type(exc).__name__)
        raise
    return "done"


def test_steps_run_on_a_thread_get_whether_each_future_settled_in_time() -> None:
    first: OneShotFuture[Any] = OneShotFuture()
    first.set(1)
    seen: list[Any] = []

    assert "done" == run_steps(_two_waits(first, OneShotFuture(), seen))
    assert [True, False] == seen


def test_an_interruption_of_a_wait_is_thrown_into_the_steps() -> None:
    class Interrupted(BaseException):
        pass

    class Interrupting(OneShotFuture[Any]):
        def _wait(self, timeout: float | None = None) -> bool:
            raise Interrupted

    seen: list[Any] = []

    with pytest.raises(Interrupted):
        run_steps(_two_waits(Interrupting(), OneShotFuture(), seen))
    assert ["Interrupted"] == seen


def test_an_interruption_before_the_wait_blocks_is_thrown_into_the_steps(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    class Interrupted(BaseException):
        pass

    def interrupted() -> float:  # (the driver reads the clock after the yield, to block)
        raise Interrupted

    def one_wait(seen: list[Any]) -> Steps[None]:
        try:
            yield OneShotFuture(), 1.0
        except BaseException as exc:
            seen.append(type(exc).__name__)
            raise

    seen: list[Any] = []
    monkeypatch.setattr(runtime, "monotonic", interrupted)

    with pytest.raises(Interrupted):
        run_steps(one_wait(seen))
    assert ["Interrupted"] == seen


def test_asked_raises_a_call_timeout_naming_the_operation_when_the_deadline_passed() -> None:
    with pytest.raises(CallTimeoutError, match=r"save_catalog\(\) timed out after 2 s"):
        run_steps(asked(OneShotFuture(), 0.0, 2.0, "save_catalog()"))


def test_on_own_thread_runs_the_function_on_a_thread_of_its_own_and_returns_its_result() -> None:
    names: list[str] = []

    result = run_steps(
        on_own_thread(lambda: names.append(threading.current_thread().name) or 5, "own")
    )

    assert (5, ["own"]) == (result, names)
