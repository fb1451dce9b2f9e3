"""How registrar messages cross processes: the carrier interface and its carriers.

- `base`: the interface (`Transport`, `Address`, `Endpoint`) and the contract every
  carrier keeps;
- `codec`: frames and pickling; `messenger`: what every carrier does with a message, an
  answer, a reply waiting and a registrar lost, written once; it drives a carrier
  through a `Route` per registrar reached and a `Link` per process (the in-memory
  double, `rr_actors.testing.MemoryNetwork`, is the smallest carrier);
- `unix/`, the AF_UNIX carrier: `system` (the system: runtime directory, authkey,
  `attach`), `sockets` (connect and the authkey handshake), `outbound` (a channel to
  another process's registrar), `inbound` (a registrar's listener), `writer` (sending
  without blocking on the peer, on a `_core.serial.SerialExecutor`), `rendezvous` (what
  its channels need of the system, and how it finds a registrar lost for good);
- `zenoh/`, the Zenoh carrier (extra `zenoh`, imported only when used): `net`
  (`ZenohNetwork`: the router per host and its config), `carrier` (a process's
  membership: the Transport surface, sending), `outbox` (writer threads), `inbox`
  (decode threads, delivery, answers), `presence` (liveliness tokens; each thread a
  `_core.serial.SerialExecutor`), `wire` (key expressions and header), `tls` (`ZenohTLS`:
  a host's certificates and the system's members, checked with `cryptography`),
  `config`, `watch`, `probe`, `gate` (the session's config, who links, why not, a
  flood's gate), `access` (who else may read a key), `options` (the Zenoh options a
  command line shares), `events` (every host's events on the network). The operator's
  tooling (`rr-actors certs`) is `rr_actors._tools.certs`, not a carrier's.
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
