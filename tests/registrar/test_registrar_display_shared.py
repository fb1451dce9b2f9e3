"""A consumer makes the display text of a request object once, not once per call (issue 20:
a dedup hit with a user-class request cost a worker round trip and a write per call)."""

from __future__ import annotations

from typing import Any

import pytest

from rr_actors.testing import catalog_snapshot


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


@pytest.mark.thread_only("one request object: a call from another process pickles it anew")
def test_calls_with_one_request_object_share_its_text_and_an_equal_new_one_gets_its_own(
    make_registrar: Any, eventually: Any
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
