"""The AF_UNIX carrier: the registrars of one machine, over authenticated Unix sockets.

`system` (the carrier: `System`, `SystemAddress`, `attach`; the runtime directory's
files, who is lost: rule 19), `link` (a connection each way: the listener, a
`RemotePeer`'s channel, the authkey handshake, the writer that never blocks a sender).
"""
