"""The Zenoh carrier's operations: who may cross hosts (TLS, the access control, the gate).

`tls` (`ZenohTLS`: a host's certificates, checked with `cryptography`), `config` (a
session's config: endpoints, TLS, the access control), `access` (who else may read a
private file), `gate` (a flood's gate on a `tls/` port, and the members' addresses it
never drops). None of it moves a registrar's message: that is the link's (`zenoh/`).
What an operator sees (who a router is linked to, every host's events and their seals)
is the observer's, run beside a session (`rr_actors.observe._links`, `_feed`, `_seal`).
"""
