"""The runtime seam in a real run: the stdlib's own objects, nothing wrapped."""

from __future__ import annotations

import os
import queue
import random
import threading
import time
import uuid

import pytest

from rr_actors._core import runtime
from rr_actors._core.actor import LateQueue
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.hlc import CLOCK


def test_a_real_run_uses_the_stdlib_objects_and_functions_themselves() -> None:
    real = {
        "Lock": threading.Lock,
        "RLock": threading.RLock,
        "Event": threading.Event,
        "Condition": threading.Condition,
        "SimpleQueue": queue.SimpleQueue,
        "Thread": threading.Thread,
        "Timer": threading.Timer,
        "monotonic": time.monotonic,
        "wall": time.time,
        "wall_ns": time.time_ns,
        "sleep": time.sleep,
        "urandom": os.urandom,
        "random": random.random,
        "get_ident": threading.get_ident,
        "current_thread": threading.current_thread,
    }

    assert real == {name: getattr(runtime, name) for name in real}
    assert not runtime.simulated()


def test_a_queue_made_in_a_real_run_is_of_its_own_class_with_the_stdlib_s_methods() -> None:
    late = LateQueue()

    assert LateQueue is type(late)
    assert queue.SimpleQueue.get is type(late).get


def test_a_simulation_replaces_exactly_the_seams() -> None:
    with pytest.raises(ValueError, match="exactly"):
        runtime.use({"Lock": threading.Lock})

    assert runtime.Lock is threading.Lock


def test_the_process_s_own_state_is_registered_for_a_simulation_to_give_each_process_its_own() -> (
    None
):
    registered = [obj for obj, _ in runtime.process_states()]

    assert DIRECTORY in registered
    assert CLOCK in registered


def test_a_thread_local_made_by_the_runtime_is_a_threading_local() -> None:
    assert any(isinstance(made, threading.local) for made in runtime.thread_locals())


def test_only_the_main_thread_of_a_real_run_handles_signals() -> None:
    elsewhere: list[bool] = []
    thread = threading.Thread(target=lambda: elsewhere.append(runtime.handles_signals()))
    thread.start()
    thread.join(10)

    assert threading.current_thread() is threading.main_thread()
    assert (True, [False]) == (runtime.handles_signals(), elsewhere)


def test_a_new_id_is_a_random_uuid4_in_its_canonical_form() -> None:
    ids = [runtime.new_id() for _ in range(2000)]

    for text in ids:
        parsed = uuid.UUID(text)
        assert (4, uuid.RFC_4122) == (parsed.version, parsed.variant)
        assert str(parsed) == text  # lower-case hex, dashes where uuid puts them
    assert len(set(ids)) == len(ids)
    assert {text[14] for text in ids} == {"4"}
    assert {text[19] for text in ids} == set("89ab")
