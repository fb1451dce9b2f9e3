"""Coroutine callbacks on the simulation: an asyncio loop on the virtual clock
(`rr_actors.simulation._loop`)."""

from __future__ import annotations

import asyncio
import gc
import logging
import shutil
import sys
import tempfile
from typing import Any

import pytest

import rr_actors as rr
from rr_actors import simulation
from rr_actors._core import runtime
from rr_actors.simulation import SimulationError

pytest.importorskip("greenlet")  # (the simulation extra)


def async_setup(registrar: rr.ResourceRegistrar) -> None:
    """A server whose `load` and `unload` are coroutines that sleep (virtual seconds)."""

    async def load(request: Any) -> Any:
        await asyncio.sleep(0.5)
        return f"slow {request}"

    async def unload(_query: Any, _response: Any) -> None:
        await asyncio.sleep(0.25)

    registrar.register_server("slow", load=load, unload=unload)


def calls() -> Any:
    """Two callers load from a coroutine server at once, then one unloads."""
    provider = rr.ResourceRegistrar.start("provider")
    app = rr.ResourceRegistrar.start("app")
    try:
        async_setup(provider)
        began = simulation.now()
        done: list[str] = []

        def caller(request: str) -> None:
            done.append(app.call("provider", "slow", request).response)

        threads = [runtime.Thread(target=caller, args=(request,)) for request in "ab"]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        loaded = simulation.now() - began
        [first, _] = app.client_queries()
        app.unload(first.id)
        return sorted(done), loaded, simulation.now() - began - loaded
    finally:
        app.stop()
        provider.stop()


def test_coroutine_callbacks_run_on_the_virtual_clock_and_replay_alike() -> None:
    """A server's coroutine `load` and `unload` run on the process's event loop in
    virtual time: two loads that each await 0.5 s take about 0.5 s together (one loop,
    no thread blocked), the unload's 0.25 s after them; the same seed, the same hash."""
    runs = [simulation.run(calls, seed=seed, timeout=30.0) for seed in (1, 2, 1)]
    for run in runs:
        responses, loaded, unloaded = run.value
        assert ["slow a", "slow b"] == responses
        assert 0.5 <= loaded < 0.6  # (two at once: not 1.0)
        assert 0.25 <= unloaded < 0.35
        assert () == tuple(run.errors)
    assert runs[0].hash == runs[2].hash
    assert runs[0].hash != runs[1].hash


def test_a_coroutine_callback_in_a_manager_process_runs_in_its_own_loop() -> None:
    """Each simulated process has its own loop (asyncio's running loop is per OS
    thread, and every simulated thread runs on one: the scheduler gives each task its
    own): a manager process's coroutine `load`, killed and restarted, runs again."""

    def scenario() -> Any:
        folder = tempfile.mkdtemp(prefix="rr-sim-loop-")
        network = simulation.SimulatedNetwork()
        try:
            spec = rr.ManagerSpec("provider", setup=async_setup, isolation="process")
            sup = rr.Supervisor(spec, state_dir=folder, network=network, name="root")
            sup.start()
            app = sup.registrar("app")
            try:
                first = app.call("provider", "slow", "x").response
                simulation.kill(sup.child("provider").pid)
                sup.wait_restarted("provider", timeout=10.0)
                again = app.call("provider", "slow", "y").response
                own = asyncio._get_running_loop() is None  # (the main thread runs none)
                return first, again, own
            finally:
                sup.stop()
                app.stop()
        finally:
            network.close()
            shutil.rmtree(folder, ignore_errors=True)

    for seed in range(3):
        run = simulation.run(scenario, seed=seed, timeout=60.0)
        assert (("slow x", "slow y", True), ()) == (run.value, tuple(run.errors)), f"seed {seed}"


def test_a_simulated_loop_refuses_what_needs_a_real_thread_or_file(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A simulated loop watches no file and starts no real thread: `add_reader` and
    `run_in_executor` (so `asyncio.to_thread`) raise `NotImplementedError` instead of
    leaving the virtual world; on a Python whose asyncio lacks the loop's hooks, making
    one raises `SimulationError` naming them."""

    def refusals() -> Any:
        loop = runtime.new_event_loop()
        refused = []
        try:
            for attempt in (
                lambda: loop.add_reader(0, print),
                lambda: loop.run_in_executor(None, print),
            ):
                try:
                    attempt()
                except NotImplementedError as exc:
                    refused.append(type(exc).__name__)
        finally:
            loop.close()
        return refused

    def without_hooks() -> str:
        try:
            runtime.new_event_loop()
        except SimulationError as exc:
            return str(exc)
        return "made"

    assert ["NotImplementedError"] * 2 == simulation.run(refusals, seed=1, timeout=30.0).value
    monkeypatch.delattr(asyncio.BaseEventLoop, "_write_to_self")
    told = simulation.run(without_hooks, seed=1, timeout=30.0).value
    assert "coroutine callbacks cannot be simulated" in told
    assert "_write_to_self" in told


def on_a_loop_of_its_own() -> Any:
    """A simulated loop run by a simulated thread (as `_core.loops` runs a process's)."""
    loop = runtime.new_event_loop()
    started = runtime.Event()

    def body() -> None:
        asyncio.set_event_loop(loop)
        loop.call_soon(started.set)
        loop.run_forever()

    runtime.Thread(target=body, daemon=True).start()
    started.wait()
    return loop


def test_a_coroutine_still_waiting_when_the_run_ends_is_closed_with_the_run() -> None:
    """A coroutine callback that waits when the run ends is closed at the run's end: its
    `finally` runs then, not later in whatever thread the garbage collector runs in, and
    no "Task was destroyed but it is pending" is logged (second review of session 6)."""
    ran: list[str] = []

    def scenario() -> None:
        loop = on_a_loop_of_its_own()

        async def waits() -> None:
            try:
                await asyncio.sleep(100.0)
            finally:
                ran.append("finally")

        loop.call_soon_threadsafe(loop.create_task, waits())
        runtime.sleep(1.0)  # allowed: virtual time

    logged: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = logged.append  # type: ignore[method-assign]
    logging.getLogger("asyncio").addHandler(handler)
    try:
        run = simulation.run(scenario, seed=1, timeout=30.0)
        assert ["finally"] == ran
        gc.collect()
    finally:
        logging.getLogger("asyncio").removeHandler(handler)
    assert ((), []) == (tuple(run.errors), [r.getMessage() for r in logged])


def test_each_loop_s_coroutines_see_their_own_async_generator_hooks() -> None:
    """asyncio's async generator hooks are per OS thread, as its running loop is: each
    simulated thread keeps its own, so a coroutine on the first of two loops registers
    its async generators with its own loop, not with the loop started last."""

    def scenario() -> Any:
        loops = [on_a_loop_of_its_own(), on_a_loop_of_its_own()]
        seen: list[bool] = []
        done = runtime.Event()

        async def probe() -> None:
            firstiter = sys.get_asyncgen_hooks().firstiter
            seen.append(getattr(firstiter, "__self__", None) is asyncio.get_running_loop())
            seen.append(asyncio.get_running_loop() is loops[0])
            done.set()

        loops[0].call_soon_threadsafe(loops[0].create_task, probe())
        done.wait()
        return seen

    for seed in range(3):
        assert [True, True] == simulation.run(scenario, seed=seed, timeout=30.0).value
