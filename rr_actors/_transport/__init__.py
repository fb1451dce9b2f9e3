"""How registrar messages cross processes: the messenger and its carriers.

- `messenger`: what every carrier does with a name and a message, written once
  (`Messenger`, the `Transport` the registrar sees; `Endpoint`, `Address`; what a carrier
  implements: `Carrier`, `Route`, `Listening`, `Remote`); `codec`: frames and pickling;
  `resolve`: which of two servers of one name is kept (rule 22);
- `unix/`, the AF_UNIX carrier; `zenoh/`, the Zenoh carrier (extra `zenoh`, imported
  only when used), its operations (TLS, access control, the gate) in `zenoh/ops/`.
"""

from rr_actors._transport.messenger import Address, Endpoint, Transport
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
