"""How registrar messages cross processes: the carrier interface and its carriers.

- `base`: the interface the registrar sees (`Transport`, `Address`, `Endpoint`) and the
  contract every carrier keeps;
- `codec`: frames and pickling; `messenger`: what every carrier does with a name and a
  message, written once (`Messenger`: the `Transport` surface, naming, replies, the
  stand-in reply, size limits, compensation, "send when served", the fan-out of what a
  carrier reports); what a carrier implements: `Carrier`, `Route`, `Listening`,
  `Remote` (the in-memory double, `rr_actors.testing.MemoryNetwork`, is the smallest);
- `unix/`, the AF_UNIX carrier: `system` (the carrier over a runtime directory: its
  files, `attach`, who is lost, rule 19) and `link` (a connection each way);
- `zenoh/`, the Zenoh carrier (extra `zenoh`, imported only when used): the link in
  `net`, `carrier`, `link`, `presence`, `wire`; its operations in `ops/` (TLS, the
  access control, the gate). The operator's tooling (`rr-actors certs`, the command
  line's network options) is `rr_actors._tools`; the event feed across hosts and the
  link watch, which run beside a session (`zenoh.net.Beside`), are the observer's
  (`rr_actors.observe._feed`).
"""

from rr_actors._transport.base import Address, Endpoint, Transport
from rr_actors._transport.unix.link import RemotePeer
from rr_actors._transport.unix.system import AttachedSystem, System, SystemAddress, attach

__all__ = [
    "Address",
    "AttachedSystem",
    "Endpoint",
    "RemotePeer",
    "System",
    "SystemAddress",
    "Transport",
    "attach",
]

if __debug__:  # mypy checks that the AF_UNIX carrier implements the interface
    from typing import TYPE_CHECKING

    if TYPE_CHECKING:
        _transport: type[Transport] = AttachedSystem
        _address: type[Address] = SystemAddress
