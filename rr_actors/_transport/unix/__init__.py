"""The AF_UNIX carrier: the registrars of one machine, over authenticated Unix sockets.

`system` (`System`, `SystemAddress`, `attach`: a process's membership), `inbound` (a
registrar's listener), `outbound` (`RemotePeer`: a channel to another process's
registrar), `writer` (sending without blocking on the peer), `sockets` (connect and the
authkey handshake), `rendezvous` (what the channels need of the system; rule 19 here).
"""
