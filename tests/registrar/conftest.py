"""Fixtures of the registrar tests (the shared ones are in tests/conftest.py)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from rr_actors.testing import System


@pytest.fixture
def system() -> Iterator[System]:
    """A fresh AF_UNIX system (runtime directory + authkey) for manager processes; closed after."""
    made = System.create()
    yield made
    made.close()
