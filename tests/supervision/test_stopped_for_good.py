"""A manager its supervisor stops for good is a mark: what a provider still holds of it goes.

Issue 32 (the kill-heavy plan's `end` findings): consumer `edge` stopped for good (the
tree's stop) while provider `api` still held ids `edge` had given up while `api` was
down; `api`'s reconcile came too late to name them, and `api` ended the run holding
them. A stopped registrar holds nothing (rule 12), so its supervisor's "it will not be
started again" is a mark as a death for good is (`_core/membership.py`): the provider
releases what it still holds of it. Here the stale id comes from the documented limit of
a consumer without a backup: restarted, it no longer knows the ids it held.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import rr_actors as rr
from tests.support.supervising import crash


def test_a_consumer_stopped_for_good_by_its_supervisor_has_its_stale_ids_released(
    tmp_path: Path, uid: str
) -> None:
    provider, consumer = f"api-{uid}", f"edge-{uid}"
    unloads: list[Any] = []
    unloaded = threading.Event()

    def unload(request: Any, _response: Any) -> None:
        unloads.append(request)
        unloaded.set()

    def setup(registrar: rr.ResourceRegistrar) -> None:
        registrar.register_server("leaf", load=lambda r: r, unload=unload)

    sup = rr.Supervisor(
        [
            rr.ManagerSpec(provider, setup, isolation="thread"),
            rr.ManagerSpec(consumer, None, isolation="thread"),  # no backup: forgets on restart
        ],
        backoff=rr.Backoff(initial=0.0, jitter=0.0),
    )
    with sup:
        sup.run_in(consumer, lambda r: r.call(provider, "leaf", "x", timeout=10))
        crash(sup, consumer)
        sup.wait_restarted(consumer, timeout=10)
        assert [] == sup.run_in(consumer, lambda r: r.client_queries())  # it forgot the id
        assert 1 == len(sup.run_in(provider, lambda r: r.server_queries("leaf")))  # held
        # the tree stops: the consumer first, for good; then the provider

    assert unloaded.wait(10)
    assert ["x"] == unloads  # released when the consumer stopped for good, unloaded once
