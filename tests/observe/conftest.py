"""Fixtures of the observer's tests: figure 2.7's tree, and for the browser tests one headless
chromium per module, a tab each."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
import zenoh

import rr_actors as rr
from tests.support import hosts
from tests.support.observed_tree import figure_27
from tests.support.observing import headless_chromium


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """A headless chromium for the module's tests (its own fresh profile)."""
    with headless_chromium() as context:
        yield context


@pytest.fixture
def page(browser: Any) -> Iterator[Any]:
    """A new tab; fails the test if the page logs an error."""
    tab = browser.new_page()
    errors: list[str] = []
    tab.on("pageerror", lambda exc: errors.append(str(exc)))
    tab.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    yield tab
    if not tab.is_closed():
        tab.close()
    assert [] == errors


@pytest.fixture
def tabs(browser: Any) -> Iterator[Any]:
    """`tabs()` opens a new tab; every tab is closed at the end, and none may log an error."""
    opened: list[Any] = []
    errors: list[str] = []

    def new() -> Any:
        tab = browser.new_page()
        tab.on("pageerror", lambda exc: errors.append(str(exc)))
        tab.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        opened.append(tab)
        return tab

    yield new
    for tab in opened:
        tab.close()
    assert [] == errors


@pytest.fixture
def tree(supervisors: Any, process_helpers: Any) -> rr.Supervisor:
    """Figure 2.7's managers in processes, started; stopped at teardown."""
    return figure_27(supervisors).start()


@pytest.fixture
def sessions() -> Iterator[tuple[zenoh.Session, zenoh.Session]]:
    """Two plain Zenoh sessions on loopback, the second connected to the first."""
    port = hosts.free_port()
    one = zenoh.open(hosts.zenoh_config(listen=[f"tcp/127.0.0.1:{port}"]))
    other = zenoh.open(hosts.zenoh_config(connect=[f"tcp/127.0.0.1:{port}"]))
    yield one, other
    other.close()  # type: ignore[no-untyped-call]
    one.close()  # type: ignore[no-untyped-call]
