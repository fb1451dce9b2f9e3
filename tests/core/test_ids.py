"""Query ids: `new_id` gives what `str(uuid.uuid4())` gives, made faster."""

from __future__ import annotations

import uuid

from rr_actors._core.ids import new_id


def test_a_new_id_is_a_random_uuid4_in_its_canonical_form() -> None:
    ids = [new_id() for _ in range(2000)]

    for text in ids:
        parsed = uuid.UUID(text)
        assert (4, uuid.RFC_4122) == (parsed.version, parsed.variant)
        assert str(parsed) == text  # lower-case hex, dashes where uuid puts them
    assert len(set(ids)) == len(ids)
    assert {text[14] for text in ids} == {"4"}
    assert {text[19] for text in ids} == set("89ab")
