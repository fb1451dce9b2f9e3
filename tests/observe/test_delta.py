"""The observer's patches (`rr_actors_lab.observe._delta`): what changed in a section, small, and
exact when applied."""

from __future__ import annotations

import json
from typing import Any

from hypothesis import given
from hypothesis import strategies as st

from rr_actors_lab.observe._delta import apply, diff

_scalars = st.one_of(st.none(), st.booleans(), st.integers(-5, 5), st.text(max_size=3))
_rows = st.lists(
    st.fixed_dictionaries({"id": st.sampled_from("abcdefgh"), "state": _scalars}),
    max_size=6,
    unique_by=lambda r: r["id"],
)
_values = st.recursive(
    st.one_of(_scalars, _rows),
    lambda inner: st.one_of(
        st.lists(inner, max_size=3), st.dictionaries(st.sampled_from("xyz"), inner, max_size=3)
    ),
    max_leaves=12,
)


@given(_values, _values)
def test_applying_the_patch_from_old_to_new_gives_new(old: Any, new: Any) -> None:
    patch = diff(old, new)

    assert new == (old if patch is None else apply(old, json.loads(json.dumps(patch))))


def _catalog(n: int) -> dict[str, Any]:
    return {
        "registrar": "erm",
        "resources": [
            {"id": f"r{i}", "request": f"'/dev/video{i}'", "consumers": [{"query_id": f"q{i}"}]}
            for i in range(n)
        ],
    }


def test_one_more_consumer_of_10000_resources_is_a_patch_of_a_few_hundred_bytes() -> None:
    old = _catalog(10_000)
    new = _catalog(10_000)
    new["resources"][5000]["consumers"].append({"query_id": "another"})

    patch = diff(old, new)

    assert patch is not None
    assert len(json.dumps(patch)) < 300
    assert new == apply(old, patch)


def test_a_removed_row_goes_by_its_id_and_the_order_is_kept() -> None:
    old = _catalog(3)
    new = {**old, "resources": [old["resources"][0], old["resources"][2]]}

    patch = diff(old, new)

    assert {"d": {"resources": {"l": {}, "k": "id", "x": ["r1"], "i": []}}, "x": []} == patch


def test_a_row_added_in_the_middle_goes_with_its_place_not_the_whole_order() -> None:
    old = _catalog(1000)
    new = {**old, "resources": [*old["resources"][:500], {"id": "new"}, *old["resources"][500:]]}

    patch = diff(old, new)

    assert patch is not None
    assert {"l": {"new": {"v": {"id": "new"}}}, "k": "id", "x": [], "i": [[500, "new"]]} == (
        patch["d"]["resources"]
    )
    assert new == apply(old, patch)


def test_equal_values_need_no_patch() -> None:
    assert diff(_catalog(3), _catalog(3)) is None
