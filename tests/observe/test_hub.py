"""What the page shows, kept once for every open page (`rr_actors_lab.observe._hub`): sections,
patches and the recent events."""

from __future__ import annotations

import json
from typing import Any

import pytest

from rr_actors_lab.observe._hub import BATCH, Hub

# -- the hub ---------------------------------------------------------------------------------


def test_a_page_gets_each_changed_section_once_and_only_the_latest_value() -> None:
    hub = Hub()
    seen: dict[str, int] = {}
    hub.put("tree", 1)
    hub.put("tree", 2)
    hub.put("graph", "g")

    first = hub.changes(seen, 0)
    unchanged = hub.put("graph", "g")
    second = hub.changes(seen, 0)

    assert [("tree", 2), ("graph", "g")] == [(k, v) for k, _, v in first.sections]
    assert not unchanged
    assert [] == second.sections


def test_a_removed_section_reaches_a_page_that_had_it_as_none() -> None:
    hub = Hub()
    seen: dict[str, int] = {}
    hub.put("catalog/cm", {"x": 1})
    hub.changes(seen, 0)

    hub.remove("catalog/cm")

    assert [("catalog/cm", None)] == [(k, v) for k, _, v in hub.changes(seen, 0).sections]
    assert [] == hub.changes({}, 0).sections  # a new page never hears of it


def test_events_are_numbered_converted_once_and_a_page_that_fell_behind_is_told() -> None:
    converted: list[int] = []

    def convert(event: int) -> dict[str, Any]:
        converted.append(event)
        return {"value": event}

    hub = Hub(ring=10, convert=convert)
    for value in range(25):
        hub.add_event(value)

    behind = hub.changes({}, 3)
    again = hub.changes({}, 20)

    assert list(range(16, 26)) == [e["seq"] for e in behind.events]
    assert 12 == behind.missed  # 4..15 fell out of the ring
    assert list(range(15, 25)) == converted  # each once, only when asked for
    assert [21, 22, 23, 24, 25] == [e["seq"] for e in again.events]


def test_a_page_gets_at_most_a_batch_of_events_at_a_time() -> None:
    hub = Hub(ring=BATCH * 3)
    for value in range(BATCH * 2):
        hub.add_event({"value": value})

    changes = hub.changes({}, 0)

    assert (BATCH, BATCH) == (len(changes.events), changes.missed)


def _strict(data: str) -> Any:
    """`data` parsed as a browser's `JSON.parse` does: `NaN` and `Infinity` are refused."""
    return json.loads(data, parse_constant=lambda name: pytest.fail(f"{name} in {data}"))


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_an_event_with_a_number_that_is_not_finite_never_costs_the_pages_the_others(
    bad: float, caplog: pytest.LogCaptureFixture
) -> None:
    """Issue 40: one `NaN` in one host's event made every page's `JSON.parse` drop the
    whole message of events, the other hosts' included."""
    hub = Hub()
    hub.add_event({"type": "InDoubt", "at": 1.0, "text": "before", "member": "alpha"})
    hub.add_event({"type": "InDoubt", "at": 2.0, "text": "bad", "load_s": bad, "member": "evil"})
    hub.add_event({"type": "InDoubt", "at": 3.0, "text": "after", "member": "bravo"})

    messages, last = hub.messages({}, 0)

    assert 3 == last
    data = messages[-1].decode().split("data: ", 1)[1].strip()
    shown = _strict(data)["events"]
    assert ["InDoubt", "Refused", "InDoubt"] == [e["type"] for e in shown]
    assert ["alpha", "evil", "bravo"] == [e["member"] for e in shown]
    assert "not finite" in shown[1]["text"]
    assert 1 == len([r for r in caplog.records if "not finite" in r.getMessage()])


def test_listeners_hear_every_change_until_removed() -> None:
    hub = Hub()
    heard: list[int] = []
    unlisten = hub.listen(lambda: heard.append(1))

    hub.put("tree", 1)
    hub.add_event({"a": 1})
    unlisten()
    hub.put("tree", 2)

    assert 2 == len(heard)
