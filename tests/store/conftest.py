"""Fixtures of the store tests: the forkserver context, run-and-kill, a manual save clock."""

from __future__ import annotations

import contextlib
import multiprocessing
import multiprocessing.connection
import multiprocessing.context
import multiprocessing.forkserver
import os
import signal
from collections.abc import Callable
from typing import Any

import pytest

from rr_actors._store import saver as _persistence
from tests.support.persisting import ManualTimers, RunAndKill


@pytest.fixture(scope="session")
def context() -> multiprocessing.context.ForkServerContext:
    """The forkserver context, its server started before any leak check.

    The server preloads what every child imports (the registrar, and the crash-consistency
    worker's module with pytest), so a child starts by a fork: imported in each child, they
    took 2-3 s of CPU apiece, and fifty kills took over the test's 300 s ceiling at load 14.
    """
    ctx = multiprocessing.get_context("forkserver")
    assert isinstance(ctx, multiprocessing.context.ForkServerContext)
    preload = ["rr_actors", "rr_actors._registrar", "rr_actors._store.saver", "cloudpickle"]
    ctx.set_forkserver_preload([*preload, "tests.store.test_saver"])
    multiprocessing.forkserver.ensure_running()
    return ctx


@pytest.fixture
def run_and_kill(context: multiprocessing.context.ForkServerContext) -> RunAndKill:
    """`run_and_kill(target, *args, messages=1)`: run `target(*args, conn)` in a child,
    receive `messages` messages from it, SIGKILL it, and return the messages."""

    def run(target: Callable[..., None], *args: Any, messages: int = 1) -> list[Any]:
        parent_end, child_end = context.Pipe()
        process = context.Process(target=target, args=(*args, child_end), daemon=True)
        process.start()
        child_end.close()
        received = []
        try:
            for _ in range(messages):
                assert parent_end.poll(30), "the child did not report in time"
                received.append(parent_end.recv())
        finally:
            assert process.pid is not None
            with contextlib.suppress(ProcessLookupError):
                os.kill(process.pid, signal.SIGKILL)
            process.join(10)
            parent_end.close()
        assert process.exitcode == -signal.SIGKILL
        return received

    return run


@pytest.fixture
def timers(monkeypatch: pytest.MonkeyPatch) -> ManualTimers:
    manual = ManualTimers()
    monkeypatch.setattr(_persistence, "timer_factory", manual)
    return manual
