"""The simulation's scheduler: determinism, virtual time, choice points, deadlock reports."""

from __future__ import annotations

import contextvars
import gc
import threading
import time
import weakref
from collections.abc import Callable

import pykka
import pytest

from rr_actors import events, simulation
from rr_actors._core import runtime
from rr_actors._core.actor import Actor
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.serial import SerialExecutor
from rr_actors.simulation import _run
from tests.support.simulated import Interrupted, interrupted_when

pytest.importorskip("greenlet")  # (the simulation extra)


def workers(count: int, rounds: int) -> Callable[[], list[tuple[int, int, float]]]:
    """Threads that take turns on a lock and sleep between: who went when."""

    def main() -> list[tuple[int, int, float]]:
        lock = runtime.Lock()
        seen: list[tuple[int, int, float]] = []

        def work(number: int) -> None:
            for step in range(rounds):
                with lock:
                    seen.append((number, step, runtime.monotonic()))
                runtime.sleep(0.25 * (number + 1))  # allowed: virtual time, the work

        threads = [runtime.Thread(target=work, args=(n,), name=f"w{n}") for n in range(count)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        return seen

    return main


# -- determinism ---------------------------------------------------------------------------


def test_one_seed_gives_the_same_trace_hash_and_the_same_result_every_time() -> None:
    runs = [simulation.run(workers(3, 4), seed=7, preempt=0.3) for _ in range(3)]

    assert 1 == len({(run.hash, run.steps, repr(run.value)) for run in runs})


def test_other_seeds_choose_other_interleavings() -> None:
    orders = {
        tuple(n for n, _, _ in simulation.run(workers(3, 2), seed=seed, preempt=0.3).value)
        for seed in range(20)
    }

    assert len(orders) > 1


def woken_in(order: Callable[[list[int]], list[int]]) -> Callable[[], list[int]]:
    """Five threads wait on an event each; one step sets them all, in `order`: as a step
    that wakes the waiters of a set of callbacks, whose order is their addresses' and
    differs from process to process (and from run to run in one). Who ran first."""

    def main() -> list[int]:
        events = [runtime.Event() for _ in range(5)]
        ran: list[int] = []

        def wait(number: int) -> None:
            events[number].wait()
            ran.append(number)

        threads = [runtime.Thread(target=wait, args=(n,), name=f"w{n}") for n in range(5)]
        for thread in threads:
            thread.start()
        runtime.sleep(1)  # allowed: virtual time; every simulated thread waits by then
        for number in order(list(range(5))):
            events[number].set()  # (no choice point: preempt is 0)
        for thread in threads:
            thread.join()
        return ran

    return main


def test_the_order_in_which_one_step_wakes_threads_does_not_change_the_run() -> None:
    for seed in range(10):
        forward = simulation.run(woken_in(list), seed=seed, preempt=0.0)
        backward = simulation.run(woken_in(lambda n: n[::-1]), seed=seed, preempt=0.0)

        assert (forward.hash, forward.value) == (backward.hash, backward.value), seed


class _Letter:
    """Garbage in a cycle whose finalizer sends (as a `__del__` that puts on a queue or
    releases a lock, or a generator's `finally`): it runs when the collector finds it."""

    def __init__(self, box: runtime.SimpleQueue[int], number: int) -> None:
        self.box = box
        self.number = number
        self.me = self  # (a cycle: only the collector frees it)

    def __del__(self) -> None:
        self.box.put(self.number)


def letters() -> list[int]:
    """Two threads write letters and throw them away; a third reads what their finalizers
    send: which arrived, in which order."""
    box: runtime.SimpleQueue[int] = runtime.SimpleQueue()
    lock = runtime.Lock()

    def write(first: int) -> None:
        for number in range(first, first + 1500):
            _Letter(box, number)
            with lock:
                _ = [[n] for n in range(number % 7)]  # (more to collect, or less)
            runtime.sleep(0)  # allowed: a scheduler step (the run collects every `GC_STEPS`)

    threads = [runtime.Thread(target=write, args=(n,), name=f"w{n}") for n in (0, 1000)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    runtime.sleep(1)  # allowed: virtual time, for the last collection's letters
    read = []
    while not box.empty():
        read.append(box.get())
    return read


def test_when_the_garbage_collector_runs_does_not_change_the_run() -> None:
    before, enabled = gc.get_threshold(), gc.isenabled()
    gc.enable()
    try:
        runs = []
        for threshold in (1, 700, 50):  # (a collection at nearly every allocation, or later)
            gc.set_threshold(threshold, 10, 10)
            runs.append(simulation.run(letters, seed=3, preempt=0.3))
    finally:
        gc.set_threshold(*before)
        if not enabled:
            gc.disable()

    assert runs[0].value  # (some were collected while it ran)
    assert 1 == len({(run.hash, tuple(run.value)) for run in runs})


def test_a_trace_lists_each_step_and_each_note() -> None:
    def main() -> None:
        simulation.note("begins")
        runtime.sleep(2)  # allowed: virtual time
        simulation.note("ends")

    run = simulation.run(main, seed=1, trace=True)

    assert run.trace is not None
    assert [(0.0, 1, "begins"), (2.0, 1, "ends")] == [s for s in run.trace if s[2] != "MainThread"]
    assert run.steps == sum(1 for s in run.trace if s[2] == "MainThread")


def test_ids_and_random_values_come_from_the_seed() -> None:
    def main() -> tuple[str, float]:
        return runtime.new_id(), runtime.random()

    first, again, other = (simulation.run(main, seed=s).value for s in (3, 3, 4))

    assert first == again
    assert first[0] != other[0]
    assert first[1] != other[1]
    assert "4" == first[0][14]  # still a UUID4's form


# -- virtual time ------------------------------------------------------------------------


def test_time_is_virtual_an_hour_of_sleep_takes_no_real_time() -> None:
    def main() -> float:
        before = runtime.monotonic()
        runtime.sleep(3600.0)  # allowed: virtual time
        return runtime.monotonic() - before

    began = time.monotonic()
    run = simulation.run(main, seed=1, until=4000.0)

    assert 3600.0 == run.value == run.elapsed
    assert time.monotonic() - began < 30.0


def test_the_clock_jumps_to_each_deadline_in_turn() -> None:
    def main() -> list[tuple[str, float]]:
        fired: list[tuple[str, float]] = []
        done = runtime.Event()
        for name, delay in (("c", 3.0), ("a", 1.0), ("b", 2.0)):
            timer = runtime.Timer(delay, lambda n=name: fired.append((n, runtime.monotonic())))
            timer.daemon = True
            timer.start()
        cancelled = runtime.Timer(1.5, done.set)
        cancelled.start()
        cancelled.cancel()
        runtime.sleep(5.0)  # allowed: virtual time
        return fired

    start = 1000.0  # (the runtime's monotonic clock when a run begins)
    assert [("a", start + 1), ("b", start + 2), ("c", start + 3)] == simulation.run(
        main, seed=1
    ).value


def test_waits_with_a_timeout_run_out_in_virtual_time() -> None:
    def main() -> list[tuple[object, float]]:
        held = runtime.Lock()
        held.acquire()
        cond = runtime.Condition()
        queue = runtime.SimpleQueue()
        outcomes: list[tuple[object, float]] = []
        began = runtime.monotonic()
        outcomes.append((runtime.Event().wait(5.0), runtime.monotonic() - began))
        outcomes.append((held.acquire(timeout=2.0), runtime.monotonic() - began))
        with cond:
            outcomes.append((cond.wait(1.0), runtime.monotonic() - began))
        try:
            queue.get(timeout=0.5)
        except runtime.Empty:
            outcomes.append(("empty", runtime.monotonic() - began))
        return outcomes

    assert [(False, 5.0), (False, 7.0), (False, 8.0), ("empty", 8.5)] == simulation.run(
        main, seed=1
    ).value


def test_the_wall_clock_is_the_one_events_read_so_an_event_made_now_is_not_older_than_now() -> None:
    """`runtime.wall()` is `runtime.wall_ns()` in seconds, as `time.time()` is
    `time.time_ns()`'s: an event's `at` reads the latter (`hlc.CLOCK.wall`), and the event
    relay read its switch time from the former then (it drops what is older than its
    switch on; it reads the events' clock now). They were two sums rounded apart: at
    0.155676965 s in, `wall()` was 0.2 us ahead, and a second server started in the
    instant its supervisor was first subscribed to lost its `CatalogRestored` (the
    simulation's `split_brain`, found by `simheal`)."""

    def main() -> list[tuple[float, float, float]]:
        seen = []
        start = runtime.monotonic()
        for instant in (0.155676965, 0.610792999, 1.0, 2.5):
            runtime.sleep(instant - (runtime.monotonic() - start))  # allowed: virtual time
            made = events.ChildStarted("root", "erm", 1)
            seen.append((runtime.wall(), runtime.wall_ns() / 1e9, made.at))
        return seen

    for wall, wall_ns, at in simulation.run(main, seed=1).value:
        assert wall == wall_ns == at


def test_the_runtime_is_the_stdlib_again_after_a_run_and_the_process_state_too() -> None:
    before = DIRECTORY.local_peers(), DIRECTORY._lock

    def main() -> bool:
        return runtime.simulated() and runtime.Lock is not threading.Lock

    assert simulation.run(main, seed=1).value
    assert runtime.Lock is threading.Lock
    assert runtime.monotonic is time.monotonic
    assert not runtime.simulated()
    assert before == (DIRECTORY.local_peers(), DIRECTORY._lock)


# -- choice points -----------------------------------------------------------------------


def lost_updates(preempt: float, seeds: range) -> set[int]:
    """The final counts of two threads that each add 1, 20 times, reading and writing
    around an uncontended lock (a check-then-act race: they lose updates if preempted)."""

    def main() -> int:
        count = [0]
        lock = runtime.Lock()

        def add() -> None:
            for _ in range(20):
                seen = count[0]
                with lock:  # (taken by nobody else: a choice point, never a wait)
                    pass
                count[0] = seen + 1

        threads = [runtime.Thread(target=add, name=f"adder{n}") for n in range(2)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        return count[0]

    return {simulation.run(main, seed=seed, preempt=preempt).value for seed in seeds}


def test_a_real_thread_keeps_the_real_seams_while_a_simulation_runs() -> None:
    # A real thread still running when a run starts (the status desk's watchdog of an
    # earlier real registrar, in CI) called `runtime.sleep` and got the simulation's:
    # "a simulated object was used outside the simulation's threads".
    inside, done = threading.Event(), threading.Event()
    seen: list[object] = []

    def real() -> None:
        assert inside.wait(10)
        try:
            runtime.sleep(0.001)  # allowed: what is tested (a real sleep, not the run's)
            seen.append(abs(runtime.monotonic() - time.monotonic()) < 1.0)
            seen.append(type(runtime.Lock()) is type(threading.Lock()))
            seen.append(runtime.get_ident() == threading.get_ident())
        except BaseException as exc:
            seen.append(exc)
        finally:
            done.set()

    thread = threading.Thread(target=real, name="a real thread")
    thread.start()

    def body() -> None:
        inside.set()
        assert done.wait(10)  # (a real wait: the run's OS thread blocks meanwhile)

    simulation.run(body, seed=1)
    thread.join(10)

    assert [True, True, True] == seen


def test_without_preemption_a_thread_runs_until_it_blocks() -> None:
    assert {40} == lost_updates(0.0, range(20))


def test_choice_points_where_nothing_blocks_let_seeds_find_a_race() -> None:
    assert {c for c in lost_updates(0.2, range(20)) if c < 40}


# -- what stops a run --------------------------------------------------------------------


def test_a_notify_that_comes_while_a_waiter_lets_go_of_its_lock_is_not_lost() -> None:
    """`Condition.wait` releases its lock at a choice point: a notify may come there,
    before the waiter blocks (a lost wake-up would be a deadlock)."""

    def main() -> int:
        cond = runtime.Condition(runtime.Lock())
        woken = []

        def waiter() -> None:
            with cond:
                woken.append(cond.wait(timeout=None))

        thread = runtime.Thread(target=waiter, name="waiter")
        thread.start()
        for _ in range(50):
            with cond:
                cond.notify()
            if woken:
                break
        thread.join()
        return len(woken)

    assert all(1 == simulation.run(main, seed=s, preempt=0.5).value for s in range(100))


def test_a_wait_that_nothing_can_end_is_a_deadlock_that_says_who_waits_on_what() -> None:
    def main() -> None:
        first, second = runtime.Lock(), runtime.Lock()
        both = runtime.Event()

        def take(one: object, other: object) -> None:
            with one:  # type: ignore[attr-defined]
                both.wait(1.0)
                with other:  # type: ignore[attr-defined]
                    pass

        threads = [
            runtime.Thread(target=take, args=(first, second), name="left"),
            runtime.Thread(target=take, args=(second, first), name="right"),
        ]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()

    with pytest.raises(simulation.DeadlockError) as raised:
        simulation.run(main, seed=1)

    report = str(raised.value)
    assert "at virtual time 1 s" in report
    assert "'MainThread' (#1) waits in Thread.join" in report
    assert "'left' (#2) waits in Lock.acquire (made at tests/simulation" in report
    assert "taken by 'right' (#3)" in report
    assert "taken by 'left' (#2)" in report
    assert "test_scheduler.py:" in report
    assert "(take)" in report


def test_a_run_that_timers_keep_alive_past_its_limit_raises_a_limit_error() -> None:
    def main() -> None:
        ticker = SerialExecutor("ticker", every=(1.0, lambda: None))
        try:
            runtime.Event().wait()
        finally:
            ticker.close()

    with pytest.raises(simulation.LimitError, match="past its limit"):
        simulation.run(main, seed=1, until=60.0)


@pytest.mark.parametrize("timeout", [0.0, -1.0, -2.0])
def test_a_run_past_its_timeout_fails_at_once_with_simulation_error_even_a_negative_one(
    timeout: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A `timeout` of 0 or less does not wait (as `threading.Event.wait`'s): before, the
    run's lock took -1 for no bound (its caller hung), and below -1 raised `ValueError`,
    taken for an interrupt (the run cancelled, its caller waiting `CANCEL_TIMEOUT`)."""
    monkeypatch.setattr(_run, "CANCEL_TIMEOUT", 1.0)  # (not 30 s, without the fix)
    release = threading.Event()  # (a real one: the run's OS thread blocks on it for real)
    try:
        with pytest.raises(simulation.SimulationError, match="did not end within"):
            simulation.run(lambda: release.wait(60), seed=1, timeout=timeout)
    finally:
        release.set()
        for thread in threading.enumerate():
            if thread.name.startswith("rr-simulation-"):
                thread.join(60)

    assert not runtime.simulated()  # (the real seams back once its thread ended)


def test_an_interrupted_caller_gets_its_interrupt_once_the_run_was_cancelled_and_ended() -> None:
    began, cleaned = threading.Event(), []

    def main() -> None:
        began.set()  # (a real event: the test's thread waits on it)
        try:
            while True:  # (for ever, in virtual time)
                runtime.sleep(0.001)  # allowed: virtual time
        finally:
            cleaned.append(runtime.simulated())  # (as the run is dropped: still simulated)

    with interrupted_when(began), pytest.raises(Interrupted):
        simulation.run(main, seed=1, until=1e9, max_steps=10**12)

    assert [True] == cleaned  # (its finally ran before the interrupt reached the caller)
    assert not runtime.simulated()  # (the real seams back)
    assert not [t for t in threading.enumerate() if t.name.startswith("rr-simulation-")]


def test_a_second_interrupt_in_the_handling_of_the_first_still_cancels_the_run() -> None:
    """A second interrupt pending as the first is raised (a test's timeout that came with
    the Ctrl-C) is raised inside the first one's handling; the run is cancelled all the
    same, and has ended when the caller gets the first (CI, stop 78: the cancel was skipped,
    the run went on after its caller for good and every later simulation in the process
    failed). Both signals are sent together; if the second was handled alone first (its
    sender descheduled between the two under load), the try is made again."""
    waiting = _run._Ended.wait.__code__  # (the caller waits on the run, not in its start)
    for _ in range(5):
        began = threading.Event()

        def main(began: threading.Event = began) -> None:
            began.set()  # (a real event: the test's thread waits on it)
            while True:  # (for ever, in virtual time)
                runtime.sleep(0.001)  # allowed: virtual time

        before = set(threading.enumerate())  # (an earlier test's run may still be ending)
        interrupting = interrupted_when(began, twice=True, waiting_in=waiting)
        with interrupting as handled, pytest.raises(KeyboardInterrupt) as raised:
            simulation.run(main, seed=1, until=1e9, max_steps=10**12)
        left = [t for t in set(threading.enumerate()) - before if t.name.startswith("rr-sim")]
        if [name for name, _ in handled] == ["SIGINT", "SIGUSR1"]:
            break

    assert ["SIGINT", "SIGUSR1"] == [name for name, _ in handled]
    assert isinstance(handled[1][1], Interrupted)  # (the second, raised in the first's handling)
    assert isinstance(raised.value, Interrupted)  # (the first, once the run ended)
    assert [] == left
    assert not runtime.simulated()


def test_what_the_main_task_raises_is_raised_with_the_seed() -> None:
    def main() -> None:
        raise KeyError("lost")

    with pytest.raises(KeyError) as raised:
        simulation.run(main, seed=42)

    assert any("seed 42" in note for note in raised.value.__notes__)


def test_an_exception_that_ends_a_thread_is_in_the_run_s_errors(
    caplog: pytest.LogCaptureFixture,
) -> None:
    def main() -> None:
        thread = runtime.Thread(target=lambda: 1 / 0, name="divider")
        thread.start()
        thread.join()

    run = simulation.run(main, seed=1)

    assert ("divider: ZeroDivisionError: division by zero",) == run.errors
    assert "simulated thread divider (seed 1) ended" in caplog.text


def test_threads_left_waiting_when_a_run_ends_are_ended_after_it_outside_its_trace() -> None:
    ran: list[str] = []

    def main() -> None:
        def wait_for_ever() -> None:
            try:
                runtime.Event().wait()
            finally:
                ran.append("finally")
                simulation.note("too late")  # (the run is over: not in its trace)

        runtime.Thread(target=wait_for_ever, name="forever", daemon=True).start()
        runtime.sleep(1.0)  # allowed: virtual time

    run = simulation.run(main, seed=1, trace=True)

    assert ["finally"] == ran
    assert run.trace is not None
    assert [] == [step for step in run.trace if step[2] == "too late"]
    assert () == run.errors


class _Held:
    """Something only a waiting thread's frame holds."""


def test_what_a_thread_left_waiting_held_is_freed_after_the_run() -> None:
    """A greenlet left suspended when its OS thread ends is never freed (greenlet's "a cycle
    of greenlets is a leak"): each run would keep its actors and catalogs for good."""
    held: list[weakref.ref[_Held]] = []

    def main() -> None:
        def wait_for_ever() -> None:
            thing = _Held()
            held.append(weakref.ref(thing))
            runtime.Event().wait()

        runtime.Thread(target=wait_for_ever, name="forever", daemon=True).start()
        runtime.sleep(1.0)  # allowed: virtual time

    simulation.run(main, seed=1)
    gc.collect()

    assert [None] == [ref() for ref in held]


# -- the simulated threads' own state ----------------------------------------------------

_MINE = runtime.local()


def test_each_simulated_thread_has_its_own_thread_local_contents() -> None:
    def main() -> list[tuple[str, str]]:
        seen: list[tuple[str, str]] = []

        def mark(name: str) -> None:
            _MINE.name = name
            runtime.sleep(1.0)  # allowed: virtual time (the others run and mark meanwhile)
            seen.append((name, _MINE.name))

        threads = [runtime.Thread(target=mark, args=(n,), name=n) for n in "abc"]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        return sorted(seen)

    assert [("a", "a"), ("b", "b"), ("c", "c")] == simulation.run(main, seed=1, preempt=0.5).value
    assert not hasattr(_MINE, "name")  # (this real thread's: untouched)


@pytest.mark.parametrize("preempt", [0.0, 1.0])
def test_a_thread_that_ended_leaves_its_thread_local_contents_to_nobody(preempt: float) -> None:
    # (the contents are swapped only when another thread runs than the one whose they are)
    def main() -> list[object]:
        seen: list[object] = []

        def first() -> None:
            _MINE.name = "first"  # (and ends with it)

        def second() -> None:
            seen.append(getattr(_MINE, "name", None))
            _MINE.name = "second"
            runtime.sleep(0.0)  # allowed: virtual time (a step of its own again: its contents kept)
            seen.append(_MINE.name)

        for target in (first, second):
            thread = runtime.Thread(target=target)
            thread.start()
            thread.join()
        seen.append(getattr(_MINE, "name", None))  # (the main thread's: none)
        return seen

    assert [None, "second", None] == simulation.run(main, seed=1, preempt=preempt).value


class _Doubler(Actor):
    def on_receive(self, message: int) -> int:
        return 2 * message


_VARIABLE: contextvars.ContextVar[str] = contextvars.ContextVar("_VARIABLE", default="unset")


def test_each_simulated_thread_starts_with_context_variables_of_its_own() -> None:
    def main() -> list[tuple[str, str]]:
        seen: list[tuple[str, str]] = []

        def first() -> None:
            _VARIABLE.set("first")
            runtime.sleep(1.0)  # allowed: virtual time
            seen.append(("first", _VARIABLE.get()))

        def second() -> None:
            runtime.sleep(0.5)  # allowed: virtual time (after `first` set its own)
            seen.append(("second", _VARIABLE.get()))

        _VARIABLE.set("main")
        threads = [runtime.Thread(target=body) for body in (first, second)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        return [*seen, ("main", _VARIABLE.get())]

    assert [("second", "unset"), ("first", "first"), ("main", "main")] == simulation.run(
        main, seed=1
    ).value


def test_actors_run_as_simulated_threads_and_leave_the_real_registry_alone() -> None:
    def main() -> tuple[list[int], int]:
        refs = [_Doubler.start() for _ in range(3)]
        answers = [ref.ask(n) for n, ref in enumerate(refs)]
        registered = len(pykka.ActorRegistry.get_all())
        for ref in refs:
            ref.stop()
        return answers, registered

    assert ([0, 2, 4], 3) == simulation.run(main, seed=1).value
    assert [] == pykka.ActorRegistry.get_all()


def test_a_simulation_does_not_run_inside_another() -> None:
    def main() -> None:
        simulation.run(lambda: None, seed=2)

    with pytest.raises(simulation.SimulationError, match="already runs"):
        simulation.run(main, seed=1)


CHOICE_POINTS = 20_000


def steps_of(preempt: float) -> int:
    """Steps of a run whose one thread passes `CHOICE_POINTS` choice points (an
    uncontended lock taken and let go: two each) and never blocks."""

    def main() -> None:
        lock = runtime.Lock()
        for _ in range(CHOICE_POINTS // 2):
            lock.acquire()
            lock.release()

    return simulation.run(main, seed=3, preempt=preempt).steps


def test_a_thread_yields_at_a_choice_point_with_the_odds_of_preempt() -> None:
    yields = steps_of(0.05) - 1  # (its first step is its start)

    assert 1 == steps_of(0.0)
    assert CHOICE_POINTS + 1 <= steps_of(1.0)  # (every choice point, its start's too)
    assert 850 <= yields <= 1150  # 1,000 expected; the binomial's spread is 31
