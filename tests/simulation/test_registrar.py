"""The registrar's semantic rules on the simulation, over many seeds (issue 42).

In-process registrars (the "thread" placement) run on `rr_actors.simulation`: their
actors, worker pools and timers are greenlets of one OS thread, and each seed chooses
another interleaving of them (`preempt`: also where no thread blocks). Each scenario is
one function; a test runs it for every seed of `SEEDS` and lists the seeds whose run
broke the rule (each one replays: `simulation.run(scenario, seed=S)`).
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors import simulation
from rr_actors._core import runtime
from tests.support import simulated

pytest.importorskip("greenlet")  # (the simulation extra)

ROOT = Path(__file__).resolve().parent.parent.parent

SEEDS = range(300)
"""The seeds each scenario runs with."""

PREEMPT = simulated.PREEMPT
"""How often a simulated thread yields where it would not block."""


def start(*names: str, **config: Any) -> list[rr.ResourceRegistrar]:
    return [rr.ResourceRegistrar.start(rr.RegistrarConfig(name=n, **config)) for n in names]


def in_threads(*bodies: Callable[[], object]) -> None:
    """Run each of `bodies` on a (simulated) thread of its own; return once all returned."""
    threads = [runtime.Thread(target=body, name=f"client-{n}") for n, body in enumerate(bodies)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()


# -- rules 1-3: load once -------------------------------------------------------------------


def concurrent_equal_calls() -> dict[str, Any]:
    """Four clients of two consumers ask for one resource at once, then release it."""
    provider, first, second = start("provider", "first", "second")
    loads: list[Any] = []
    unloads: list[tuple[Any, int]] = []
    released = [0]

    def load(request: Any) -> Any:
        loads.append(request)
        simulation.sleep(1.0)
        return {"camera": request}

    provider.register_server(
        "leaf", load=load, unload=lambda request, _: unloads.append((request, released[0]))
    )
    queries: list[rr.Query] = []

    def client(consumer: rr.ResourceRegistrar, pause: float) -> Callable[[], None]:
        def body() -> None:
            simulation.sleep(pause)
            queries.append(consumer.call("provider", "leaf", "front"))

        return body

    in_threads(client(first, 0.0), client(second, 0.0), client(first, 0.5), client(second, 0.25))
    served = sorted(q.id for q in provider.server_queries("leaf"))

    def release(query: rr.Query) -> Callable[[], None]:
        def body() -> None:
            released[0] += 1
            (first if query.origin_rr == "first" else second).unload(query.id)

        return body

    in_threads(*(release(q) for q in queries))
    return {
        "loads": loads,
        "ids": sorted(q.id for q in queries),
        "served": served,
        "responses": [q.response for q in queries],
        "unloads": unloads,
        "left": (provider.server_queries("leaf"), first.client_queries()),
        "clean": simulated.stopped_clean(first, second, provider),
    }


def test_concurrent_equal_requests_load_once_and_unload_once_after_the_last_release() -> None:
    def broken(seen: dict[str, Any]) -> bool:
        return (
            ["front"] != seen["loads"]
            or 4 != len(set(seen["ids"]))
            or seen["ids"] != seen["served"]
            or [{"camera": "front"}] * 4 != seen["responses"]
            or [("front", 4)] != seen["unloads"]
            or ([], []) != seen["left"]
            or not seen["clean"]
        )

    assert [] == simulated.seeds_where(concurrent_equal_calls, broken, SEEDS)


def different_requests() -> dict[str, Any]:
    """Three clients ask for three different resources of one server at once."""
    provider, consumer = start("provider", "consumer")
    started: list[float] = []

    def load(request: Any) -> Any:
        started.append(simulation.now())
        simulation.sleep(1.0)
        return request

    provider.register_server("leaf", load=load, unload=lambda *_: None)
    done: list[float] = []

    def client(request: str) -> Callable[[], None]:
        def body() -> None:
            consumer.call("provider", "leaf", request)
            done.append(simulation.now())

        return body

    began = simulation.now()
    in_threads(client("a"), client("b"), client("c"))
    return {
        "loads": len(started),
        "took": max(done) - began,
        "clean": simulated.stopped_clean(consumer, provider),
    }


def test_different_requests_to_one_server_load_concurrently() -> None:
    def broken(seen: dict[str, Any]) -> bool:
        return 3 != seen["loads"] or seen["took"] > 1.0 or not seen["clean"]

    assert [] == simulated.seeds_where(different_requests, broken, SEEDS)


# -- rule 4: a load that raises leaks nothing -------------------------------------------


def failing_composite() -> dict[str, Any]:
    """Two clients ask at once for a composite whose load loads a leaf, then raises."""
    consumer, agent, producer = start("consumer", "agent", "producer")
    leaf_unloads: list[Any] = []
    composite_loads: list[Any] = []

    def composite_load(request: Any) -> Any:
        composite_loads.append(request)
        agent.call("producer", "leaf", request)
        simulation.sleep(0.5)
        raise ValueError("the filter broke")

    producer.register_server(
        "leaf", load=lambda r: r, unload=lambda request, _: leaf_unloads.append(request)
    )
    agent.register_server("composite", load=composite_load, unload=lambda *_: None)
    errors: list[tuple[str, ...]] = []

    def client() -> None:
        try:
            consumer.call("agent", "composite", "x")
        except rr.ResourceLoadError as exc:
            errors.append(tuple(f"{f.registrar}/{f.server} {f.exc_type}" for f in exc.stack))

    in_threads(client, client)
    return {
        "errors": errors,
        "loads": len(composite_loads),
        "leaf unloads": len(leaf_unloads),
        "left": (
            producer.server_queries("leaf"),
            agent.server_queries("composite"),
            agent.client_queries(),
            consumer.client_queries(),
        ),
        "clean": simulated.stopped_clean(consumer, agent, producer),
    }


def test_a_load_that_raises_fails_its_callers_and_unloads_what_it_had_loaded() -> None:
    def broken(seen: dict[str, Any]) -> bool:
        return (
            [("agent/composite ValueError",)] * 2 != seen["errors"]
            or 1 != seen["loads"]  # (rule 3: both came while it loaded)
            or 1 != seen["leaf unloads"]  # (rule 4: what it loaded is unloaded)
            or ([], [], [], []) != seen["left"]
            or not seen["clean"]
        )

    assert [] == simulated.seeds_where(failing_composite, broken, SEEDS)


# -- rules 5 and 7: dependencies, and the order of unloads -------------------------------


def composite() -> dict[str, Any]:
    """A composite whose load calls a leaf of another registrar; two clients share it."""
    consumer, agent, producer = start("consumer", "agent", "producer")
    journal: list[str] = []

    def leaf_unload(request: Any, response: Any) -> None:
        journal.append("leaf unload starts")
        simulation.sleep(0.5)
        journal.append("leaf unload ends")

    producer.register_server("leaf", load=lambda r: f"leaf {r}", unload=leaf_unload)

    def composite_load(request: Any) -> Any:
        journal.append("composite load")
        return agent.call("producer", "leaf", request).response

    agent.register_server(
        "composite",
        load=composite_load,
        unload=lambda *_: journal.append("composite unload"),
    )
    queries: list[rr.Query] = []
    in_threads(*[lambda: queries.append(consumer.call("agent", "composite", "x"))] * 2)
    held = [(q.origin_rr, q.request) for q in producer.server_queries("leaf")]
    in_threads(*(lambda q=q: consumer.unload(q.id) for q in queries))
    return {
        "held": held,
        "responses": [q.response for q in queries],
        "journal": journal,
        "left": (producer.server_queries("leaf"), agent.client_queries()),
        "clean": simulated.stopped_clean(consumer, agent, producer),
    }


def test_a_call_made_while_loading_is_a_dependency_released_before_its_resource_unloads() -> None:
    def broken(seen: dict[str, Any]) -> bool:
        return (
            [("agent", "x")] != seen["held"]  # the agent holds the leaf: a dependency
            or ["leaf x", "leaf x"] != seen["responses"]
            or [
                "composite load",
                "leaf unload starts",
                "leaf unload ends",
                "composite unload",
            ]
            != seen["journal"]
            or ([], []) != seen["left"]
            or not seen["clean"]
        )

    assert [] == simulated.seeds_where(composite, broken, SEEDS)


# -- rule 9: a status climbs every dependency path, once each ------------------------------


def climbing_status() -> dict[str, Any]:
    """A leaf's provider sends a status; it climbs through a composite to its consumers."""
    consumer, agent, producer = start("consumer", "agent", "producer")
    heard: list[tuple[str, str, str]] = []

    def hear(who: str) -> Callable[[rr.Query, rr.StatusUpdate], None]:
        return lambda query, update: heard.append((who, query.id, update.message))

    producer.register_server(
        "leaf", load=lambda r: r, unload=lambda *_: None, on_status=hear("leaf")
    )
    agent.register_server(
        "composite",
        load=lambda r: agent.call("producer", "leaf", r).response,
        unload=lambda *_: None,
        on_status=hear("composite"),
    )
    queries: list[rr.Query] = []
    in_threads(
        lambda: queries.append(consumer.call("agent", "composite", "x", on_status=hear("a"))),
        lambda: queries.append(consumer.call("agent", "composite", "x", on_status=hear("b"))),
    )
    (leaf,) = producer.server_queries("leaf")
    producer.send_status(leaf.id, rr.Status.WARNING, "hot")
    ids = {q.id for q in queries}
    for query in queries:
        consumer.unload(query.id)
    return {
        "heard": heard,
        "leaf": leaf.id,
        "ids": ids,
        "clean": simulated.stopped_clean(consumer, agent, producer),
    }


def test_a_status_reaches_each_server_and_consumer_up_the_path_once_before_send_returns() -> None:
    def broken(seen: dict[str, Any]) -> bool:
        by = {who: (qid, message) for who, qid, message in seen["heard"]}
        return (
            4 != len(seen["heard"])
            or {"leaf", "composite", "a", "b"} != set(by)
            or ("hot",) != tuple({message for _, _, message in seen["heard"]})
            or seen["leaf"] != by["leaf"][0]
            or seen["ids"] != {qid for who, qid, _ in seen["heard"] if who in "ab"}
            or not seen["clean"]
        )

    assert [] == simulated.seeds_where(climbing_status, broken, SEEDS)


# -- rule 17: a call that timed out leaves nothing behind --------------------------------


def impatient_and_patient() -> dict[str, Any]:
    """One client gives up before a slow load ends, another equal one waits for it; then
    a lone impatient client whose load completes only after it gave up."""
    provider, consumer = start("provider", "consumer")
    loads: list[Any] = []
    unloads: list[Any] = []

    def load(request: Any) -> Any:
        loads.append(request)
        simulation.sleep(3.0)
        return request

    provider.register_server("slow", load=load, unload=lambda request, _: unloads.append(request))
    outcomes: list[str] = []

    def impatient(request: str) -> Callable[[], None]:
        def body() -> None:
            try:
                consumer.call("provider", "slow", request, timeout=1.0)
            except rr.CallTimeoutError:
                outcomes.append(f"{request}: timed out")

        return body

    patient: list[rr.Query] = []
    in_threads(
        impatient("shared"),
        lambda: patient.append(consumer.call("provider", "slow", "shared", timeout=10.0)),
        impatient("alone"),
    )
    simulation.sleep(5.0)  # (the late load of "alone" completes meanwhile)
    held = sorted(q.request for q in provider.server_queries("slow"))
    consumer.unload(patient[0].id)
    return {
        "outcomes": sorted(outcomes),
        "loads": sorted(loads),
        "held": held,
        "unloads": sorted(unloads),
        "left": (provider.server_queries("slow"), consumer.client_queries()),
        "clean": simulated.stopped_clean(consumer, provider),
    }


def test_a_call_that_timed_out_leaves_nothing_behind_and_takes_nothing_from_a_patient_one() -> None:
    def broken(seen: dict[str, Any]) -> bool:
        return (
            ["alone: timed out", "shared: timed out"] != seen["outcomes"]
            or ["alone", "shared"] != seen["loads"]
            or ["shared"] != seen["held"]  # "alone" was released when its load completed
            or ["alone", "shared"] != seen["unloads"]
            or ([], []) != seen["left"]
            or not seen["clean"]
        )

    assert [] == simulated.seeds_where(impatient_and_patient, broken, SEEDS)


# -- determinism ---------------------------------------------------------------------------

SCENARIOS = [
    concurrent_equal_calls,
    different_requests,
    failing_composite,
    composite,
    climbing_status,
    impatient_and_patient,
]


@pytest.mark.parametrize("scenario", SCENARIOS, ids=lambda s: s.__name__)
def test_each_seed_replays_its_run_the_same_trace_hash_and_outcome(
    scenario: Callable[[], dict[str, Any]],
) -> None:
    for seed in range(0, 300, 30):
        first, again = (simulation.run(scenario, seed=seed, preempt=PREEMPT) for _ in range(2))
        assert (first.hash, first.steps, repr(first.value)) == (
            again.hash,
            again.steps,
            repr(again.value),
        ), f"seed {seed}"


def test_seeds_choose_different_interleavings_of_one_scenario() -> None:
    hashes = {
        simulation.run(concurrent_equal_calls, seed=s, preempt=PREEMPT).hash for s in range(20)
    }

    assert len(hashes) > 10


def test_a_seed_gives_the_same_hashes_in_another_process() -> None:
    """With string hashing fixed (`PYTHONHASHSEED`), as a replay in another process runs."""
    source = (
        "from tests.simulation.test_registrar import PREEMPT, SCENARIOS, simulation\n"
        "from tests.simulation import test_supervision as supervised\n"
        "for scenario in SCENARIOS:\n"
        "    for seed in range(3):\n"
        "        print(simulation.run(scenario, seed=seed, preempt=PREEMPT).hash)\n"
        "for seed in range(3):\n"  # (manager processes under kills: issue 42, step 2)
        "    tree = supervised.tree(kills=3)\n"
        "    print(simulation.run(tree, seed=seed, preempt=supervised.PREEMPT).hash)\n"
    )
    environment = {**os.environ, "PYTHONHASHSEED": "0"}
    outputs = [
        subprocess.run(
            [sys.executable, "-c", source],
            cwd=ROOT,
            env=environment,
            capture_output=True,
            text=True,
            timeout=120,
            check=True,
        ).stdout
        for _ in range(2)
    ]

    assert 3 * len(SCENARIOS) + 3 == len(outputs[0].split())
    assert outputs[0] == outputs[1]
