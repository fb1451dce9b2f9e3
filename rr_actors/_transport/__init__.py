"""How registrar messages cross processes: the messenger and its carriers.

`messenger` (what every carrier does with a name and a message, written once), `codec`
(frames), `resolve` (rule 22's policy); the carriers `unix/` and `zenoh/` (extra).
"""

from rr_actors._transport.messenger import Address, Endpoint, Transport
from rr_actors._transport.unix.system import AttachedSystem, System, SystemAddress, attach

__all__ = [
    "Address",
    "AttachedSystem",
    "Endpoint",
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
