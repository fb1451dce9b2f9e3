"""Deterministic simulation: the same protocol code on a simulated world, one seed a run.

`run(fn, seed=S)` runs `fn()` with every thread it starts (actors, worker pools, serial
executors, timers) as a greenlet of one OS thread, one at a time, chosen by a scheduler
seeded with `S`, on a virtual clock that jumps to the next deadline whenever nothing is
ready. The protocol code is the one a real run uses: only the seams of
`rr_actors._core.runtime` (threads, locks, events, conditions, queues, clocks, ids,
randomness) are simulated. So one seed gives one history, hash included, every time;
many seeds search many interleavings, each replayable.

Needs the `simulation` extra (`greenlet`). One simulation runs at a time per process,
and nothing else of rr_actors runs beside it (it replaces the process's runtime while it
runs). Across processes, the same seed gives the same hash when string hashing is fixed
(`PYTHONHASHSEED=0`): the iteration order of a set of strings depends on it.
"""

from __future__ import annotations

from rr_actors._extras import needs

with needs("simulation", "rr_actors.simulation"):  # greenlet: one line if it is missing
    from rr_actors.simulation._network import SimulatedNetwork
    from rr_actors.simulation._run import Run, kill, note, now, pid, run, sleep, start_process
    from rr_actors.simulation._scheduler import DeadlockError, LimitError, SimulationError

__all__ = [
    "DeadlockError",
    "LimitError",
    "Run",
    "SimulatedNetwork",
    "SimulationError",
    "kill",
    "note",
    "now",
    "pid",
    "run",
    "sleep",
    "start_process",
]
