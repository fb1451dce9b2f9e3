"""How registrar messages cross processes: the carrier interface and its carriers.

- `base`: the interface (`Transport`, `Address`, `Endpoint`) and the contract every
  carrier keeps;
- `codec`: frames and pickling; `writer`: sending without blocking on the peer;
- the AF_UNIX carrier: `sockets` (connect and the authkey handshake), `outbound` (a
  channel to another process's registrar), `inbound` (a registrar's listener), `unix`
  (the system: runtime directory, authkey, `attach`);
- the Zenoh carrier (extra `zenoh`, imported only when used): `zenoh_net`
  (`ZenohNetwork`: the router per host and its config), `zenoh_carrier` (a process's
  membership: the Transport surface, sending), `zenoh_outbox` (writer threads),
  `zenoh_inbox` (decode threads, delivery, answers), `zenoh_presence` (liveliness
  tokens; each thread a `_core.serial.SerialExecutor`), `zenoh_wire` (key expressions
  and header); `zenoh_tls` (`ZenohTLS`: a host's certificates and the system's members,
  checked with `cryptography`) and `zenoh_certs` (`rr-actors certs`: a CA, a host's
  certificate).
"""

from rr_actors._transport.base import Address, Endpoint, Transport
from rr_actors._transport.outbound import RemotePeer
from rr_actors._transport.unix import AttachedSystem, System, SystemAddress, attach

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
