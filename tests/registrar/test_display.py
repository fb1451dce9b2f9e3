"""Tests of `rr_actors/_registrar/display.py`: display texts and labels, made once, user code
contained (`TestDisplay`), one text per request object a consumer holds
(`TestDisplayShared`).
"""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.testing import catalog_snapshot
from tests.support.hostile import ExitsWhenShown, HangsWhenShown

# -- for TestDisplay -----------------------------------------------------------------------


def texts(registrar: Any) -> dict[str, tuple[Any, Any, Any]]:
    """Server -> (request_text, response_text, label) of its only resource."""
    return {
        r.server: (r.request_text, r.response_text, r.label)
        for r in catalog_snapshot(registrar).resources
    }


def leaf(registrar: Any, name: str = "leaf", **kwargs: Any) -> Any:
    registrar.register_server(name, load=lambda r: {"for": "x"}, unload=lambda r, s: None, **kwargs)
    return registrar


# -- for TestDisplayShared -----------------------------------------------------------------


class Counted:
    """A request of a user class whose `repr` counts its runs."""

    def __init__(self, shown: list[int]) -> None:
        self.shown = shown

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Counted)

    def __hash__(self) -> int:
        return 3

    def __repr__(self) -> str:
        self.shown.append(1)
        return "Counted()"


def client_texts(registrar: Any) -> list[Any]:
    return [c.request_text for c in catalog_snapshot(registrar).clients]


class TestDisplay:
    """Display texts and labels: what observers show of a value is made once, by the registrar
    that owns it, with user code contained (issue 21, bug 6; issue 24, item 2).
    """

    def test_a_request_whose_repr_hangs_reads_as_failed_after_compare_timeout_and_runs_once(
        self, make_registrar: Any, shared: Any, gates: Any, eventually: Any
    ) -> None:
        provider = leaf(make_registrar("provider", compare_timeout=0.5))
        leaf(provider, "plain")
        consumer = make_registrar("consumer")
        gate, shown = gates(), shared.list()

        consumer.call(provider.name, "leaf", HangsWhenShown(gate, shown), timeout=5)
        consumer.call(provider.name, "plain", {"name": "lidar2"}, timeout=5)

        assert eventually(lambda: texts(provider)["leaf"][0] is not None, timeout=10)
        assert eventually(lambda: 2 == len(shown))
        for _ in range(5):  # every look at the catalog shows the stored text: no repr runs
            catalog_snapshot(provider)
        assert "<repr failed: TimeoutError>" == texts(provider)["leaf"][0]
        assert ("{'name': 'lidar2'}", "{'for': 'x'}", None) == texts(provider)["plain"]
        assert 2 == len(
            shown
        )  # once at the provider (its resource), once at the consumer (its record)

    def test_a_request_whose_repr_raises_system_exit_reads_as_failed_and_the_registrar_serves_on(
        self, make_registrar: Any, eventually: Any
    ) -> None:
        provider = leaf(make_registrar("provider"))
        consumer = make_registrar("consumer")

        query = consumer.call(provider.name, "leaf", ExitsWhenShown(), timeout=5)

        assert eventually(lambda: texts(provider)["leaf"][0] is not None, timeout=10)
        assert "<repr failed: SystemExit>" == texts(provider)["leaf"][0]
        consumer.unload(query.id, timeout=5)
        assert {"for": "x"} == consumer.call(provider.name, "leaf", "again", timeout=5).response

    @pytest.mark.parametrize(
        ("label", "expected"),
        [
            (lambda r: r["name"], "jackal-driver"),
            (lambda r: r["missing"], "<label failed: KeyError>"),
            (lambda r: 42, "<label failed: returned int>"),
            (lambda r: "x" * 100, "x" * 37 + "..."),
        ],
        ids=["named", "raises", "not-a-string", "too-long"],
    )
    def test_a_servers_label_names_each_resource_and_a_failing_one_reads_as_failed(
        self, make_registrar: Any, eventually: Any, label: Any, expected: str
    ) -> None:
        provider = leaf(make_registrar("provider"), label=label)
        consumer = make_registrar("consumer")

        consumer.call(provider.name, "leaf", {"bus": "b", "name": "jackal-driver"}, timeout=5)

        assert eventually(lambda: texts(provider)["leaf"][2] is not None, timeout=10)
        assert expected == texts(provider)["leaf"][2]

    def test_a_label_that_is_not_callable_is_a_config_error(self, make_registrar: Any) -> None:
        provider = make_registrar("provider")

        with pytest.raises(rr.ConfigError, match="label must be callable"):
            leaf(provider, label="name")

    def test_the_backup_keeps_every_display_text_and_label_beside_its_values(
        self, make_registrar: Any, eventually: Any, tmp_path: Path
    ) -> None:
        path = tmp_path / "p.db"
        provider = make_registrar("provider", backup_path=str(path), save_on_modify=True)
        leaf(provider, label=lambda r: r["name"])
        consumer = make_registrar("consumer", backup_path=str(tmp_path / "c.db"))

        consumer.call(provider.name, "leaf", {"name": "lidar2"}, timeout=5)

        def stored() -> list[Any]:
            db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
            try:
                return db.execute(
                    "SELECT request_text, response_text, label FROM resources"
                ).fetchall()
            finally:
                db.close()

        assert eventually(lambda: stored() == [("{'name': 'lidar2'}", "{'for': 'x'}", "lidar2")])
        assert ["{'name': 'lidar2'}"] == [
            c.request_text for c in catalog_snapshot(consumer).clients
        ]


class TestDisplayShared:
    """A consumer makes the display text of a request object once, not once per call (issue 20:
    a dedup hit with a user-class request cost a worker round trip and a write per call).
    """

    @pytest.mark.thread_only("one request object: a call from another process pickles it anew")
    def test_calls_with_one_request_object_share_its_text_and_an_equal_new_one_gets_its_own(
        self, make_registrar: Any, eventually: Any
    ) -> None:
        provider = make_registrar("provider")
        provider.register_server("leaf", load=lambda r: "loaded", unload=lambda r, s: None)
        consumer = make_registrar("consumer")
        shown: list[int] = []
        request = Counted(shown)

        ids = [consumer.call(provider.name, "leaf", request, timeout=5).id for _ in range(6)]

        assert eventually(lambda: client_texts(consumer) == ["Counted()"] * 6, timeout=10)
        assert 2 == len(shown)  # once for the provider's resource, once at the consumer
        consumer.call(provider.name, "leaf", Counted(shown), timeout=5)  # equal, not the same
        assert eventually(lambda: client_texts(consumer) == ["Counted()"] * 7, timeout=10)
        assert 3 == len(shown)
        for query_id in ids[1:]:
            consumer.unload(query_id, timeout=5)
        consumer.call(provider.name, "leaf", request, timeout=5)
        assert eventually(lambda: client_texts(consumer) == ["Counted()"] * 3, timeout=10)
        assert 3 == len(shown)  # the first record, which made the text, is still held
        consumer.unload(ids[0], timeout=5)
        consumer.call(provider.name, "leaf", request, timeout=5)
        assert eventually(lambda: client_texts(consumer) == ["Counted()"] * 3, timeout=10)
        assert 4 == len(shown)  # it went: the next call makes the text again (and holds it)
