"""The gated slow load: a load callback that says it started and waits on a gate.

Registrar tests hold a load (or many waiters of one load) at a known point this way. The
`gated_load` fixture (conftest) makes one from a `gates` gate and `shared` objects, so it
works in both placements; a test without `make_registrar` builds one from
`threading.Event`s.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


def same(request: Any) -> Any:
    """The response of a load that answers with its request."""
    return request


class GatedLoad:
    """The gated slow load: a `load` callback (or `respond` for `serve`) held at a gate.

    Each call records its request in `requests`, sets `started`, waits (at most `wait`
    seconds, then fails) until the test sets `gate`, and answers `respond(request)`
    (which may raise: a load that fails late). Make one with the `gated_load` fixture;
    build one by hand from `threading.Event`s where a test runs without `make_registrar`.
    """

    def __init__(
        self,
        gate: Any,
        started: Any,
        respond: Callable[[Any], Any] = same,
        *,
        wait: float = 10.0,
        requests: Any = None,
    ) -> None:
        self.gate = gate
        self.started = started
        self.respond = respond
        self.wait = wait
        self.requests = [] if requests is None else requests

    def __call__(self, request: Any) -> Any:
        self.requests.append(request)
        self.started.set()
        assert self.gate.wait(self.wait), "the gate of a gated load never opened"
        return self.respond(request)
