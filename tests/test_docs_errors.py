"""The errors reference is readable in its source: each error with its bases, when it is
raised and what to do, and not only the directive that renders the docstrings (issue 30)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

import rr_actors
from rr_actors import errors

PAGE = Path(__file__).resolve().parent.parent / "docs" / "reference" / "errors.md"
ERRORS = sorted(
    name
    for name in errors.__all__
    if isinstance(getattr(errors, name), type) and name != "ErrorFrame"
)


def entries() -> dict[str, tuple[str, str]]:
    """Each `**`Name`** (`Base`, ...). Text` entry of the page: name -> (bases, text)."""
    text = PAGE.read_text()
    found = re.findall(r"\*\*`(\w+)`\*\* \(([^)]*)\)\.(.*?)(?=\n\n)", text, re.DOTALL)
    return {name: (bases, body) for name, bases, body in found}


@pytest.mark.parametrize("name", ERRORS)
def test_every_error_has_an_entry_with_its_bases_and_what_to_do(name: str) -> None:
    bases, body = entries()[name]

    expected = [b.__name__ for b in getattr(errors, name).__bases__]
    assert expected == re.findall(r"`(\w+)`", bases)
    assert "*What to do:*" in body


@pytest.mark.parametrize("name", ERRORS)
def test_every_error_is_importable_from_rr_actors_as_the_page_says(name: str) -> None:
    """The page: "importable from `rr_actors` and from `rr_actors.errors`". `TransferError` and
    `InternalError` were not (issue 44 item 8)."""
    assert getattr(errors, name) is getattr(rr_actors, name, None)
    assert name in rr_actors.__all__


def test_the_page_draws_every_error_in_its_tree() -> None:
    tree = re.search(r"```text\n(.*?)```", PAGE.read_text(), re.DOTALL)

    assert tree is not None
    assert set(ERRORS) <= set(re.findall(r"\b(\w+Error)\b", tree[1]))
