"""Cancel storm: awaited calls cancelled around a provider's SIGKILL leave no id held.

Each run starts a supervised process manager with a backup, awaits 2,000 `acall`s (20
distinct requests, caller-chosen ids) from a consumer registrar, cancels 70% of them
0-50 ms after they start and SIGKILLs the provider 55-70 ms in. Once the provider is back
and the consumer has unloaded every id it holds, the provider must hold nothing for it
(rule 17: a cancelled call is withdrawn as a timed-out one is; rule 20: the reconcile after
the restart releases what the consumer does not hold). Prints one row per run and the
total of ids kept; exits 1 if any run kept one.

    python benchmarks/stress_cancel.py [--runs 20] [--calls 2000] [--seed 1]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import random
import signal
import sys
import tempfile
import time
import uuid
from collections import Counter

import rr_actors as rr

SETTLE_S = 20.0
"""Seconds the provider is given, after the consumer unloaded everything, to release what
it still holds (its reconcile takes milliseconds; this bounds a run that never does)."""


def _setup(erm: rr.ResourceRegistrar) -> None:
    erm.register_server("res", load=lambda request: {"n": request["n"]}, unload=lambda q, r: None)


async def _storm(
    app: rr.ResourceRegistrar, pid: int, calls: int, rng: random.Random
) -> dict[str, str]:
    """Start `calls` awaited calls, cancel most, kill the provider: each id's outcome
    (`answered`, `cancelled`, or the name of the error it failed with)."""

    async def one(query_id: str, n: int) -> str:
        try:
            await app.acall("erm", "res", {"n": n}, query_id=query_id, timeout=10.0)
        except asyncio.CancelledError:
            return "cancelled"
        except rr.RrError as exc:
            return type(exc).__name__
        return "answered"

    loop = asyncio.get_running_loop()
    ids = [str(uuid.uuid4()) for _ in range(calls)]
    tasks = [loop.create_task(one(query_id, i % 20)) for i, query_id in enumerate(ids)]
    for task in tasks:
        if rng.random() < 0.7:
            loop.call_later(rng.uniform(0.0, 0.05), task.cancel)
    killed = asyncio.Event()

    def kill() -> None:
        os.kill(pid, signal.SIGKILL)
        killed.set()

    loop.call_later(rng.uniform(0.055, 0.07), kill)
    outcomes = await asyncio.gather(*tasks, return_exceptions=True)
    await killed.wait()  # (a small storm may be over before the kill: it still comes)
    return {q: o if isinstance(o, str) else "cancelled" for q, o in zip(ids, outcomes, strict=True)}


def run(calls: int, seed: int) -> Counter[str]:
    """One run: how many calls ended each way (`answered`, `cancelled`, an error's name),
    and, as `kept <outcome>`, how many ids of each the provider still holds at the end."""
    rng = random.Random(seed)  # noqa: S311 - a reproducible schedule, not a secret
    with tempfile.TemporaryDirectory() as state:
        sup = rr.Supervisor(
            [rr.ManagerSpec("erm", _setup, isolation="process")],
            max_restarts=10,
            period=5.0,
            state_dir=state,
        )
        with sup:
            app = sup.registrar("app")
            restarts = sup.child("erm").restarts
            outcomes = asyncio.run(_storm(app, sup.child("erm").pid, calls, rng))
            sup.wait_restarted("erm", restarts=restarts + 1, timeout=30.0)
            for query_id, outcome in outcomes.items():
                if outcome == "answered":
                    with contextlib.suppress(rr.UnknownQueryError):  # forgotten (told FATAL)
                        app.unload(query_id)
            deadline = time.monotonic() + SETTLE_S
            kept = app.fetch_queries("erm", "res")
            while kept and time.monotonic() < deadline:
                time.sleep(0.1)  # the provider's reconcile is asynchronous: poll, bounded
                kept = app.fetch_queries("erm", "res")
            counts = Counter(outcomes.values())
            counts.update(f"kept {outcomes.get(q.id, 'unknown')}" for q in kept)
            return counts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--calls", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    total: Counter[str] = Counter()
    print(f"{'run':>4} {'answered':>9} {'cancelled':>9} {'failed':>7}  kept at the provider")
    for i in range(args.runs):
        counts = run(args.calls, args.seed + i)
        total.update(counts)
        kept = {k[5:]: n for k, n in counts.items() if k.startswith("kept ")}
        failed = sum(
            n for k, n in counts.items() if k not in ("answered", "cancelled") and k[:5] != "kept "
        )
        print(
            f"{i + 1:>4} {counts['answered']:>9} {counts['cancelled']:>9} {failed:>7}  "
            f"{', '.join(f'{n} {k}' for k, n in sorted(kept.items())) or '0'}"
        )
    cancelled = total["kept cancelled"]
    print(f"ids of cancelled calls kept after the storm in {args.runs} runs: {cancelled}")
    print(f"ids kept in all: {sum(n for k, n in total.items() if k.startswith('kept '))}")
    sys.exit(1 if cancelled else 0)


if __name__ == "__main__":
    main()
