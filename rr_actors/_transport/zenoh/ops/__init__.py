"""The Zenoh carrier's operations: who may cross hosts, and what an operator sees of it.

`tls` (`ZenohTLS`: a host's certificates, checked with `cryptography`; an event batch's
`Seal`), `config` (a session's config: endpoints, TLS, the access control), `access`
(who else may read a private file), `watch` (who a router is linked to, and why a
`connect` endpoint is not: our own handshake), `gate` (a flood's gate on a `tls/` port,
and the members' addresses it never drops), `events` (every host's events on the
network, as JSON lines), `options` (the command line's network options). None of it
moves a registrar's message: that is the link's (`zenoh/`).
"""
