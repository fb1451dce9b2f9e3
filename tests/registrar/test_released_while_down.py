"""A release that failed as its provider was down, then the consumer SIGKILLed (issue 32).

Found by `rr-actors check` in the shipped `killheavy` plan: consumer `api` released an id
at `db` while `db` was down (`RegistrarUnavailableError`: the id is given up, `db`
releases it when they reconcile) and was then SIGKILLed. `db` restarted while `api` was
down (its `ReconcileAsk` reached nobody), then `api` restarted from its backup, which
has no record at `db` any more: it never reconciled with `db`, which held the id to the
end of the run (rule 20: ids a consumer released are released at the provider, its
`unload` runs once).

Real manager processes with backups under one supervisor, real SIGKILLs; the restarts
wait for the test (`ManualTimer`), which lets them happen one at a time, in its order.
"""

from __future__ import annotations

import os
import signal
import sys
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.testing import SharedObjects
from tests.support.supervising import ManualTimer

pytestmark = [
    pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals"),
    pytest.mark.usefixtures("by_value"),  # (tests/conftest.py)
]


def provider_setup(unloads: Any) -> Callable[[rr.ResourceRegistrar], None]:
    def setup(registrar: rr.ResourceRegistrar) -> None:
        registrar.register_server(
            "leaf", load=lambda r: {"for": r}, unload=lambda r, _s: unloads.append(r)
        )

    return setup


def fire_first(timer: ManualTimer) -> None:
    """Run the earliest restart the supervisor scheduled, and only that one."""
    with timer.cond:
        _delay, fn, handle = timer.pending.pop(0)
    if not handle.cancelled:
        fn()


def unload_outcome(query_id: str) -> Callable[[rr.ResourceRegistrar], str]:
    def run(registrar: rr.ResourceRegistrar) -> str:
        try:
            registrar.unload(query_id, timeout=10)
        except rr.RrError as exc:
            return type(exc).__name__
        return "released"

    return run


@pytest.mark.parametrize(
    "first", ["provider", "consumer"], ids=["provider-first", "consumer-first"]
)
def test_an_id_released_while_its_provider_was_down_is_released_after_both_restart(
    first: str,
    tmp_path: Path,
    process_helpers: SharedObjects,
    eventually: Callable[..., bool],
) -> None:
    unloads = process_helpers.list()
    uid = uuid.uuid4().hex[:8]
    provider, consumer = f"db-{uid}", f"api-{uid}"
    timer = ManualTimer()  # each restart waits for the test
    specs = [
        rr.ManagerSpec(provider, provider_setup(unloads), isolation="process"),
        rr.ManagerSpec(consumer, None, isolation="process", heartbeat=None),
    ]
    sup = rr.Supervisor(
        specs, state_dir=tmp_path, backoff=rr.Backoff(initial=1.0, jitter=0.0), timer=timer
    )
    with sup:
        qid = sup.run_in(consumer, lambda r: r.call(provider, "leaf", "x", timeout=10).id)
        pids = {info.name: info.pid for info in sup.which_children()}
        os.kill(pids[provider], signal.SIGKILL)
        assert timer.wait_scheduled(1, timeout=10)  # its restart is due, not done
        assert "RegistrarUnavailableError" == sup.run_in(consumer, unload_outcome(qid))
        assert [] == sup.run_in(consumer, lambda r: [q.id for q in r.client_queries()])
        os.kill(pids[consumer], signal.SIGKILL)  # a restart is expected: no death watch
        assert timer.wait_scheduled(2, timeout=10)

        if first == "provider":  # it asks the consumer to reconcile: nobody hears it
            fire_first(timer)
            sup.wait_restarted(provider, timeout=15)
            assert [qid] == sup.run_in(provider, lambda r: [q.id for q in r.server_queries("leaf")])
            fire_first(timer)
            sup.wait_restarted(consumer, timeout=15)
        else:
            timer.pending.reverse()  # (the consumer's restart was scheduled second)
            fire_first(timer)
            sup.wait_restarted(consumer, timeout=15)
            fire_first(timer)
            sup.wait_restarted(provider, timeout=15)

        def released() -> bool:
            return [] == sup.run_in(provider, lambda r: [q.id for q in r.server_queries("leaf")])

        assert eventually(lambda: released() and len(unloads) >= 1, timeout=10)
        assert ["x"] == list(unloads)  # its unload ran once
        assert [] == sup.run_in(consumer, lambda r: [q.id for q in r.client_queries()])
