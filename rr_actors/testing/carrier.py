"""What a carrier's tests serve and send: the registrar side of the `Transport` surface.

A carrier (`rr_actors._transport`) carries registrar messages without knowing them; its
tests need a registrar to serve and messages to send. They take them from here, not from
the registrar's private modules (docs/explanation/architecture.md, "Tests"):

- `Served(registrar)`: a registrar of this process as a carrier serves it
  (`transport.serve(Served(registrar))`);
- `Fetch`, `Load`, `Revoke`: registrar messages, to send raw through a carrier.
"""

from __future__ import annotations

from rr_actors._registrar.life import Served
from rr_actors._registrar.messages import Fetch, Load, Revoke

__all__ = ["Fetch", "Load", "Revoke", "Served"]
