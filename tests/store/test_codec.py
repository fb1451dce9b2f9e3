"""How stored values are encoded and decoded (`rr_actors._store.codec`): a request stored
with cloudpickle comes back (its code with its file's name), and one without a digest is
found again (issue 3's contract)."""

from __future__ import annotations

import collections
import pickle
import traceback
from pathlib import Path
from typing import Any

import cloudpickle
import pytest

import rr_actors as rr
from rr_actors._core import wire
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


def test_a_function_in_a_restored_request_keeps_its_file_so_a_traceback_shows_file_and_line(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    # cloudpickle 3.1.3 names code it pickles by value "<dynamic-code>": stored as it,
    # a restored request's function raised with no file and no source line
    path = tmp_path / "p.db"
    name = unique("P")

    def local_divide(value: int) -> float:  # pickled by value: a closure
        return 1 / value  # the line a traceback must show

    provider = start(started, name, path, save_on_modify=True)
    provider.register_server("leaf", load=lambda r: r["f"](2), unload=noop_unload)
    provider.call(name, "leaf", {"f": local_divide})

    [resource] = read_backup(path).resources
    with pytest.raises(ZeroDivisionError) as info:
        resource.request["f"](0)

    [*_, raised] = traceback.extract_tb(info.value.__traceback__)
    assert (__file__, "local_divide") == (raised.filename, raised.name)
    assert "return 1 / value  # the line a traceback must show" == raised.line


@pytest.mark.parametrize(
    "value",
    ["shared-2", {"server": "edge/resource", "request": "unique-0-7"}, ("a", 1, None, b"x")],
)
def test_small_builtin_data_is_stored_as_cloudpickle_would_store_it_without_cloudpickle(
    value: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    expected = cloudpickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
    monkeypatch.setattr(wire, "Pickler", None)  # (a pickler built: a TypeError)
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
