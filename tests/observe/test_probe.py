"""Reading a live registrar's catalog for the observer (`rr_actors.observe._probe`): a hostile
`__repr__` stops nothing (issue 21, bug 6)."""

from __future__ import annotations

import sys
import threading
import time
import traceback
from typing import Any

import cloudpickle
import pytest

import rr_actors as rr

# -- bug 6: a hostile __repr__ stops nothing -----------------------------------------------------


class HangsWhenShown:
    def __init__(self, gate: threading.Event) -> None:
        self.gate = gate

    def __eq__(self, other: object) -> bool:
        return isinstance(other, HangsWhenShown)

    def __hash__(self) -> int:
        return 1

    def __repr__(self) -> str:
        self.gate.wait(30)
        return "HangsWhenShown()"


class ExitsWhenShown:
    def __eq__(self, other: object) -> bool:
        return isinstance(other, ExitsWhenShown)

    def __hash__(self) -> int:
        return 2

    def __repr__(self) -> str:
        raise SystemExit("shown")


def hostile_setup(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("leaf", load=lambda r: "ok", unload=lambda r, s: None)


@pytest.mark.timeout(60)
def test_a_hanging_or_exiting_repr_shows_failed_and_the_graph_keeps_updating_without_new_threads(
    supervisors: Any,
) -> None:
    gate = threading.Event()
    sup = supervisors(
        [
            rr.ManagerSpec(
                "erm",
                setup=hostile_setup,
                config=rr.RegistrarConfig("erm", compare_timeout=0.5),
            )
        ]
    ).start()
    observer = sup.observe()
    try:
        app = sup.registrar(rr.RegistrarConfig("action", compare_timeout=0.5))
        app.call("erm", "leaf", HangsWhenShown(gate), timeout=5)
        app.call("erm", "leaf", ExitsWhenShown(), timeout=5)
        before = threading.active_count()
        drawn = [sup.graph()]
        deadline = time.monotonic() + 10
        while "repr failed: TimeoutError" not in drawn[-1] and time.monotonic() < deadline:
            drawn.append(sup.graph())  # (the text is made once compare_timeout is over)
        drawn += [sup.graph() for _ in range(10)]
        app.call("erm", "leaf", "after", timeout=5)
        last = sup.graph()
        after = threading.active_count()
    finally:
        gate.set()
        observer.close()

    assert "repr failed: TimeoutError" in drawn[-1]
    assert "repr failed: SystemExit" in last
    assert "after" in last  # the graph still follows the catalog
    assert after <= before + 3  # (a worker or two may start; not one hung thread per look: 12+)


class HangsForGood:
    """A request whose `repr` never returns (in a manager process: no gate reaches it)."""

    def __eq__(self, other: object) -> bool:
        return isinstance(other, HangsForGood)

    def __hash__(self) -> int:
        return 3

    def __repr__(self) -> str:
        threading.Event().wait(60)
        return "HangsForGood()"


def hung_in_repr(sup: rr.Supervisor, name: str) -> int:
    """Threads of manager `name`'s process that are in `HangsForGood.__repr__` now.

    (Not its count of threads: a connection's writer thread starts when an answer first
    has to wait for the socket, and `run_in`'s thread may still be ending after it
    answered; a loaded machine showed one more, with no hung thread more.)
    """

    def count(_registrar: Any) -> int:
        hung = 0
        for frame in sys._current_frames().values():
            stack = traceback.walk_stack(frame)
            hung += any(f.f_code.co_qualname == "HangsForGood.__repr__" for f, _ in stack)
        return hung

    return int(sup.run_in(name, count, timeout=5))


@pytest.mark.timeout(60)
def test_a_hanging_repr_in_a_process_manager_costs_one_thread_once_not_one_per_refresh(
    supervisors: Any, process_helpers: Any
) -> None:
    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # (for the manager process)
    sup = supervisors(
        [
            rr.ManagerSpec(
                "erm",
                setup=hostile_setup,
                isolation="process",
                config=rr.RegistrarConfig("erm", compare_timeout=0.5),
            )
        ]
    ).start()
    app = sup.registrar(rr.RegistrarConfig("action", compare_timeout=0.5))
    app.call("erm", "leaf", HangsForGood(), timeout=30)  # (a bound that holds under load)
    drawn = [sup.graph()]
    deadline = time.monotonic() + 10
    while "repr failed: TimeoutError" not in drawn[-1] and time.monotonic() < deadline:
        drawn.append(sup.graph())

    hung = hung_in_repr(sup, "erm")
    drawn += [sup.graph() for _ in range(20)]  # each reads erm's catalog in its process
    hung_after = hung_in_repr(sup, "erm")

    assert "repr failed: TimeoutError" in drawn[-1]
    assert (1, 1) == (hung, hung_after)  # one thread hangs, once: not one more per refresh
