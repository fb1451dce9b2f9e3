"""How stored values are encoded and decoded (`rr_actors._store.codec`): a request stored
with cloudpickle comes back, and one without a digest is found again (issue 3's contract)."""

from __future__ import annotations

import collections
import pickle
from pathlib import Path
from typing import Any

import cloudpickle
import pytest

import rr_actors as rr
from rr_actors._store import codec
from rr_actors._store.files import read_backup
from rr_actors.testing import crash
from tests.support.durable_pair import noop_unload, start
from tests.support.persisting import consumer_ids, unique

# -- requests are stored with cloudpickle ---------------------------------------------------------


def test_a_request_holding_a_function_defined_here_is_stored_and_restored(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    path = tmp_path / "p.db"
    name = unique("P")
    offset = 40

    def local_callback(value: int) -> int:  # not importable by name: plain pickle refuses it
        return value + offset

    provider = start(started, name, path, save_on_modify=True)
    provider.register_server("leaf", load=lambda r: r["f"](2), unload=noop_unload)
    query = provider.call(name, "leaf", {"f": local_callback})

    [resource] = read_backup(path).resources
    assert (42, 42, {query.id}) == (query.response, resource.request["f"](2), consumer_ids(path))


@pytest.mark.parametrize(
    "value",
    ["shared-2", {"server": "edge/resource", "request": "unique-0-7"}, ("a", 1, None, b"x")],
)
def test_small_builtin_data_is_stored_as_cloudpickle_would_store_it_without_cloudpickle(
    value: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    expected = cloudpickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
    monkeypatch.setattr(codec.cloudpickle, "dumps", None)  # (a pickler built: a TypeError)
    assert codec.dumps(value) == expected


def test_an_unhashable_request_without_a_digest_is_found_again_after_a_restart(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    # Counter has its own __eq__ (so no stored digest) and is unhashable: after a restore
    # only `==` against the restored request can find it
    path = tmp_path / "p.db"
    name = unique("P")
    loads: list[Any] = []

    def load(request: Any) -> Any:
        loads.append(request)
        return {"pid": len(loads)}

    provider = start(started, name, path, save_on_modify=True)
    provider.register_server("leaf", load=load, unload=noop_unload)
    first = provider.call(name, "leaf", collections.Counter({"cam": 2, "lidar": 1}))
    crash(provider)  # a clean stop would give back the id this registrar holds itself

    provider = start(started, name, path, save_on_modify=True)
    provider.register_server("leaf", load=load, unload=noop_unload)
    again = provider.call(name, "leaf", collections.Counter({"lidar": 1, "cam": 2}))

    assert (1, {"pid": 1}, {first.id, again.id}) == (len(loads), again.response, consumer_ids(path))
